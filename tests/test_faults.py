"""Faults: a full disk, a killed solve, a cache from another version, temp files left by a crash.

The cache's own faults (killed visibility, damaged HDF5 files, garbage manifests, two runs at
once) are in test_cache.py; this file covers what happens around a stage's outputs.
"""

from __future__ import annotations

import errno
import json
import os
import re
import signal
import subprocess
from pathlib import Path

import numpy as np
import pytest

from cli_helpers import (RES, assert_one_error_line, copy_sample, copy_scene, decision_line, h5_arrays, invoke, kill_when, manifest, ok, run_proc, snapshot, vis_file, vis_stage, wavelight_exe, VIS_H5, VIS_STAGE)
from pipelines.io import images
from pipelines.io.files import atomic_output, is_temporary, output_set

SOLVE = ["solve", "--resolution", RES, "--reflectance", "lambert"]


def temporaries(scene: Path) -> list[Path]:
    return [p for p in scene.rglob(".*") if p.is_file() and is_temporary(p.name)]


def solved_data(scene: Path) -> dict:
    """The solve's numbers, bit for bit: the light and relit pixels and the coefficient file's
    datasets (file bytes differ between runs by their time stamps, not their data)."""
    out = scene / "out"
    return {"light": images.read_latlong(out / "light_latlong.exr").tobytes(),
            "relit": images.read_image(out / "relit.exr").pixels.tobytes(),
            "coefficients": h5_arrays(out / "coefficients.h5")}


# -- the output set --------------------------------------------------------------------------
def test_output_set_replaces_all_files_or_none(tmp_path):
    a, b = tmp_path / "a.txt", tmp_path / "b.txt"
    a.write_text("old a")
    b.write_text("old b")
    with pytest.raises(OSError):
        with output_set():
            with atomic_output(a) as tmp:
                tmp.write_text("new a")
            assert a.read_text() == "old a"  # not yet: the set is not finished
            with atomic_output(b) as tmp:
                raise OSError(errno.ENOSPC, "No space left on device")
    assert (a.read_text(), b.read_text()) == ("old a", "old b")
    assert temporaries(tmp_path) == []
    with output_set():
        for p in (a, b):
            with atomic_output(p) as tmp:
                tmp.write_text("new " + p.stem)
    assert (a.read_text(), b.read_text()) == ("new a", "new b")
    assert temporaries(tmp_path) == []


def test_disk_full_during_solve_keeps_old_results(lambert_solved, tmp_path, monkeypatch):
    """A write that fails halfway through the solve's outputs (ENOSPC on the 6th file) leaves every
    earlier result and the manifest as they were, no temp file, and one error line naming the file."""
    scene = copy_scene(lambert_solved, tmp_path / "scene")
    before = snapshot(scene)
    real = images.write_exr
    calls = []

    def failing(path, *args, **kwargs):
        calls.append(Path(path).name)
        if len(calls) == 3:  # light_latlong.exr and light_cross.exr are written, then relit.exr fails
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(path))
        return real(path, *args, **kwargs)

    monkeypatch.setattr(images, "write_exr", failing)
    result = invoke(scene, *SOLVE, "--force")
    line = assert_one_error_line(result, "relit.exr", quiet=False)
    assert "no space left on device" in line and "Free some disk space" in line
    assert calls == ["light_latlong.exr", "light_cross.exr", "relit.exr"]
    assert snapshot(scene) == before
    assert temporaries(scene) == []


# A write that fails: OSError(ENOSPC) as Python's own writes raise it, or an OSError with no errno
# at all (some libraries raise one with a message only, or nothing).
WRITE_ERRORS = {"enospc": lambda: OSError(errno.ENOSPC, os.strerror(errno.ENOSPC)), "no-errno": lambda: OSError()}


def _says_why(line: str, kind: str) -> None:
    if kind == "enospc":
        assert "no space left on device" in line and "Free some disk space" in line, line
    else:
        assert "the write failed" in line and "Check that the disk has free space" in line, line


class _HalfWriter:
    """A file whose first write puts half its bytes on disk, then fails (a disk filling up)."""

    def __init__(self, f, exc: OSError):
        self.f, self.exc = f, exc

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.f.close()

    def write(self, data):
        data = memoryview(data).cast("B")
        self.f.write(data[: len(data) // 2])
        self.f.flush()
        raise self.exc


@pytest.mark.parametrize("kind", WRITE_ERRORS)
def test_disk_full_writing_the_visibility_file(scene, monkeypatch, kind):
    """The HDF5 file is built in memory and written through atomic_output (files.h5_file): when
    that write fails halfway, the old visibility file and the manifest stay as they were, no temp
    file is left, and the one error line names the .h5 file; once the disk has room the cache is
    still up to date."""
    from pipelines.io import files

    before = snapshot(scene)

    def failing_open(path, mode="r", *args, **kwargs):
        f = open(path, mode, *args, **kwargs)
        return _HalfWriter(f, WRITE_ERRORS[kind]()) if "w" in mode else f

    monkeypatch.setattr(files, "open", failing_open, raising=False)  # h5_file's write (files.py's only open)
    line = assert_one_error_line(invoke(scene, "visibility", "--resolution", RES, "--force"), VIS_H5, quiet=False)
    _says_why(line, kind)
    assert snapshot(scene) == before
    assert temporaries(scene) == []
    monkeypatch.undo()
    assert decision_line(ok(invoke(scene, "visibility", "--resolution", RES)), VIS_STAGE).startswith(
        f"{VIS_STAGE}: skipped, up to date")


@pytest.mark.parametrize("kind", WRITE_ERRORS)
def test_disk_full_writing_a_visibility_chunk(tmp_path, monkeypatch, kind):
    """The exact method saves its rows in chunk files (np.save) that outlive a failed run: the
    third save fails halfway. One error line names that chunk; the two finished chunks stay whole,
    nothing else is left (no temp file, no half chunk, no visibility file, no record), and the
    next run resumes from the two chunks."""
    scene = copy_sample(tmp_path / "scene")
    args = ["visibility", "--resolution", RES, "--visibility", "exact"]
    real_save = np.save
    saves = []

    def failing_save(f, arr, *rest, **kwargs):
        saves.append(len(arr))
        if len(saves) == 3:
            f.write(b"\x93NUMPY" + bytes(100))  # the start of the file, then the disk is full
            raise WRITE_ERRORS[kind]()
        return real_save(f, arr, *rest, **kwargs)

    monkeypatch.setattr(np, "save", failing_save)
    line = assert_one_error_line(invoke(scene, *args), "chunk_00002.npy", quiet=False)
    _says_why(line, kind)
    partial = list((scene / ".wavelight" / "partial").iterdir())
    assert len(partial) == 1
    assert sorted(p.name for p in partial[0].iterdir()) == ["chunk_00000.npy", "chunk_00001.npy"]
    for p in partial[0].iterdir():
        assert np.load(p, allow_pickle=False).shape[0] == saves[0]
    assert not vis_file(scene, slot="-exact").exists()
    assert not (scene / ".wavelight" / "manifest.json").exists() or \
        vis_stage(slot="-exact") not in manifest(scene)["stages"]
    assert temporaries(scene) == []
    monkeypatch.undo()
    err = ok(invoke(scene, *args))
    assert re.search(r": resuming, 2/\d+ chunks already done$", err, re.M), err
    assert vis_file(scene, slot="-exact").is_file()


class _FailingImageOutput:
    """OpenImageIO's ImageOutput whose write fails: by raising `failure` (an OSError) or, as
    OpenImageIO itself does, by returning False with `failure` (text) as its error."""

    def __init__(self, failure):
        self.failure = failure

    def open(self, name, spec):
        with open(name, "wb") as f:
            f.write(b"v/1\x01 half an image")
        return True

    def write_image(self, arr):
        if isinstance(self.failure, OSError):
            raise self.failure
        return False

    def close(self):
        return True

    def geterror(self):
        return self.failure


@pytest.mark.parametrize("name, failure, says", [
    pytest.param("relit.exr", WRITE_ERRORS["enospc"], "no space left on device", id="exr-enospc"),
    pytest.param("relit.exr", WRITE_ERRORS["no-errno"], "the write failed", id="exr-oserror-without-errno"),
    pytest.param("relit.exr", lambda: "", "cannot write the image (unknown error)", id="exr-oiio-no-detail"),
    pytest.param("light_cross.png", lambda: "PNG write error", "cannot write the image (PNG write error)",
                 id="png-oiio-message"),
])
def test_failed_image_write_during_solve_is_one_error_line(lambert_solved, tmp_path, monkeypatch, name, failure,
                                                           says):
    """An image of the solve's outputs cannot be written (OpenImageIO gives no errno: it returns
    False with a message, maybe empty; a binding may raise an OSError without errno): one error
    line naming the image, exit 1, every earlier result and the manifest as they were, no temp
    file. (The preview PNGs with text go through outputs.write_display_png, the EXRs through
    images.write_exr.)"""
    import OpenImageIO as oiio

    scene = copy_scene(lambert_solved, tmp_path / "scene")
    before = snapshot(scene)
    real_create = oiio.ImageOutput.create

    def create(filename, *args):
        if Path(filename).name.startswith(f".{name}."):
            return _FailingImageOutput(failure())
        return real_create(filename, *args)

    monkeypatch.setattr(oiio.ImageOutput, "create", create)
    line = assert_one_error_line(invoke(scene, *SOLVE, "--force"), str(scene / "out" / name), quiet=False)
    assert says in line, line
    assert snapshot(scene) == before
    assert temporaries(scene) == []


def _can_mount_tmpfs(path: Path) -> bool:
    path.mkdir(parents=True, exist_ok=True)
    try:
        r = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=8m", "tmpfs", str(path)], capture_output=True,
                           timeout=30)
    except (OSError, subprocess.TimeoutExpired):
        return False
    return r.returncode == 0


def test_really_full_disk_fails_cleanly(lambert_solved, tmp_path):
    """On a real full file system (an 8 MB tmpfs with 100 kB left): one error line, exit 1, no
    crash (HDF5 writes that fail inside the library used to segfault), old results intact;
    after space is freed the same command succeeds."""
    mnt = tmp_path / "small"
    if not _can_mount_tmpfs(mnt):
        pytest.skip("cannot mount a tmpfs here (needs root); the injected disk-full test covers the logic")
    try:
        scene = copy_scene(lambert_solved, mnt / "scene")
        free_kb = os.statvfs(mnt).f_bavail * os.statvfs(mnt).f_frsize // 1024
        filler = mnt / "filler"
        with open(filler, "wb") as f:
            f.write(b"\0" * max(0, (free_kb - 100) * 1024))
        before = snapshot(scene)
        result = subprocess.run([wavelight_exe(), "-q", "-s", str(scene), *SOLVE, "--force"], capture_output=True,
                                text=True, timeout=300)
        assert result.returncode == 1, (result.returncode, result.stderr[-2000:])
        lines = result.stderr.splitlines()
        assert len(lines) == 1 and lines[0].startswith("Error: ") and "no space left on device" in lines[0], lines
        assert "Traceback" not in result.stderr
        after = snapshot(scene)
        for rel, data in before.items():
            assert after.get(rel) == data, f"{rel} changed on a full disk"
        filler.unlink()
        result = subprocess.run([wavelight_exe(), "-q", "-s", str(scene), *SOLVE, "--force"], capture_output=True,
                                text=True, timeout=300)
        assert result.returncode == 0, result.stderr
        assert temporaries(scene) == []
    finally:
        subprocess.run(["umount", "-l", str(mnt)], capture_output=True)


# -- kill -9 ---------------------------------------------------------------------------------
@pytest.mark.parametrize("moment", ["computing", "writing"])
def test_killed_solve_reruns_to_identical_results(tmp_path, moment):
    """SIGKILL while the solve computes or while it writes its outputs; the rerun (no manual
    cleanup) removes the dead run's temp files and ends with the same numbers, bit for bit, as an
    uninterrupted run."""
    reference = copy_sample(tmp_path / "reference")
    ok(invoke(reference, *SOLVE))
    killed = copy_sample(tmp_path / "killed")
    ok(invoke(killed, "visibility", "--resolution", RES))  # shared by both: the solve is what is killed
    log = tmp_path / "killed.err"
    with open(log, "w") as err:
        proc = subprocess.Popen([wavelight_exe(), "-s", str(killed), *SOLVE], stdout=subprocess.DEVNULL, stderr=err)
        if moment == "writing":
            def ready():
                return any(is_temporary(p.name) for p in (killed / "out").glob(".*"))
        else:
            def ready():
                return "level 0:" in log.read_text()  # the light solve has begun
        kill_when(proc, ready, timeout=120, poll=0.001)
    assert proc.returncode == -signal.SIGKILL, f"the solve ended before it could be killed:\n{log.read_text()}"
    assert "solve" not in manifest(killed)["stages"]
    # nothing under a final name: outputs replace their old versions together, at the end
    assert not (killed / "out" / "solve_report.json").exists()
    left = temporaries(killed)
    if moment == "writing":
        assert left, "the kill came before any output was started"
    result = run_proc(killed, *SOLVE)
    assert result.returncode == 0, result.stderr
    assert decision_line(result.stderr, "solve") == "solve: running (no previous run)"
    assert temporaries(killed) == []
    assert solved_data(killed) == solved_data(reference)


# -- versions --------------------------------------------------------------------------------
def test_cache_from_another_version_is_rebuilt_with_a_reason(lambert_solved, tmp_path):
    """A manifest whose solve was recorded by another stage version: `status` calls it stale and
    says why, and the next solve reruns with that reason (and the same numbers)."""
    scene = copy_scene(lambert_solved, tmp_path / "scene")
    data = manifest(scene)
    from wavelight_cli.stages.solve import VERSION as SOLVE_VERSION

    data["stages"]["solve"]["version"] = SOLVE_VERSION - 1
    (scene / ".wavelight" / "manifest.json").write_text(json.dumps(data))
    result = invoke(scene, "status", "--json")
    ok(result)
    status = json.loads(result.stdout)
    row = next(r for r in status if r["stage"] == "solve")
    assert row["state"] == "stale" and row["reason"] == f"stage version changed: {SOLVE_VERSION - 1} -> {SOLVE_VERSION}"
    assert next(r for r in status if r["stage"] == VIS_STAGE)["state"] == "fresh"
    before = solved_data(scene)
    err = ok(invoke(scene, *SOLVE))
    assert decision_line(err, "solve") == f"solve: running (stage version changed: {SOLVE_VERSION - 1} -> {SOLVE_VERSION})"
    assert decision_line(err, VIS_STAGE).startswith(f"{VIS_STAGE}: skipped, up to date")
    assert solved_data(scene) == before
    assert manifest(scene)["stages"]["solve"]["version"] == SOLVE_VERSION
    assert manifest(scene)["stages"]["solve"]["wavelight"]  # which wavelight wrote it


def test_stale_temp_files_are_swept_under_the_lock(lambert_solved, tmp_path):
    """Temp files a killed run left (in out/, the cache and the scene folder) are removed by the
    next run on the scene; other hidden files are not touched."""
    scene = copy_scene(lambert_solved, tmp_path / "scene")
    planted = [scene / "out" / ".relit.exr.abcd1234.tmp.exr", scene / ".wavelight" / ".visibility.h5.x_y9z8w7.tmp.h5",
               scene / ".pose.json.q1w2e3r4.tmp.json"]
    for p in planted:
        p.write_bytes(b"half a file")
    keep = scene / ".my_notes"
    keep.write_text("mine")
    err = ok(invoke(scene, *SOLVE))
    assert decision_line(err, "solve").startswith("solve: skipped, up to date")
    assert not any(p.exists() for p in planted)
    assert keep.read_text() == "mine"


def test_an_os_error_on_a_temp_file_names_the_file_it_stands_for(tmp_path):
    """A write that fails on its temp file (a read-only out/: mkstemp, or the manifest's rename)
    named `out/.ro.exr.p05upp5s.tmp.exr` (bad-input sweep): the line names out/ro.exr."""
    import errno

    from pipelines.io.files import final_path
    from wavelight_cli.main import os_error_line

    temp = tmp_path / "out" / ".relit.exr.p05upp5s.tmp.exr"
    assert is_temporary(temp.name) and final_path(temp) == tmp_path / "out" / "relit.exr"
    assert final_path(tmp_path / "relit.exr") == tmp_path / "relit.exr"
    line = os_error_line(PermissionError(errno.EACCES, "Permission denied", str(temp)), tmp_path)
    assert line.startswith(f"{tmp_path / 'out' / 'relit.exr'}: permission denied"), line


def test_a_file_or_dangling_link_where_a_folder_goes_is_named(tmp_path):
    """out/export a file: the line named out/export/mitsuba ('not a directory'); a dangling link:
    'file exists' (bad-input sweep). Now the thing in the way is named, with what it is."""
    import errno

    from wavelight_cli.main import os_error_line

    (tmp_path / "out").mkdir()
    (tmp_path / "out" / "export").write_text("")
    line = os_error_line(NotADirectoryError(errno.ENOTDIR, "Not a directory", str(tmp_path / "out" / "export" / "m")))
    assert line.startswith(f"{tmp_path / 'out' / 'export'}: is a file, where wavelight writes a folder"), line
    (tmp_path / "out" / "export").unlink()
    (tmp_path / "out" / "export").symlink_to(tmp_path / "nowhere")
    line = os_error_line(FileExistsError(errno.EEXIST, "File exists", str(tmp_path / "out" / "export")))
    assert line.startswith(f"{tmp_path / 'out' / 'export'}: is a dangling symbolic link"), line
