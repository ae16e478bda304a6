"""A `solve` that runs its visibility stage in the same process takes that stage's rows and
centre-ray hits from memory (`visibility.read_kept`, `scene.keep_hits`) instead of reading the file
back and casting the hits again: the same light, relit image and coverage, bit for bit, as a solve
that reads them from the cache; and a file changed since is read, not the memory."""

from __future__ import annotations

import os

import numpy as np

from cli_helpers import RES, copy_sample, h5_arrays, invoke, ok, vis_file
from pipelines.io import visibility_file
from wavelight_cli.stages import visibility as vis_stage


def _counting_reads(monkeypatch) -> list:
    calls = []
    real = visibility_file.read_visibility

    def counted(path, *a, **k):
        calls.append(path)
        return real(path, *a, **k)

    monkeypatch.setattr(visibility_file, "read_visibility", counted)
    return calls


def _relit(scene, name: str = "relit") -> np.ndarray:
    import OpenImageIO as oiio

    return np.asarray(oiio.ImageBuf(str(scene / "out" / f"{name}.exr")).get_pixels(oiio.FLOAT))


def test_solve_takes_the_visibility_it_just_cast_and_gets_the_same_bits(tmp_path, monkeypatch):
    scene = copy_sample(tmp_path / "scene")
    reads = _counting_reads(monkeypatch)
    ok(invoke(scene, "solve", "--resolution", RES))
    assert reads == [], "the solve read back the visibility file the same process had just written"
    assert str(vis_file(scene)) not in vis_stage._KEPT, "the kept rows must go to their one reader"
    first, relit = h5_arrays(scene / "out" / "coefficients.h5"), _relit(scene)
    ok(invoke(scene, "solve", "--resolution", RES, "--force"))
    assert [str(p) for p in reads] == [str(vis_file(scene))]
    assert h5_arrays(scene / "out" / "coefficients.h5") == first
    np.testing.assert_array_equal(_relit(scene), relit)  # (its coverage: the kept hits, then cast again)


def test_a_solve_after_a_visibility_command_in_the_same_process_takes_its_rows(tmp_path, monkeypatch):
    """`visibility`, then `solve` (its visibility stage up to date) in one process: the kept rows
    are still the file's, and the solve takes them."""
    scene = copy_sample(tmp_path / "scene")
    ok(invoke(scene, "visibility", "--resolution", RES))
    reads = _counting_reads(monkeypatch)
    ok(invoke(scene, "solve", "--resolution", RES))
    assert reads == []


def test_a_visibility_file_changed_since_is_read_not_the_memory(tmp_path, monkeypatch):
    scene = copy_sample(tmp_path / "scene")
    ok(invoke(scene, "visibility", "--resolution", RES))
    path = vis_file(scene)
    assert str(path) in vis_stage._KEPT
    st = path.stat()
    os.utime(path, ns=(st.st_atime_ns, st.st_mtime_ns + 1_000_000_000))  # (another process rewrote it)
    reads = _counting_reads(monkeypatch)
    data = vis_stage.read_kept(path)
    assert [str(p) for p in reads] == [str(path)]
    assert data.stored.shape[0] == len(data.samples) > 0


def test_kept_hits_are_the_cast_ones(tmp_path):
    from pipelines.geometry.camera import mesh_hits
    from pipelines.io.scene_files import read_camera, read_pose
    from wavelight_cli import scene as sc

    scene = copy_sample(tmp_path / "scene")
    ok(invoke(scene, "visibility", "--resolution", RES))
    files = sc.SceneFiles(scene)
    view, camera = sc.photo_view(files), read_camera(scene / "camera.json")
    backend = sc.scene_backend(sc.scene_mesh(files.mesh))
    assert sc._LOADED.get("hits"), "the visibility stage kept no hits"
    kept = sc.mesh_coverage(view, camera, backend)
    cast = mesh_hits(camera, read_pose(scene / "pose.json"), backend)
    assert cast.sum() > 1000
    np.testing.assert_array_equal(kept, cast)  # (the sample has no mask.png)
    sc._LOADED.pop("hits")
    np.testing.assert_array_equal(sc.mesh_coverage(view, camera, backend), cast)


def test_render_takes_the_visibility_it_just_cast_and_gets_the_same_image(tmp_path, monkeypatch):
    from cli_helpers import render_args

    scene = copy_sample(tmp_path / "scene")
    reads = _counting_reads(monkeypatch)
    ok(invoke(scene, *render_args(scene)))
    assert reads == []
    first = _relit(scene, "render")
    ok(invoke(scene, *render_args(scene), "--force"))
    assert [str(p) for p in reads] == [str(vis_file(scene))]
    np.testing.assert_array_equal(_relit(scene, "render"), first)
