"""Several photos under one light (issue 19, item 3): views/NAME/ in the scene folder, register and
visibility per view, one light solved on every view's rows, the per-view report, the errors.

The fast tests run at R = 8 on a copy of spot_textured_sun (main + views/left + views/right); the
accuracy comparison (1 view against 3) runs at the default R = 32 and is marked slow.
"""

from __future__ import annotations

import json
import shutil
import sys
from pathlib import Path

import numpy as np
import pytest

from cli_helpers import RES, invoke, ok

SCENES = Path(__file__).parent / "data" / "scenes"
REPO = Path(__file__).resolve().parents[1]


def copy_views_scene(tmp_path: Path, name: str = "spot_textured_sun") -> Path:
    dst = tmp_path / name
    shutil.copytree(SCENES / name, dst, ignore=shutil.ignore_patterns(".wavelight", "out", "truth"))
    return dst


def error_line(result) -> str:
    assert result.exit_code != 0, result.stdout + result.stderr
    text = (result.stderr or "") + (result.stdout or "")
    lines = [ln for ln in text.splitlines() if ln.startswith("Error:")]
    assert len(lines) == 1, text
    assert "Traceback" not in text
    return lines[0]


def solve_fast(scene: Path, *extra: str):
    return invoke(scene, "solve", "-R", RES, "--reflectance", "lambert", *extra)


def test_three_views_report_per_view(tmp_path):
    scene = copy_views_scene(tmp_path)
    ok(solve_fast(scene))
    report = json.loads((scene / "out" / "solve_report.json").read_text())
    assert report["options"]["views"] == ["main", "left", "right"]
    assert report["held_out"]["mode"] == "view" and report["held_out"]["view"] == "left"  # fewest pixels of the two
    views = report["views"]
    assert list(views) == ["main", "left", "right"]
    total = sum(v["pixels"]["used"] for v in views.values())
    assert total == report["pixels"]["used"]
    for name, v in views.items():
        assert v["pixels"]["used"] > 20000
        assert 0 < v["relit_rmse"] < 0.6
        assert (scene / v["outputs"] / "relit.exr").is_file() and (scene / v["outputs"] / "residual.png").is_file()
    # the whole left view is held out (for the model choice), nothing of the others
    assert views["left"]["pixels"]["held_out"] == views["left"]["pixels"]["used"] - views["left"]["pixels"]["saturated_excluded"]
    assert views["main"]["pixels"]["held_out"] == 0 and views["right"]["pixels"]["held_out"] == 0
    assert views["left"]["held_out_rmse"] is not None and views["main"]["held_out_rmse"] is None
    # a light fitted without the left view predicts it no better than the one fitted with it
    assert views["left"]["held_out_rmse"] >= views["left"]["relit_rmse"] - 1e-3
    # ... but nearly as well: the held-out view rendered with the parts' colours and texture too
    # (it was 65 % with kd = 1 on every part against a relit 2.9 %)
    print("left view: held-out", views["left"]["held_out_rmse"], "relit", views["left"]["relit_rmse"])
    assert views["left"]["held_out_rmse"] <= 1.5 * views["left"]["relit_rmse"] + 0.01
    obs = report["observability_by_view"]
    assert set(obs["views"]) == {"main", "left", "right"}
    assert obs["union"]["weakly_observed"] <= min(v["weakly_observed"] for v in obs["views"].values())
    for name in ("left", "right"):
        assert (scene / "out" / "views" / name / "observability_view.png").is_file()
    ok(invoke(scene, "report"))
    md = (scene / "out" / "report.md").read_text()
    assert "## Views" in md and "| left (held out) | 44400 |" in md


def test_relight_a_view_by_its_name(tmp_path):
    """relight --view NAME renders one of the scene's photos from its own camera and pose and compares
    it with that photo: the same error the solve reports for the view; a name the scene lacks, or a
    --view-camera with a named view, is one error line."""
    scene = copy_views_scene(tmp_path)
    ok(solve_fast(scene))
    report = json.loads((scene / "out" / "solve_report.json").read_text())
    for name, out in (("left", "left"), ("main", "mainview")):
        result = invoke(scene, "relight", "--view", name, "--name", out)
        ok(result)
        summary = json.loads((scene / "out" / f"{out}.json").read_text())
        assert summary["pixels"] == report["views"][name]["pixels"]["used"]
        assert summary["reference"].endswith("image.exr")
        assert summary["relative_rmse_vs_photo"] == pytest.approx(report["views"][name]["relit_rmse"], rel=2e-3)
        assert (scene / "out" / f"{out}_residual.png").is_file()
        assert (f"view {name}," if name != "main" else "photo view,") in result.stdout + result.stderr
    # the left view's visibility is the one the solve cached (not cast again)
    assert f"visibility/views-left/R{RES}: skipped" in ok(invoke(scene, "relight", "--view", "left", "--name", "x"))
    # under another light there is nothing to compare with, but the view's photo stays behind the render
    ok(invoke(scene, "relight", "--view", "left", "--rotate", "90", "--name", "turned"))
    assert "relative_rmse_vs_photo" not in json.loads((scene / "out" / "turned.json").read_text())
    line = error_line(invoke(scene, "relight", "--view", "nope"))
    assert "--view nope" in line and "main, left, right" in line
    line = error_line(invoke(scene, "relight", "--view", "left", "--view-camera", str(scene / "camera.json")))
    assert "--view-camera" in line


def test_insert_into_a_view_by_its_name(tmp_path):
    """insert --view NAME composites the object into that photo, seen from its own camera and pose:
    the object covers the pixel its centre projects to in that view (and not in the main photo's
    place), and the view's cached visibility is reused."""
    from pipelines.geometry.camera import project
    from pipelines.io import images
    from pipelines.io.scene_files import read_camera, read_pose

    scene = copy_views_scene(tmp_path)
    ok(solve_fast(scene))
    at = (0.8, -0.6, 0.25)
    args = ("insert", "--at", *map(str, at), "--radius", "0.25")
    for view, name, folder in ((None, "main_ball", scene), ("left", "left_ball", scene / "views" / "left")):
        result = invoke(scene, *args, "--name", name, *(() if view is None else ("--view", view)))
        err = ok(result)
        if view is not None:
            assert f"visibility/views-left/R{RES}: skipped" in err
        summary = json.loads((scene / "out" / f"{name}.json").read_text())
        assert summary["view"] == (view or "main") and summary["object_pixels"] > 500
        assert Path(summary["photo"]).parent == folder
        cam = read_camera(folder / "camera.json" if (folder / "camera.json").is_file() else scene / "camera.json")
        uv = project(cam, read_pose(folder / "pose.json"), np.array([at]))[0]
        render = images.read_image(scene / "out" / f"{name}_render.exr").pixels
        photo = images.read_image(Path(summary["photo"])).pixels
        composite = images.read_image(scene / "out" / f"{name}.exr").pixels
        c, r = int(round(uv[0])), int(round(uv[1]))
        assert np.abs(composite[r, c] - photo[r, c]).max() > 1e-3  # the object is where its centre projects
        assert render[r, c].max() > 0
    # the two composites differ: each is its own photo's view
    a = images.read_image(scene / "out" / "main_ball.exr").pixels
    b = images.read_image(scene / "out" / "left_ball.exr").pixels
    assert a.shape == b.shape and np.abs(a - b).mean() > 0.01
    line = error_line(invoke(scene, *args, "--view", "nope"))
    assert "--view nope" in line and "main, left, right" in line


def test_photos_of_different_exposure(tmp_path):
    """A photo taken at another exposure (auto exposure: views/left 1.6x brighter): `solve` fits each
    photo's gain relative to the main one (--view-exposure fit, the default) and finds the same light
    as with equal exposures; relight --view and insert --view render that photo at its own exposure.
    With --view-exposure same the light fits none of the photos and the solve says so."""
    from pipelines.io import images

    same = copy_views_scene(tmp_path / "a")
    brighter = copy_views_scene(tmp_path / "b")
    photo = brighter / "views" / "left" / "image.exr"
    images.write_exr(photo, images.read_image(photo).pixels * np.float32(1.6))
    ok(solve_fast(same))
    ok(solve_fast(brighter))
    ra = json.loads((same / "out" / "solve_report.json").read_text())
    rb = json.loads((brighter / "out" / "solve_report.json").read_text())
    assert rb["options"]["view_exposure"] == "fit" and rb["view_exposure"]["mode"] == "fit"
    truth = {"main": 1.0, "left": 1.6, "right": 1.0}
    for name, v in rb["views"].items():
        print(name, "fitted exposure", v["exposure"], "(equal photos:", ra["views"][name]["exposure"], ")",
              "gain left", v["gain_left"], "relit", v["relit_rmse"], ra["views"][name]["relit_rmse"])
        assert v["exposure"] == pytest.approx(truth[name], rel=0.01)  # measured: 1.602, 0.9996
        assert ra["views"][name]["exposure"] == pytest.approx(1.0, rel=0.01)  # measured: 1.002, 0.9994
        assert v["gain_left"] == pytest.approx(1.0, abs=0.01)
        assert v["relit_rmse"] == pytest.approx(ra["views"][name]["relit_rmse"], rel=0.03)
    assert rb["relit"]["relative_rmse_vs_photo"] == pytest.approx(ra["relit"]["relative_rmse_vs_photo"], rel=0.03)
    # relight --view left compares with the brighter photo at that photo's exposure: the solve's error
    ok(invoke(brighter, "relight", "--view", "left", "--name", "left"))
    summary = json.loads((brighter / "out" / "left.json").read_text())
    assert summary["view_exposure"] == pytest.approx(rb["views"]["left"]["exposure"])
    assert summary["relative_rmse_vs_photo"] == pytest.approx(rb["views"]["left"]["relit_rmse"], rel=2e-3)
    # insert --view left: the object is rendered 1.6x brighter there, as its photo is
    renders = []
    for scene in (same, brighter):
        ok(invoke(scene, "insert", "--at", "0.8", "-0.6", "0.25", "--radius", "0.25", "--view", "left", "--name", "ball"))
        renders.append(images.read_image(scene / "out" / "ball_render.exr").pixels)
    obj = renders[0].max(axis=2) > 1e-3
    ratio = np.median(renders[1][obj] / np.maximum(renders[0][obj], 1e-6))
    print("insert: object brighter by", ratio)
    assert ratio == pytest.approx(1.6, rel=0.02)
    # the photos taken to be of one exposure: the light fits the brighter photo and the others badly
    err = ok(solve_fast(brighter, "--view-exposure", "same"))
    assert "--view-exposure fit" in err
    rs = json.loads((brighter / "out" / "solve_report.json").read_text())
    assert rs["view_exposure"]["mode"] == "same" and rs["views"]["left"]["exposure"] == 1.0
    assert rs["views"]["left"]["gain_left"] > 1.1  # measured 1.415
    assert rs["relit"]["relative_rmse_vs_photo"] > 3 * rb["relit"]["relative_rmse_vs_photo"]  # measured 19.7 % against 3.9 %


def test_two_views_hold_out_pixels_and_cache_per_view(tmp_path):
    scene = copy_views_scene(tmp_path)
    ok(solve_fast(scene, "--single-view"))
    report = json.loads((scene / "out" / "solve_report.json").read_text())
    assert "views" not in report and report["options"]["views"] == ["main"]
    assert not (scene / ".wavelight" / "visibility" / f"views-left-R{RES}.h5").exists()
    err = ok(solve_fast(scene, "--views", "main,left"))
    # adding a view computes its visibility only
    assert f"visibility/photo/R{RES}: skipped" in err
    assert f"visibility/views-left/R{RES}: running" in err
    assert f"visibility/views-right/R{RES}" not in err
    assert "solve: running (params changed: views" in err
    report = json.loads((scene / "out" / "solve_report.json").read_text())
    assert report["held_out"]["mode"] == "pixels"
    for v in report["views"].values():  # ~10 % of each view's pixels held out, its error reported
        assert 0.05 < v["pixels"]["held_out"] / v["pixels"]["used"] < 0.15
        assert v["held_out_rmse"] is not None
    # changing one view's photo reruns the solve, not the visibility
    img = scene / "views" / "left" / "image.exr"
    from pipelines.io import images

    pixels = images.read_image(img).pixels
    images.write_exr(img, pixels * 1.5)
    err = ok(solve_fast(scene, "--views", "main,left"))
    assert "solve: running (input changed: photo:left)" in err
    assert f"visibility/views-left/R{RES}: skipped" in err


def test_register_a_view(tmp_path):
    scene = copy_views_scene(tmp_path)
    truth = json.loads((scene / "views" / "left" / "pose.json").read_text())
    (scene / "views" / "left" / "pose.json").unlink()
    r = invoke(scene, "solve", "-R", RES)
    assert "views/left/pose.json" in error_line(r) and "wavelight register" in error_line(r)
    ok(invoke(scene, "register", "--views", "left"))
    pose = json.loads((scene / "views" / "left" / "pose.json").read_text())
    assert pose["registration"]["rms_px"] < 1.0
    R0, R1 = np.array(truth["R"]), np.array(pose["R"])
    angle = np.degrees(np.arccos(np.clip((np.trace(R0.T @ R1) - 1) / 2, -1, 1)))
    assert angle < 0.5
    assert (scene / "out" / "views" / "left" / "register_overlay.png").is_file()
    man = json.loads((scene / ".wavelight" / "manifest.json").read_text())
    assert "register/left" in man["stages"] and "register" not in man["stages"]


def test_view_image_size_differs_from_its_camera(tmp_path):
    scene = copy_views_scene(tmp_path)
    cam = json.loads((scene / "views" / "right" / "camera.json").read_text())
    cam["width"] = 300
    (scene / "views" / "right" / "camera.json").write_text(json.dumps(cam))
    line = error_line(solve_fast(scene))
    assert "views/right/image.exr: image is 320x240 but camera.json says 300x240" in line
    assert not (scene / "out").exists() and not (scene / ".wavelight" / "visibility").exists()


def test_view_that_sees_nothing_of_the_mesh(tmp_path):
    scene = copy_views_scene(tmp_path)
    (scene / "views" / "left" / "pose.json").write_text(json.dumps(
        {"R": [[1, 0, 0], [0, 1, 0], [0, 0, 1]], "t": [100.0, 0.0, 10.0]}))
    line = error_line(solve_fast(scene))
    assert "views/left/pose.json" in line and "no pixel of the image sees the mesh" in line
    assert not (scene / "out").exists()  # nothing of the solve written
    assert not (scene / ".wavelight" / "visibility" / f"views-left-R{RES}.h5").exists()


def test_view_without_pose_or_correspondences_and_bad_names(tmp_path):
    scene = copy_views_scene(tmp_path)
    for name in ("pose.json", "correspondences.csv"):
        (scene / "views" / "right" / name).unlink()
    line = error_line(solve_fast(scene))
    assert "views/right/pose.json: the view has neither pose.json nor correspondences.csv" in line
    shutil.rmtree(scene / "views" / "right")
    r = solve_fast(scene, "--views", "main,nope")
    assert r.exit_code == 2 and "nope" in error_line(r) and "main, left" in error_line(r)
    r = solve_fast(scene, "--views", "left")
    assert r.exit_code == 2 and "leaves out main" in error_line(r)
    r = solve_fast(scene, "--views", "main,left", "--single-view")
    assert r.exit_code == 2
    (scene / "views" / "left" / "image.exr").unlink()
    assert "views/left/image.exr: a view without a photo" in error_line(solve_fast(scene))
    assert not (scene / "out").exists()


def _sun_angle_and_probes(scene: Path, truth_scene: Path) -> tuple[float | None, dict]:
    sys.path.insert(0, str(REPO / "benchmarks"))
    from bench_e2e import dominant_direction, probe_errors

    report = json.loads((scene / "out" / "solve_report.json").read_text())
    c = np.array(report["brightest_direction"]["centroid"]["direction"])
    truth = dominant_direction(truth_scene)
    angle = None if truth is None else float(np.degrees(np.arccos(np.clip(c @ truth, -1, 1))))
    return angle, probe_errors(scene / "out" / "coefficients.h5", truth_scene)


@pytest.mark.slow
@pytest.mark.parametrize("name", ["spot_textured_sun", "spot_textured_overcast"])
def test_three_views_lower_the_light_error(tmp_path, name):
    """One light fitted to 3 views against the main view alone, both Lambertian with one uniform
    material (`--single-material`: the texture not modelled, the probes' errors are high on both,
    the sun direction is robust to it). Measured (R = 32): sun 0.92 -> 0.83 deg, diffuse probe
    14.7 -> 13.6 %, glossy 44.7 -> 40.6 %; overcast: diffuse 22.1 -> 20.6 %, glossy 67.9 -> 57.1 %."""
    scene = copy_views_scene(tmp_path, name)
    ok(invoke(scene, "solve", "--reflectance", "lambert", "--single-material", "--single-view"))
    one = _sun_angle_and_probes(scene, SCENES / name)
    ok(invoke(scene, "solve", "--reflectance", "lambert", "--single-material"))
    three = _sun_angle_and_probes(scene, SCENES / name)
    report = json.loads((scene / "out" / "solve_report.json").read_text())
    assert three[1]["diffuse"] < 0.97 * one[1]["diffuse"]
    assert three[1]["glossy"] < 0.95 * one[1]["glossy"]
    print(f"sun {one[0]} -> {three[0]} deg, probes {one[1]} -> {three[1]}")
    if one[0] is not None:  # a sun: found within 2 deg from either, no worse from three
        assert one[0] < 2.0 and three[0] < 2.0 and three[0] <= one[0] + 0.05
    # why: directions the main view alone observes weakly, the others see
    obs = report["observability_by_view"]
    assert obs["union"]["weakly_observed"] < 0.2 * obs["views"]["main"]["weakly_observed"]
    assert obs["views"]["left"]["adds"]["well_observed"] + obs["views"]["right"]["adds"]["well_observed"] > 50


@pytest.mark.slow
def test_three_views_with_the_texture_modelled(tmp_path):
    """Parts and the texture modelled (the default on this scene) and 3 views against 1: the probes
    and the ground's albedo relative to Spot's improve (measured: diffuse probe 0.78 -> 0.55 %,
    glossy 6.88 -> 5.45 %, the ground / Spot ratio's worst channel 4.5 % -> 1.6 % off the truth
    (0.4434, 0.7016, 1.0371)); the sun's centroid is 0.18 and 0.37 deg off the truth's dominant
    direction (before `brightest`'s window: 0.34 and 1.83 deg, the peak texel alone from three
    views)."""
    truth = np.array([0.4434, 0.7016, 1.0371])
    scene = copy_views_scene(tmp_path, "spot_textured_sun")
    results = []
    for extra in (("--single-view",), ()):
        ok(invoke(scene, "solve", "--reflectance", "lambert", *extra))
        refl = json.loads((scene / "out" / "reflectance.json").read_text())
        ground = next(p for p in refl["parts"] if p["name"] == "ground")
        ratio_error = float(np.max(np.abs(np.asarray(ground["relative_to_reference"]) / truth - 1)))
        results.append((*_sun_angle_and_probes(scene, SCENES / "spot_textured_sun"), ratio_error))
    (sun1, probes1, ratio1), (sun3, probes3, ratio3) = results
    print(f"sun {sun1:.2f} -> {sun3:.2f} deg, diffuse {probes1['diffuse']:.4f} -> {probes3['diffuse']:.4f}, glossy "
          f"{probes1['glossy']:.4f} -> {probes3['glossy']:.4f}, ratio {ratio1:.4f} -> {ratio3:.4f}")
    assert probes3["diffuse"] < 0.9 * probes1["diffuse"] and probes3["diffuse"] < 0.01
    assert probes3["glossy"] < 0.9 * probes1["glossy"]
    assert ratio3 < 0.6 * ratio1 and ratio3 < 0.03
    assert sun1 < 1.0 and sun3 < 1.0


@pytest.mark.parametrize("supersample", [1, 2])
def test_texel_response_is_the_lambertian_gram_diagonal(mitsuba_scene, supersample):
    """The observability map's per-view texel response is diag(T'T) of the view's pixels (T the
    Lambertian kd = 1 transport, V cos omega), bit-packed rows and supersampled fractions alike,
    for a slice of the rows as for all of them (the blocks run on both cores)."""
    from pipelines.controllers.views import texel_response
    from pipelines.geometry import visibility as vis
    from pipelines.light.cubemap import CubeMap

    scene = mitsuba_scene("spot_overcast")
    samples = type(scene.samples)(**{k: v[::23] for k, v in vars(scene.samples).items()})
    cube = CubeMap(8)
    data = vis.compute_visibility(scene.backend, samples, cube, supersample=supersample)
    T = data.dense() * np.maximum(samples.normal @ cube.directions.T, 0) * cube.solid_angles
    V = data.dense()
    assert 0 < T.max() and (T == 0).any() and 0 < V.mean() < 1
    assert ((V > 0) & (V < 1)).any() == (supersample > 1)  # (fractions: V^2 is not V)
    rows = slice(100, 1500)
    assert len(samples) > rows.stop
    for sl in (None, rows):
        expect = (T[sl or slice(None)].astype(np.float64) ** 2).sum(axis=0)
        np.testing.assert_allclose(texel_response(data, sl, block=128), expect, rtol=1e-5, atol=1e-12 * expect.max())
