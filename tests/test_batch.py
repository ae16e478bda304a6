"""`make batch` (Makefile): wavelight over several scene folders, one make target per scene.

Real processes: `make -j2 batch` in the repository, on private copies of the sample scene in
tmp_path. The batch target does not depend on the venv's install stamp; the tests pass
WAVELIGHT= the console script of the interpreter running them, so make never runs pip.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import time
from pathlib import Path

import pytest

from cli_helpers import (RES, copy_sample, h5_arrays, manifest, sha256, wavelight_exe, VIS_STAGE)
REPO = Path(__file__).resolve().parents[1]

pytestmark = pytest.mark.skipif(shutil.which("make") is None, reason="needs GNU make")


def make_batch(scenes: list[Path], batch: Path, *extra: str, timeout: float = 600.0,
               **popen) -> subprocess.CompletedProcess | subprocess.Popen:
    """`make -j2 batch SCENES=... BATCH=... R=8` in the repository (or a Popen with popen=...)."""
    cmd = ["make", "--no-print-directory", "-j2", "batch", "SCENES=" + " ".join(map(str, scenes)),
           f"BATCH={batch}", f"R={RES}", f"WAVELIGHT={wavelight_exe()}", *extra]
    env = {k: v for k, v in os.environ.items() if k not in ("MAKEFLAGS", "MFLAGS", "MAKELEVEL")}
    if popen:
        return subprocess.Popen(cmd, cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                text=True, **popen)
    return subprocess.run(cmd, cwd=REPO, env=env, capture_output=True, text=True, timeout=timeout)


def markers(batch: Path, suffix: str) -> dict[str, Path]:
    """{scene path (first line of the marker): marker file} for every $(BATCH)/*.<suffix>."""
    return {p.read_text().splitlines()[0]: p for p in sorted(batch.glob(f"*.{suffix}"))}


def log_of(marker: Path) -> str:
    return marker.with_suffix(".log").read_text()


def good_scenes(root: Path) -> list[Path]:
    """Two copies of the sample scene with the same folder name (their logs must not collide)."""
    return [copy_sample(root / "good_a" / "scene"), copy_sample(root / "good_b" / "scene")]


def broken_scene(root: Path) -> Path:
    scene = copy_sample(root / "broken" / "scene")
    camera = json.loads((scene / "camera.json").read_text())
    camera["fx"] = -1
    (scene / "camera.json").write_text(json.dumps(camera))
    return scene


def assert_solved(scene: Path) -> None:
    assert (scene / "out" / "solve_report.json").is_file(), scene
    assert (scene / "out" / "report.md").is_file(), scene


@pytest.fixture(scope="module")
def solved_batch(tmp_path_factory):
    """A batch of two good scenes, run once: (scenes, batch folder, make's result). Read-only."""
    root = tmp_path_factory.mktemp("solved_batch")
    scenes = good_scenes(root)
    batch = root / "batch"
    return scenes, batch, make_batch(scenes, batch)


def test_batch_broken_scene_does_not_stop_the_others(tmp_path):
    good = good_scenes(tmp_path)
    broken = broken_scene(tmp_path)
    batch = tmp_path / "batch"
    # the broken scene in the middle: make must go on with the one after it, without -k
    result = make_batch([good[0], broken, good[1]], batch)
    out = result.stdout + result.stderr
    assert result.returncode != 0, out
    assert "pip install" not in out, "the batch must not (re)install the venv"

    for scene in good:
        assert_solved(scene)
    ok_markers, failed = markers(batch, "ok"), markers(batch, "failed")
    assert set(ok_markers) == {str(s) for s in good}, out
    assert set(failed) == {str(broken)}, out
    assert len({p.name for p in batch.glob("*.log")}) == 3, "scenes named alike share a log"

    lines = failed[str(broken)].read_text().splitlines()
    assert lines[0] == str(broken)
    assert lines[1].startswith("Error:") and "camera.json" in lines[1] and "fx" in lines[1], lines
    assert lines[1] == [ln for ln in log_of(failed[str(broken)]).splitlines() if ln.startswith("Error:")][-1]
    assert not (broken / "out" / "solve_report.json").exists()

    # the summary: one line per scene, the broken one named with its error, and why make failed
    summary = (batch / "summary.txt").read_text().splitlines()
    assert summary == [f"ok      {good[0]}", f"FAILED  {broken}: {lines[1]}", f"ok      {good[1]}"], summary
    assert f"FAILED  {broken}: {lines[1]}" in result.stdout
    assert f"1 of 3 scenes failed: {broken}" in result.stdout
    for log in batch.glob("*.log"):
        assert "Traceback" not in log.read_text(), log
    assert "Traceback" not in out


def test_batch_rerun_skips_finished_stages(solved_batch):
    scenes, batch, first = solved_batch
    assert first.returncode == 0, first.stdout + first.stderr
    for scene in scenes:
        assert_solved(scene)
    assert set(markers(batch, "ok")) == {str(s) for s in scenes}
    assert not list(batch.glob("*.failed"))
    before = {s: (sha256(s / "out" / "coefficients.h5"), manifest(s)) for s in scenes}

    again = make_batch(scenes, batch)
    assert again.returncode == 0, again.stdout + again.stderr
    assert "all 2 scenes ok" in again.stdout
    ok_markers = markers(batch, "ok")
    assert set(ok_markers) == {str(s) for s in scenes}
    for scene in scenes:
        log = log_of(ok_markers[str(scene)])  # the logs keep the stage lines (no -q)
        assert f"{VIS_STAGE}: skipped, up to date" in log, log
        assert "solve: skipped, up to date" in log, log
        assert "Traceback" not in log
        assert (sha256(scene / "out" / "coefficients.h5"), manifest(scene)) == before[scene]
        assert_solved(scene)


def test_batch_resumes_after_interrupt(tmp_path, solved_batch):
    """Ctrl-C (SIGINT to make's process group) mid-visibility, then the same command again."""
    scene = copy_sample(tmp_path / "scene")
    batch = tmp_path / "batch"
    # Ctrl-C must reach make and wavelight even when this test runs in the background (a
    # non-interactive shell starts background jobs with SIGINT ignored, and children inherit that)
    exact = "WAVELIGHT_ARGS=--visibility exact"  # the exact method runs in resumable chunks
    stage = f"{VIS_STAGE}-exact"
    proc = make_batch([scene], batch, exact, start_new_session=True,
                      preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    try:
        deadline = time.monotonic() + 120
        logs = []
        while time.monotonic() < deadline and proc.poll() is None:
            logs = list(batch.glob("*.log"))  # a progress line: at least one chunk is on disk
            if logs and f"{stage}: casting [" in logs[0].read_text():
                break
            time.sleep(0.02)
        assert proc.poll() is None, "the batch ended before it could be interrupted"
        os.killpg(proc.pid, signal.SIGINT)
        out, _ = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    assert proc.returncode != 0, out
    assert not list(batch.glob("*.ok")), "an interrupted scene must not be marked done"
    assert not (batch / "summary.txt").exists()

    again = make_batch([scene], batch, exact)
    assert again.returncode == 0, again.stdout + again.stderr
    (marker,) = markers(batch, "ok").values()
    log = log_of(marker)
    assert f"{stage}: resuming" in log or f"{stage}: skipped, up to date" in log, log
    assert "Traceback" not in log
    assert_solved(scene)
    # no damage: the same numbers as an uninterrupted run of the same command
    reference = copy_sample(tmp_path / "reference")
    assert make_batch([reference], tmp_path / "reference_batch", exact).returncode == 0
    for rel in (".wavelight/visibility/photo-R8-exact.h5", "out/coefficients.h5"):
        assert h5_arrays(scene / rel) == h5_arrays(reference / rel), rel
