"""Shared helpers for the CLI and cache tests (tests/test_cli.py, tests/test_cache.py).

Every test works on a private copy of the bundled sample scene (sample_data/spot_sun) in tmp_path;
nothing outside the repository is read.
"""

from __future__ import annotations

import hashlib
import re
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
from click.testing import CliRunner

from wavelight_cli.main import cli

REPO = Path(__file__).resolve().parents[1]
SAMPLE = REPO / "sample_data" / "spot_sun"
RES = "8"  # light resolution for fast runs (3 * 8^2 = 192 directions)
VIS_STAGE = f"visibility/photo/R{RES}"  # the photo view's visibility at RES (the cache's stage name)
VIS_H5 = f".wavelight/visibility/photo-R{RES}.h5"  # ... and its file


def vis_stage(resolution=RES, slot: str = "") -> str:
    """The cache's name of the photo view's visibility at a resolution (`slot`: more options, e.g. "-exact")."""
    return f"visibility/photo/R{resolution}{slot}"


def vis_file(scene: Path, resolution=RES, slot: str = "") -> Path:
    return scene / ".wavelight" / "visibility" / f"photo-R{resolution}{slot}.h5"


def wavelight_exe() -> str:
    """The installed console script of this venv (a real process, for kill/lock tests)."""
    exe = Path(sys.executable).parent / "wavelight"
    if exe.is_file():
        return str(exe)
    found = shutil.which("wavelight")
    assert found, "the wavelight console script is not installed"
    return found


def copy_sample(dst: Path, calibrated: bool = True) -> Path:
    """A fresh copy of the sample scene (without any cache or results it may carry).

    calibrated: put the true camera.json and pose.json (truth/) in the scene folder, as if calibrate
    and register had run exactly; False leaves them out (the demo's starting point)."""
    shutil.copytree(SAMPLE, dst, ignore=shutil.ignore_patterns(".wavelight", "out", "scene.toml"))
    if calibrated:
        for name in ("camera.json", "pose.json"):
            shutil.copy(dst / "truth" / name, dst / name)
    return dst


def copy_scene(src: Path, dst: Path) -> Path:
    """Copy a scene including its cache and results (file times preserved)."""
    shutil.copytree(src, dst, copy_function=shutil.copy2)
    return dst


def invoke(scene: Path, *args: str, quiet: bool = False):
    """Run `wavelight -s scene args...` in process; returns click's Result (stdout/stderr separate)."""
    argv = ["-s", str(scene)] + (["-q"] if quiet else []) + [str(a) for a in args]
    return CliRunner().invoke(cli, argv, catch_exceptions=True)


def ok(result) -> str:
    """Assert a clean exit and return stderr (where the progress lines go)."""
    assert result.exit_code == 0, (
        f"exit {result.exit_code}\nstdout:\n{result.stdout}\nstderr:\n{result.stderr}\n"
        f"exception: {result.exception!r}")
    return result.stderr


def run_proc(scene: Path, *args: str, timeout: float = 300.0) -> subprocess.CompletedProcess:
    return subprocess.run([wavelight_exe(), "-s", str(scene), *map(str, args)], capture_output=True,
                          text=True, timeout=timeout)


def render_args(scene: Path, *extra: str, res: str = RES) -> list[str]:
    return ["render", "--resolution", res, "--light", str(scene / "truth" / "env_latlong.exr"),
            "--material", str(scene / "truth" / "material.json"), *extra]


def stage_lines(text: str, stage: str) -> list[str]:
    return [line for line in text.splitlines() if line.startswith(f"{stage}: ")]


def decision_line(text: str, stage: str) -> str:
    """The one `stage: running (...)` / `stage: skipped, ...` / `stage: redrawing the previews (...)`
    line of a run."""
    lines = [ln for ln in stage_lines(text, stage)
             if ln.startswith((f"{stage}: running (", f"{stage}: skipped, ", f"{stage}: redrawing the previews ("))]
    assert len(lines) == 1, f"expected one decision line for {stage}, got {lines}\n{text}"
    return lines[0]


def snapshot(scene: Path) -> dict[str, tuple[bytes, int]]:
    """Every file under .wavelight/ and out/ with its bytes and mtime.

    The lock file is left out: it is the scene's mutex (every run rewrites the holder's pid in
    it), not cached data.
    """
    snap = {}
    for sub in (".wavelight", "out"):
        root = scene / sub
        if not root.exists():
            continue
        for p in sorted(root.rglob("*")):
            rel = p.relative_to(scene).as_posix()
            if rel == ".wavelight/lock":
                continue
            if p.is_dir():
                snap[rel + "/"] = (b"", 0)
            else:
                snap[rel] = (p.read_bytes(), p.stat().st_mtime_ns)
    return snap


def manifest(scene: Path) -> dict:
    return json.loads((scene / ".wavelight" / "manifest.json").read_text())


def sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def h5_arrays(path: Path) -> dict[str, tuple[str, tuple, bytes]]:
    """Every dataset of an HDF5 file as (dtype, shape, raw bytes): equality is bit-identity."""
    import h5py

    out = {}
    with h5py.File(path, "r") as f:
        def visit(name, obj):
            if isinstance(obj, h5py.Dataset):
                arr = np.ascontiguousarray(obj[()])
                out[name] = (arr.dtype.str, arr.shape, arr.tobytes())
        f.visititems(visit)
    return out


def rotate_pose(scene: Path, angle: float = 1e-3) -> None:
    """Turn the camera by a tiny rotation about the world z axis (R stays orthonormal)."""
    path = scene / "pose.json"
    pose = json.loads(path.read_text())
    c, s = np.cos(angle), np.sin(angle)
    rz = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    pose["R"] = (np.asarray(pose["R"]) @ rz).tolist()
    path.write_text(json.dumps(pose, indent=1))


_BASELINE: dict[str, Path] = {}


def baseline_scene(tmp_path_factory) -> Path:
    """A sample copy after one successful `visibility` and `render` at R=8 (made once per session).

    Tests must copy it (copy_scene) before changing anything.
    """
    if "scene" not in _BASELINE:
        scene = copy_sample(tmp_path_factory.mktemp("baseline") / "scene")
        ok(invoke(scene, "visibility", "--resolution", RES))
        ok(invoke(scene, *render_args(scene)))
        assert vis_file(scene).is_file()
        assert (scene / "out" / "render.exr").is_file()
        _BASELINE["scene"] = scene
    return _BASELINE["scene"]


def assert_one_error_line(result, culprit: str, quiet: bool, code: int | None = None) -> str:
    """A failed command: exit 1 (exit 2, a usage error, when `culprit` is an option: `--name`;
    `code` overrides), no traceback, exactly one `Error:` line, last on stderr, naming `culprit`;
    with -q nothing else printed, otherwise only `stage: ...` progress before it."""
    code = code if code is not None else 2 if culprit.startswith("--") else 1
    assert result.exit_code == code, (result.exit_code, result.output)
    # Anything but SystemExit means an exception escaped the CLI (a traceback for a real user).
    assert isinstance(result.exception, SystemExit), repr(result.exception)
    assert "Traceback" not in result.output
    err = result.stderr.splitlines()
    errors = [ln for ln in err if ln.startswith("Error:")]
    assert len(errors) == 1, result.stderr
    line = errors[0]
    assert err[-1] == line, f"the error must be the last line on stderr:\n{result.stderr}"
    if quiet:
        assert err == [line], f"with -q only the error line may be printed:\n{result.stderr}"
        assert result.stdout == "", f"a failed run printed results:\n{result.stdout}"
    else:  # the other lines are the stages' progress (`stage: ...`)
        assert all(re.match(r"^[a-z][A-Za-z0-9/_-]*: ", ln) for ln in err[:-1]), result.stderr
    assert culprit in line, f"the error must name {culprit!r}: {line}"
    assert "\n" not in line
    return line


FILE_SUFFIXES = (".exr", ".json", ".png", ".obj", ".ply", ".csv", ".h5")


def check_bad_input(source: Path, tmp_path: Path, mutate, args, culprit: str) -> str:
    """On a copy of `source`: apply `mutate` (or None), run `args` (arguments that name files are
    taken relative to the copy), and assert one error line naming `culprit` (a file name or an
    option), with `.wavelight/` and `out/` left exactly as they were. Returns the error line."""
    scene = copy_scene(source, tmp_path / "bad")
    if mutate:
        mutate(scene)
    argv = [str(scene / a) if a.endswith(FILE_SUFFIXES) and not a.startswith("-") else a for a in args]
    before = snapshot(scene)
    line = assert_one_error_line(invoke(scene, *argv), culprit, quiet=False)
    assert snapshot(scene) == before, f"a failed run changed the cache or the results: {line}"
    return line


def kill_when(proc: subprocess.Popen, ready, timeout: float, poll: float = 0.01) -> None:
    """SIGKILL `proc` as soon as `ready()` is true (checked every `poll` s, up to `timeout` s) unless
    it has ended by then; the process is always reaped."""
    try:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline and proc.poll() is None and not ready():
            time.sleep(poll)
        if proc.poll() is None:
            os.kill(proc.pid, signal.SIGKILL)
        proc.wait(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
