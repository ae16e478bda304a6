"""The per-scene stage cache through the CLI (DESIGN §5): why a stage runs or is skipped, damaged
outputs and manifests, status, resuming a killed run, and the per-scene lock."""

from __future__ import annotations

import json
import math
import re
import signal
import subprocess

import numpy as np
import pytest

from cli_helpers import (RES, assert_one_error_line, copy_sample, copy_scene, decision_line, h5_arrays, invoke, kill_when, manifest, ok, render_args, rotate_pose, run_proc, sha256, snapshot, wavelight_exe, VIS_STAGE, VIS_H5, vis_stage, vis_file)
from wavelight_cli.stages.visibility import CHUNK_PIXELS





@pytest.fixture(scope="module")
def baseline_arrays(baseline):
    return h5_arrays(baseline / VIS_H5)


def _file_state(path):
    return path.read_bytes(), path.stat().st_mtime_ns


def _vis(scene, *extra):
    return ok(invoke(scene, "visibility", "--resolution", RES, *extra))


# -- runs and skips -----------------------------------------------------------------------------

def test_first_run_runs_then_everything_skips(tmp_path):
    scene = copy_sample(tmp_path / "scene")
    err = _vis(scene)
    assert decision_line(err, VIS_STAGE) == f"{VIS_STAGE}: running (no previous run)"
    h5 = scene / VIS_H5
    assert h5.is_file()
    rec = manifest(scene)["stages"][VIS_STAGE]
    assert rec["params"]["resolution"] == 8
    assert rec["outputs"] == {VIS_H5: sha256(h5)}
    state = _file_state(h5)

    err = _vis(scene)
    assert decision_line(err, VIS_STAGE).startswith(f"{VIS_STAGE}: skipped, up to date")
    assert _file_state(h5) == state
    assert manifest(scene)["stages"][VIS_STAGE] == rec

    err = ok(invoke(scene, *render_args(scene)))
    assert decision_line(err, VIS_STAGE).startswith(f"{VIS_STAGE}: skipped, up to date")
    assert decision_line(err, "render") == "render: running (no previous run)"
    assert (scene / "out" / "render.exr").is_file() and (scene / "out" / "render.png").is_file()
    assert _file_state(h5) == state
    before = snapshot(scene)

    err = ok(invoke(scene, *render_args(scene)))
    assert decision_line(err, VIS_STAGE).startswith(f"{VIS_STAGE}: skipped, up to date")
    assert decision_line(err, "render").startswith("render: skipped, up to date")
    assert snapshot(scene) == before


def test_pose_change_reruns_visibility_then_render(scene, baseline_arrays):
    old = manifest(scene)["stages"]
    rotate_pose(scene)
    err = _vis(scene)
    assert decision_line(err, VIS_STAGE) == f"{VIS_STAGE}: running (input changed: pose.json)"
    new_vis = manifest(scene)["stages"][VIS_STAGE]
    assert new_vis["key"] != old[VIS_STAGE]["key"]
    assert h5_arrays(scene / VIS_H5)["pixels/position"] != baseline_arrays["pixels/position"]

    err = ok(invoke(scene, *render_args(scene)))
    assert decision_line(err, VIS_STAGE).startswith(f"{VIS_STAGE}: skipped, up to date")
    assert decision_line(err, "render") == f"render: running (upstream changed: {VIS_STAGE})"
    assert manifest(scene)["stages"]["render"]["upstream"] == {VIS_STAGE: new_vis["key"]}


def test_pose_change_then_render_reruns_both(scene):
    rotate_pose(scene)
    err = ok(invoke(scene, *render_args(scene)))
    assert decision_line(err, VIS_STAGE) == f"{VIS_STAGE}: running (input changed: pose.json)"
    assert decision_line(err, "render") == f"render: running (upstream changed: {VIS_STAGE})"


def test_display_option_reruns_nothing_expensive(scene):
    """The PNG exposure is a display option: changing it redraws the preview from the EXR, it does
    not rerun the render (nor its visibility)."""
    h5, exr, png = (_file_state(scene / p) for p in (VIS_H5, "out/render.exr", "out/render.png"))
    key = manifest(scene)["stages"]["render"]["key"]
    err = ok(invoke(scene, *render_args(scene, "--exposure", "1")))
    assert decision_line(err, VIS_STAGE).startswith(f"{VIS_STAGE}: skipped, up to date")
    assert decision_line(err, "render") == "render: redrawing the previews (display options changed: exposure null -> 1.0)"
    assert _file_state(scene / VIS_H5) == h5 and _file_state(scene / "out/render.exr") == exr
    assert _file_state(scene / "out/render.png") != png
    rec = manifest(scene)["stages"]["render"]
    assert rec["display"]["exposure"] == 1.0 and rec["key"] == key
    assert sha256(scene / "out/render.png") == rec["outputs"]["out/render.png"]
    err = ok(invoke(scene, *render_args(scene, "--exposure", "1")))
    assert decision_line(err, "render").startswith("render: skipped, up to date")


def test_material_change_reruns_render_only(scene):
    err = ok(invoke(scene, "render", "--resolution", RES, "--light", scene / "truth" / "env_latlong.exr",
                    "--kd", "0.5", "0.5", "0.5"))
    assert decision_line(err, VIS_STAGE).startswith(f"{VIS_STAGE}: skipped, up to date")
    assert decision_line(err, "render").startswith("render: running (params changed: material ")


def test_two_resolutions_coexist(scene, baseline_arrays):
    """Visibility at another R is another result: the R = 8 one stays, and commands at R = 8 reuse it
    (before, one slot: `compare -R 16` then `relight` recomputed the most expensive stage twice)."""
    err = ok(invoke(scene, "visibility", "--resolution", "16"))
    assert decision_line(err, vis_stage(16)) == f"{vis_stage(16)}: running (no previous run)"
    stages = manifest(scene)["stages"]
    assert stages[vis_stage(16)]["params"]["resolution"] == 16 and stages[VIS_STAGE]["params"]["resolution"] == 8
    import h5py

    with h5py.File(vis_file(scene, 16), "r") as f:
        assert int(f.attrs["resolution"]) == 16
        assert int(f.attrs["n_texels"]) == 3 * 16 * 16
    assert h5_arrays(scene / VIS_H5) == baseline_arrays  # the R = 8 result is untouched
    err = ok(invoke(scene, *render_args(scene)))  # R = 8 again: nothing to recompute
    assert decision_line(err, VIS_STAGE).startswith(f"{VIS_STAGE}: skipped, up to date")
    assert decision_line(err, "render").startswith("render: skipped, up to date")
    err = ok(invoke(scene, *render_args(scene, res="16")))  # the render against R = 16 reads the R = 16 result
    assert decision_line(err, vis_stage(16)).startswith(f"{vis_stage(16)}: skipped, up to date")
    assert decision_line(err, "render") == f"render: running (upstream changed: {vis_stage(16)}, {VIS_STAGE})"


def test_old_visibility_results_are_pruned(scene):
    """Of each view the 4 most recently computed visibility results are kept (DESIGN §6)."""
    for r in ("2", "4", "16", "32"):
        ok(invoke(scene, "visibility", "--resolution", r))
    names = {n for n in manifest(scene)["stages"] if n.startswith("visibility/photo/")}
    assert names == {vis_stage(r) for r in (4, 16, 32, 2)}, names  # R = 8 (the oldest) went
    assert not (scene / VIS_H5).exists() and vis_file(scene, 2).is_file()


def test_force_reruns_and_gives_the_same_bits(scene, baseline_arrays):
    err = _vis(scene, "--force")
    assert decision_line(err, VIS_STAGE) == f"{VIS_STAGE}: running (--force)"
    assert h5_arrays(scene / VIS_H5) == baseline_arrays
    err = ok(invoke(scene, *render_args(scene, "--force")))
    assert decision_line(err, VIS_STAGE).startswith(f"{VIS_STAGE}: skipped, up to date")
    assert decision_line(err, "render") == "render: running (--force)"


def test_deleted_output_reruns_render(scene):
    (scene / "out" / "render.png").unlink()
    h5 = _file_state(scene / VIS_H5)
    err = ok(invoke(scene, *render_args(scene)))
    assert decision_line(err, VIS_STAGE).startswith(f"{VIS_STAGE}: skipped, up to date")
    assert decision_line(err, "render") == "render: running (output missing: out/render.png)"
    assert (scene / "out" / "render.png").is_file()
    assert _file_state(scene / VIS_H5) == h5
    rec = manifest(scene)["stages"]["render"]
    for rel, digest in rec["outputs"].items():
        assert sha256(scene / rel) == digest


def _overwrite_middle(path):
    data = bytearray(path.read_bytes())
    mid = len(data) // 2
    data[mid:mid + 64] = bytes((b ^ 0x5A) for b in data[mid:mid + 64])
    path.write_bytes(bytes(data))


def _truncate(path):
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 3])


@pytest.mark.parametrize("damage", [_overwrite_middle, _truncate], ids=["overwrite-middle", "truncate"])
@pytest.mark.parametrize("command", ["visibility", "render"])
def test_damaged_visibility_file_is_detected_and_rebuilt(scene, baseline_arrays, damage, command):
    h5 = scene / VIS_H5
    recorded = manifest(scene)["stages"][VIS_STAGE]["outputs"][VIS_H5]
    damage(h5)
    assert sha256(h5) != recorded

    lines, rows = _status(scene)
    assert rows[VIS_STAGE]["state"] == "stale"
    assert rows[VIS_STAGE]["reason"] == f"output missing or damaged: {VIS_H5}"
    assert lines[VIS_STAGE].split()[1] == "stale"

    args = ["visibility", "--resolution", RES] if command == "visibility" else render_args(scene)
    err = ok(invoke(scene, *args))
    line = decision_line(err, VIS_STAGE)
    assert line.startswith(f"{VIS_STAGE}: running (")
    assert "hash mismatch" in line and VIS_H5 in line
    if command == "render":  # same visibility key, intact results: nothing to redo
        assert decision_line(err, "render").startswith("render: skipped, up to date")
    assert h5_arrays(h5) == baseline_arrays
    assert sha256(h5) == manifest(scene)["stages"][VIS_STAGE]["outputs"][VIS_H5]
    err = _vis(scene)
    assert decision_line(err, VIS_STAGE).startswith(f"{VIS_STAGE}: skipped, up to date")


@pytest.mark.parametrize("content, reason", [
    pytest.param(b"\x00\xffgarbage\x89PNG\r\n" * 20, "manifest damaged, rebuilding", id="binary"),
    pytest.param(b'{"format": 1, "stages": {VIS_STAGE: {"key": ', "manifest damaged, rebuilding",
                 id="truncated-json"),
    pytest.param(b"", "manifest damaged, rebuilding", id="empty"),
    pytest.param(b'{"format": 99, "stages": {}}', "manifest damaged, rebuilding", id="unknown-format"),
    pytest.param(b'{"format": 1, "stages": []}', "manifest damaged, rebuilding", id="stages-not-object"),
    pytest.param(b"[1, 2, 3]", "manifest damaged, rebuilding", id="json-array"),
    pytest.param(b"null", "manifest damaged, rebuilding", id="json-null"),
    pytest.param(b'{"format": 1, "stages": {VIS_STAGE: 5}}', None, id="record-not-object"),
])
def test_garbage_manifest_means_rebuild_not_crash(scene, baseline_arrays, content, reason):
    (scene / ".wavelight" / "manifest.json").write_bytes(content)
    status = invoke(scene, "status", "--json")
    ok(status)
    assert all(r["state"] != "fresh" for r in json.loads(status.stdout))
    if reason is not None:  # (the text status said only "no stage has run": bad-input sweep)
        text = invoke(scene, "status")
        ok(text)
        assert "manifest.json: damaged; the next stage rebuilds it" in text.stdout, text.stdout
    err = _vis(scene)
    line = decision_line(err, VIS_STAGE)
    assert line.startswith(f"{VIS_STAGE}: running (")
    if reason is not None:
        assert line == f"{VIS_STAGE}: running ({reason})"
    assert h5_arrays(scene / VIS_H5) == baseline_arrays
    rec = manifest(scene)["stages"][VIS_STAGE]
    assert rec["outputs"] == {VIS_H5: sha256(scene / VIS_H5)}
    err = _vis(scene)
    assert decision_line(err, VIS_STAGE).startswith(f"{VIS_STAGE}: skipped, up to date")


CAL = ["calibrate", "--pattern", "acircles", "--pattern-size", "4x11", "--spacing", "10mm"]


@pytest.mark.parametrize("loss", ["deleted", "garbage"])
def test_lost_manifest_keeps_the_records_camera_and_pose_carry(tmp_path, loss):
    """camera.json and pose.json carry the record of the calibrate / register run that wrote them.
    After the manifest is lost, both stages are still up to date, a later register that rebuilds
    the manifest keeps calibrate's record (camera.json is calibrate's, not hand-written: a new
    calibration may replace it), and a camera.json edited since is not taken for calibrate's."""
    scene = copy_sample(tmp_path / "scene", calibrated=False)
    ok(invoke(scene, *CAL))
    ok(invoke(scene, "register"))
    before = manifest(scene)["stages"]
    edited = copy_scene(scene, tmp_path / "edited")
    for s in (scene, edited):
        path = s / ".wavelight" / "manifest.json"
        path.unlink() if loss == "deleted" else path.write_bytes(b"\x00 not json")

    _, rows = _status(scene)
    assert {s: (r["state"], r["key"]) for s, r in rows.items()} == {
        s: ("fresh", before[s]["key"][:12]) for s in ("calibrate", "register")}
    assert decision_line(ok(invoke(scene, "register")), "register").startswith("register: skipped, up to date")
    err = ok(invoke(scene, "register", "--max-mesh-distance", "0.02"))  # reruns, and writes a new manifest
    assert decision_line(err, "register").startswith("register: running (params changed: max_mesh_distance")
    stages = manifest(scene)["stages"]
    assert stages["calibrate"]["key"] == before["calibrate"]["key"]
    assert stages["calibrate"]["outputs"]["camera.json"] == sha256(scene / "camera.json")
    assert decision_line(ok(invoke(scene, *CAL)), "calibrate").startswith("calibrate: skipped, up to date")
    err = ok(invoke(scene, *CAL[:-1], "11mm"))  # replaces camera.json: it is calibrate's
    assert decision_line(err, "calibrate").startswith("calibrate: running (params changed: spacing")
    assert json.loads((scene / "camera.json").read_text())["calibration"]["spacing_m"] == pytest.approx(0.011)

    cam = json.loads((edited / "camera.json").read_text())
    cam["fx"] += 1.0  # edited by hand: its record no longer proves its content
    (edited / "camera.json").write_text(json.dumps(cam, indent=1))
    assert "calibrate" not in _status(edited)[1]
    line = assert_one_error_line(invoke(edited, *CAL[:-1], "11mm"), str(edited / "camera.json"), quiet=False)
    assert "was not written by wavelight calibrate as it is now" in line


# -- status -------------------------------------------------------------------------------------

def _status(scene):
    text = invoke(scene, "status")
    ok(text)
    js = invoke(scene, "status", "--json")
    ok(js)
    rows = {r["stage"]: r for r in json.loads(js.stdout)}
    lines = {ln.split()[0]: ln for ln in text.stdout.splitlines()[1:] if ln.strip()}
    return lines, rows


def test_status_reports_fresh_then_stale_after_pose_change(scene):
    lines, rows = _status(scene)
    assert set(rows) == {VIS_STAGE, "render"} == set(lines)
    for stage in rows:
        assert rows[stage]["state"] == "fresh" and rows[stage]["reason"] == "up to date"
        assert lines[stage].split()[1] == "fresh" and lines[stage].endswith("up to date")
    assert rows[VIS_STAGE]["params"]["resolution"] == 8
    assert rows[VIS_STAGE]["key"] == manifest(scene)["stages"][VIS_STAGE]["key"][:12]

    rotate_pose(scene)
    lines, rows = _status(scene)
    assert rows[VIS_STAGE]["state"] == "stale"
    assert rows[VIS_STAGE]["reason"] == "input changed: pose.json"
    assert lines[VIS_STAGE].split()[1] == "stale"
    assert lines[VIS_STAGE].endswith("input changed: pose.json")

    ok(invoke(scene, *render_args(scene)))
    lines, rows = _status(scene)
    assert {s: r["state"] for s, r in rows.items()} == {VIS_STAGE: "fresh", "render": "fresh"}


def test_status_marks_downstream_of_a_stale_stage_stale(scene):
    rotate_pose(scene)
    lines, rows = _status(scene)
    assert rows["render"]["state"] == "stale"
    assert VIS_STAGE in rows["render"]["reason"]
    assert lines["render"].split()[1] == "stale"


def test_status_without_any_run(tmp_path):
    scene = copy_sample(tmp_path / "scene")
    result = invoke(scene, "status")
    ok(result)
    assert "no stage has run" in result.stdout
    js = invoke(scene, "status", "--json")
    ok(js)
    assert json.loads(js.stdout) == []


# -- killed run, resume -------------------------------------------------------------------------

KILL_ARGS = ["visibility", "--resolution", "32", "--visibility", "exact"]  # the exact method runs in chunks
KILL_STAGE, KILL_H5 = vis_stage(32, "-exact"), ".wavelight/visibility/photo-R32-exact.h5"


def test_killed_visibility_run_resumes_to_identical_bits(tmp_path):
    killed = copy_sample(tmp_path / "killed")
    reference = copy_sample(tmp_path / "reference")
    exe = wavelight_exe()
    # the uninterrupted reference runs meanwhile, in its own copy
    with open(tmp_path / "ref.err", "w") as ref_err, open(tmp_path / "killed.err", "w") as kill_err:
        ref = subprocess.Popen([exe, "-s", str(reference), *KILL_ARGS], stdout=subprocess.DEVNULL, stderr=ref_err)
        proc = subprocess.Popen([exe, "-s", str(killed), *KILL_ARGS], stdout=subprocess.DEVNULL, stderr=kill_err)
        kill_when(proc, lambda: len(list(killed.glob(".wavelight/partial/photo-R32-exact-*/chunk_*.npy"))) >= 2,
                  timeout=240)
    chunks = list(killed.glob(".wavelight/partial/photo-R32-exact-*/chunk_*.npy"))
    log = (tmp_path / "killed.err").read_text()
    assert len(chunks) >= 2, f"no chunks appeared before the deadline:\n{log}"
    assert proc.returncode == -signal.SIGKILL, f"the run ended before it could be interrupted:\n{log}"

    assert not (killed / KILL_H5).exists()
    man = killed / ".wavelight" / "manifest.json"
    assert not man.exists() or KILL_STAGE not in manifest(killed)["stages"]
    partial = list((killed / ".wavelight" / "partial").glob("photo-R32-exact-*"))
    assert len(partial) == 1
    n_done = len(list(partial[0].glob("chunk_*.npy")))
    assert n_done >= 2

    result = run_proc(killed, *KILL_ARGS)
    assert result.returncode == 0, result.stderr
    assert decision_line(result.stderr, KILL_STAGE) == f"{KILL_STAGE}: running (no previous run)"
    m = re.search(rf"^{KILL_STAGE}: resuming, (\d+)/(\d+) chunks already done$", result.stderr, re.M)
    assert m, result.stderr
    done, total = int(m.group(1)), int(m.group(2))
    assert done == n_done
    assert done < total, "the killed run had already finished every chunk: not an interruption"
    assert "Traceback" not in result.stderr

    assert ref.wait(timeout=600) == 0, (tmp_path / "ref.err").read_text()
    resumed_arrays, ref_arrays = h5_arrays(killed / KILL_H5), h5_arrays(reference / KILL_H5)
    assert set(resumed_arrays) == set(ref_arrays)
    assert "visibility" in ref_arrays and "pixels/pixel" in ref_arrays
    for name in ref_arrays:
        assert resumed_arrays[name] == ref_arrays[name], f"{name} differs after resuming"
    assert total == math.ceil(ref_arrays["pixels/pixel"][1][0] / CHUNK_PIXELS)

    rec, ref_rec = manifest(killed)["stages"][KILL_STAGE], manifest(reference)["stages"][KILL_STAGE]
    assert rec["key"] == ref_rec["key"]
    assert rec["outputs"] == {KILL_H5: sha256(killed / KILL_H5)}
    # the resumed run cast only the rays of the missing chunks
    assert 0 < rec["summary"]["rays_cast_this_run"] < ref_rec["summary"]["rays_cast_this_run"]
    assert not (killed / ".wavelight" / "partial").exists()
    assert not [p for p in (killed / ".wavelight").rglob("*") if p.name.endswith(".tmp.h5")]


def test_a_damaged_resume_chunk_is_cast_again(tmp_path):
    """A chunk of an interrupted exact run damaged on disk (cut short, or not the chunk's rows) is
    cast again on the next run, not read: no traceback, and the same bits as an uninterrupted run."""
    scene = copy_sample(tmp_path / "scene")
    args = ["visibility", "--resolution", "8", "--visibility", "exact"]
    stage, h5 = vis_stage(8, "-exact"), ".wavelight/visibility/photo-R8-exact.h5"
    first = run_proc(scene, *args)
    assert first.returncode == 0, first.stderr
    reference = h5_arrays(scene / h5)
    key = manifest(scene)["stages"][stage]["key"]
    partial = scene / ".wavelight" / "partial" / f"photo-R8-exact-{key[:16]}"
    partial.mkdir(parents=True)
    (partial / "chunk_00000.npy").write_bytes(b"\x93NUMPY" + b"\0" * 990)  # cut short
    np.save(partial / "chunk_00001.npy", np.zeros((3, 24), np.uint8))  # not the chunk's rows
    np.save(partial / "chunk_00002.npy", np.zeros((CHUNK_PIXELS, 5), np.uint8))  # nor its width (review)
    again = run_proc(scene, *args, "--force")
    assert again.returncode == 0, again.stderr
    assert "Traceback" not in again.stderr
    assert f"{stage}: 3 damaged chunk(s) of an interrupted run are cast again" in again.stderr, again.stderr
    assert h5_arrays(scene / h5) == reference
    assert not (scene / ".wavelight" / "partial").exists()


# -- concurrent runs ----------------------------------------------------------------------------

def _start(exe, scene, args, log):
    return subprocess.Popen([exe, "-s", str(scene), *map(str, args)], stdout=subprocess.DEVNULL, stderr=log)


def test_two_concurrent_visibility_runs(tmp_path):
    scene = copy_sample(tmp_path / "scene")
    exe = wavelight_exe()
    args = ["visibility", "--resolution", "16"]
    logs = [tmp_path / "a.err", tmp_path / "b.err"]
    with open(logs[0], "w") as la, open(logs[1], "w") as lb:
        procs = [_start(exe, scene, args, la), _start(exe, scene, args, lb)]
        codes = [p.wait(timeout=600) for p in procs]
    errs = [p.read_text() for p in logs]
    assert codes == [0, 0], errs
    stage = vis_stage(16)
    decisions = [decision_line(e, stage) for e in errs]
    running = [i for i, d in enumerate(decisions) if d == f"{stage}: running (no previous run)"]
    assert len(running) == 1, decisions
    other = 1 - running[0]
    assert decisions[other].startswith(f"{stage}: skipped, up to date"), decisions
    if "waiting: another wavelight run holds" in errs[other]:
        lines = errs[other].splitlines()
        waited = next(i for i, ln in enumerate(lines) if ln.startswith("waiting: another wavelight run holds"))
        assert waited < lines.index(decisions[other])
    for e in errs:
        assert "Traceback" not in e and "Error" not in e

    h5 = vis_file(scene, 16)
    import h5py

    with h5py.File(h5, "r") as f:
        assert f.attrs["format"] == "wavelight-visibility-1"
        assert int(f.attrs["resolution"]) == 16
        n = int(f.attrs["n_pixels"])
        assert f["visibility"].shape[0] == n == f["pixels/pixel"].shape[0] > 10_000
    assert manifest(scene)["stages"][stage]["outputs"] == {".wavelight/visibility/photo-R16.h5": sha256(h5)}
    assert not (scene / ".wavelight" / "partial").exists()
    js = invoke(scene, "status", "--json")
    ok(js)
    assert [(r["stage"], r["state"]) for r in json.loads(js.stdout)] == [(stage, "fresh")]


def test_concurrent_visibility_and_render(tmp_path):
    scene = copy_sample(tmp_path / "scene")
    exe = wavelight_exe()
    logs = [tmp_path / "vis.err", tmp_path / "render.err"]
    with open(logs[0], "w") as la, open(logs[1], "w") as lb:
        procs = [_start(exe, scene, ["visibility", "--resolution", RES], la),
                 _start(exe, scene, render_args(scene), lb)]
        codes = [p.wait(timeout=600) for p in procs]
    errs = [p.read_text() for p in logs]
    assert codes == [0, 0], errs
    vis_decisions = [decision_line(e, VIS_STAGE) for e in errs]
    assert sum(d == f"{VIS_STAGE}: running (no previous run)" for d in vis_decisions) == 1, vis_decisions
    assert sum(d.startswith(f"{VIS_STAGE}: skipped, up to date") for d in vis_decisions) == 1, vis_decisions
    assert decision_line(errs[1], "render") == "render: running (no previous run)"
    stages = manifest(scene)["stages"]
    assert stages["render"]["upstream"] == {VIS_STAGE: stages[VIS_STAGE]["key"]}
    for stage in (VIS_STAGE, "render"):
        for rel, digest in stages[stage]["outputs"].items():
            assert sha256(scene / rel) == digest



def test_stage_params_compare_as_the_manifest_holds_them(scene):
    """A tuple option (insert's --object-kd, click's nargs=3) is stored as a list: a rerun with the
    same value is up to date, not 'params changed: [0.5, 0.5, 0.5] -> [0.5, 0.5, 0.5]'."""
    from wavelight_cli.cache import SceneCache, Stage

    cache = SceneCache(scene)

    def stage():
        return Stage("probe-params", 1, {"object_kd": (0.5, 0.5, 0.5), "at": (1.0, 2.0, 3.0)})

    assert stage().params == {"object_kd": [0.5, 0.5, 0.5], "at": [1.0, 2.0, 3.0]}
    with cache.lock(10.0, lambda m: None):
        first = cache.plan(stage())
        assert first.run
        cache.record(first, [], 0.0)
        again = cache.plan(stage())
        assert not again.run, again.reason
