"""out/report.html in a real browser: headless Chromium (Debian's /usr/bin/chromium; .ci/run installs
it) loads the page, and the test asserts that it loads, that every <img> decoded (naturalWidth > 0),
that nothing was fetched but the page itself and data: URIs, that the console stayed free of errors,
that the photo / relit slider moves, and that a screenshot has the size asked for and is not blank.

The browser is driven over the DevTools protocol through `--remote-debugging-pipe` (NUL-separated
JSON on file descriptors 3 and 4), with the standard library only. The screenshots are saved in
build/report-browser/ (or $WAVELIGHT_SCREENSHOT_DIR) and their paths printed (pytest -s shows them).
"""

from __future__ import annotations

import base64
import json
import os
import select
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest

from cli_helpers import REPO

CHROMIUM = os.environ.get("WAVELIGHT_CHROMIUM", "/usr/bin/chromium")
FLAGS = ("--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
         "--disable-background-networking", "--disable-component-update", "--disable-sync",
         "--disable-extensions", "--disable-default-apps", "--hide-scrollbars", "--mute-audio",
         "--remote-debugging-pipe")
VIEWPORT = (1280, 900)


def _high(fd: int) -> int:
    """`fd` moved to a number >= 10."""
    import fcntl

    high = fcntl.fcntl(fd, fcntl.F_DUPFD, 10)
    os.close(fd)
    return high


class Browser:
    """Chromium over the DevTools pipe: `call(method, **params)` on the page's session; the events
    that arrive meanwhile are kept in `events`."""

    def __init__(self, profile: Path, timeout: float = 60.0):
        self.timeout = timeout
        to_child_r, self._w = os.pipe()
        self._r, from_child_w = os.pipe()
        to_child_r, from_child_w = (_high(fd) for fd in (to_child_r, from_child_w))  # clear of 3 and 4
        # the child reads commands on fd 3 and writes replies on fd 4: bash moves the pipes there (dash takes one-digit fds only)
        move = f'exec "$0" "$@" 3<&{to_child_r} 4>&{from_child_w} {to_child_r}<&- {from_child_w}>&-'
        self._log = open(profile.parent / "chromium-stderr.log", "wb")
        self.proc = subprocess.Popen(["/bin/bash", "-c", move, CHROMIUM, *FLAGS, f"--user-data-dir={profile}",
                                      "about:blank"],
                                     stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                                     stderr=self._log,
                                     pass_fds=(to_child_r, from_child_w))
        os.close(to_child_r)
        os.close(from_child_w)
        self._buf = b""
        self._id = 0
        self.events: list[dict] = []
        self.session = None
        try:
            target = self.call("Target.createTarget", url="about:blank")["targetId"]
            self.session = self.call("Target.attachToTarget", targetId=target, flatten=True)["sessionId"]
        except BaseException:
            self.close()
            raise

    def _send(self, message: dict) -> None:
        data = json.dumps(message).encode() + b"\0"
        while data:
            data = data[os.write(self._w, data):]

    def _receive(self, deadline: float) -> dict:
        while b"\0" not in self._buf:
            left = deadline - time.monotonic()
            if left <= 0:
                raise TimeoutError("no answer from Chromium")
            ready, _, _ = select.select([self._r], [], [], left)
            if ready:
                chunk = os.read(self._r, 1 << 20)
                if not chunk:
                    raise RuntimeError(f"Chromium closed the pipe (exit {self.proc.poll()})")
                self._buf += chunk
        raw, self._buf = self._buf.split(b"\0", 1)
        return json.loads(raw)

    def call(self, method: str, **params):
        self._id += 1
        msg = {"id": self._id, "method": method, "params": params}
        if self.session is not None and not method.startswith("Target."):
            msg["sessionId"] = self.session
        self._send(msg)
        deadline = time.monotonic() + self.timeout
        while True:
            reply = self._receive(deadline)
            if reply.get("id") == self._id:
                if "error" in reply:
                    raise RuntimeError(f"{method}: {reply['error']}")
                return reply.get("result", {})
            if "method" in reply:
                self.events.append(reply)

    def wait_for(self, event: str, timeout: float | None = None) -> dict:
        deadline = time.monotonic() + (timeout or self.timeout)
        for e in self.events:
            if e["method"] == event:
                return e
        while True:
            e = self._receive(deadline)
            if "method" in e:
                self.events.append(e)
                if e["method"] == event:
                    return e

    def evaluate(self, expression: str):
        r = self.call("Runtime.evaluate", expression=expression, returnByValue=True, awaitPromise=True)
        if "exceptionDetails" in r:
            raise RuntimeError(f"{expression}: {r['exceptionDetails']}")
        return r["result"].get("value")

    def screenshot(self, path: Path, width: int, height: int) -> Path:
        self.call("Emulation.setDeviceMetricsOverride", width=width, height=height, deviceScaleFactor=1, mobile=False)
        shot = self.call("Page.captureScreenshot", format="png", captureBeyondViewport=False)
        path.write_bytes(base64.b64decode(shot["data"]))
        return path

    def close(self) -> None:
        try:
            self.call("Browser.close")
        except (RuntimeError, TimeoutError, OSError):
            pass
        try:
            self.proc.wait(timeout=20)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
        for fd in (self._r, self._w):
            try:
                os.close(fd)
            except OSError:
                pass
        self._log.close()


def _chromium_or_skip():
    if not (Path(CHROMIUM).is_file() and os.access(CHROMIUM, os.X_OK)):
        if os.environ.get("CI"):
            pytest.fail(f"{CHROMIUM} is missing: .ci/run installs Debian's chromium")
        pytest.skip(f"{CHROMIUM} not installed (apt-get install chromium)")


@pytest.fixture(scope="module")
def page(tmp_path_factory, lambert_solved):
    """The sample scene's report.html (test_report's scene: solve, compare, relights, insert, export)
    loaded in Chromium: (browser, scene, folder of the browser's files)."""
    from test_report import reported_scene

    _chromium_or_skip()
    scene = reported_scene(tmp_path_factory, lambert_solved)
    root = tmp_path_factory.mktemp("report_browser")
    html = scene / "out" / "report.html"
    browser = Browser(root / "profile")
    try:
        for domain in ("Page", "Runtime", "Log", "Network"):
            browser.call(f"{domain}.enable")
        browser.call("Emulation.setDeviceMetricsOverride", width=VIEWPORT[0], height=VIEWPORT[1],
                     deviceScaleFactor=1, mobile=False)
        t0 = time.monotonic()
        browser.call("Page.navigate", url=html.as_uri())
        browser.wait_for("Page.loadEventFired")
        browser.load_seconds = time.monotonic() - t0
        yield browser, scene, root
    finally:
        browser.close()


def test_page_loads_with_every_image(page):
    browser, scene, _ = page
    state = browser.evaluate("""(() => {
        const imgs = Array.from(document.images);
        return {ready: document.readyState, title: document.title, count: imgs.length,
                broken: imgs.filter(i => !(i.complete && i.naturalWidth > 0)).map(i => i.alt),
                external: imgs.filter(i => !i.src.startsWith('data:')).map(i => i.src.slice(0, 80)),
                sections: Array.from(document.querySelectorAll('section h2')).map(h => h.textContent)};
    })()""")
    assert state["ready"] == "complete"
    assert state["title"] == f"wavelight report: {scene.name}"
    assert state["broken"] == [], f"images that did not load: {state['broken']}"
    assert state["external"] == []
    # overview, slider (2), light, levels, compare (2), turned, same + residual, insert + shadow
    assert state["count"] >= 12, state
    for title in ("Result", "Recovered light", "Refinement, level by level", "Reflectance", "The bases side by side",
                  "Relighting and insertion", "Exports"):
        assert title in state["sections"]


def test_nothing_is_fetched_but_the_page(page):
    browser, scene, _ = page
    urls = [e["params"]["request"]["url"] for e in browser.events if e["method"] == "Network.requestWillBeSent"]
    page_url = (scene / "out" / "report.html").as_uri()
    assert page_url in urls
    assert all(u == page_url or u.startswith("data:") for u in urls), [u[:80] for u in urls]
    failed = [e["params"] for e in browser.events if e["method"] == "Network.loadingFailed"]
    assert failed == []


def test_no_console_errors(page):
    browser, _, _ = page
    browser.evaluate("new Promise(r => setTimeout(r, 200))")  # let late messages arrive
    errors = [e["params"] for e in browser.events if e["method"] == "Runtime.exceptionThrown"]
    errors += [e["params"] for e in browser.events
               if e["method"] == "Runtime.consoleAPICalled" and e["params"]["type"] in ("error", "assert", "warning")]
    errors += [e["params"]["entry"] for e in browser.events
               if e["method"] == "Log.entryAdded" and e["params"]["entry"]["level"] in ("error", "warning")]
    assert errors == []


def test_the_slider_moves_the_split(page):
    browser, _, _ = page
    clip = browser.evaluate("""(() => {
        const fig = document.querySelector('figure.slider');
        const range = fig.querySelector('input[type=range]'), over = fig.querySelector('img.over');
        const before = over.style.clipPath;
        range.value = 20; range.dispatchEvent(new Event('input'));
        const moved = over.style.clipPath;
        fig.querySelector('button').click();
        const toggled = over.style.clipPath;
        range.value = 50; range.dispatchEvent(new Event('input'));
        return [before, moved, toggled];
    })()""")
    assert clip == ["inset(0px 0px 0px 50%)", "inset(0px 0px 0px 20%)", "inset(0px 0px 0px 100%)"]


def _png_pixels(path: Path) -> np.ndarray:
    import cv2

    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    assert img is not None, path
    return img


def test_screenshots_have_the_size_asked_for_and_are_not_blank(page):
    browser, _, _ = page
    shots = Path(os.environ.get("WAVELIGHT_SCREENSHOT_DIR", REPO / "build" / "report-browser"))
    shots.mkdir(parents=True, exist_ok=True)
    shot = browser.screenshot(shots / "report-viewport.png", *VIEWPORT)
    px = _png_pixels(shot)
    assert px.shape == (VIEWPORT[1], VIEWPORT[0], 3)
    grey = px.mean(axis=2)
    assert grey.std() > 20, f"a blank screenshot (std {grey.std():.1f})"
    assert (grey < 128).mean() > 0.02 and (grey > 128).mean() > 0.2  # text and figures on a white page
    assert len(np.unique(px.reshape(-1, 3) // 16, axis=0)) > 50  # colours: the images are drawn
    height = int(browser.evaluate("Math.ceil(document.documentElement.scrollHeight)"))
    assert height > 3 * VIEWPORT[1]  # the whole report, not a stub
    full = browser.screenshot(shots / "report-full.png", VIEWPORT[0], height)
    whole = _png_pixels(full)
    assert whole.shape == (height, VIEWPORT[0], 3)
    band = whole[: height // 4 * 4].reshape(4, height // 4, VIEWPORT[0], 3)
    assert all(b.std() > 20 for b in band), "a quarter of the page is blank"
    print(f"\nscreenshots: {shot} ({VIEWPORT[0]}x{VIEWPORT[1]}), {full} ({VIEWPORT[0]}x{height}); "
          f"page loaded in {browser.load_seconds:.2f} s")
