"""`wavelight relight`: new views of the Mitsuba scenes against Mitsuba's renders of them (with the
true and with the recovered light), new lights, and the bad inputs. Numbers in the docstrings are
measured with the code as of this writing."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from cli_helpers import (check_bad_input, invoke, ok, VIS_STAGE)
from pipelines.light import cubemap
from pipelines.io import images

SCENES = Path(__file__).parent / "data" / "scenes"


def _novel_args(scene: Path, name: str) -> list[str]:
    nv = scene / "truth" / "novel_view"
    return ["relight", "--name", name, "--view", str(nv / "pose.json"), "--view-camera", str(nv / "camera.json"),
            "--reference", str(nv / "image.exr"), "--reference-mask", str(nv / "mask.png")]


def _truth_args(scene: Path) -> list[str]:
    return ["--light", str(scene / "truth" / "env_latlong.exr"), "--material", str(scene / "truth" / "material.json")]


def _error(scene: Path, name: str) -> float:
    return json.loads((scene / "out" / f"{name}.json").read_text())["relative_rmse_vs_photo"]


@pytest.fixture(scope="module")
def mitsuba(tmp_path_factory):
    made = {}

    def get(name):
        if name not in made:
            made[name] = shutil.copytree(SCENES / name, tmp_path_factory.mktemp(name) / name)
        return made[name]
    return get


@pytest.mark.slow
@pytest.mark.parametrize("name, bound", [("spot_overcast", 0.02), ("bunny_sun", 0.04), ("teapot_sun_phong", None)])
def test_new_view_with_the_true_light_matches_mitsuba(mitsuba, name, bound):
    """The forward model is right for unseen views: Mitsuba's render from 40 deg further round,
    against ours with the true light and material at R = 32, over the view's mask. Measured:
    spot_overcast 0.48 %, bunny_sun 2.22 %, teapot_sun_phong 7.71 %. The teapot's error is the
    sun's quantisation at R = 32 (its input view is at 9.61 %, see test_forward_mitsuba): the new
    view must be no worse than the input view, whatever that level is."""
    scene = mitsuba(name)
    ok(invoke(scene, *_novel_args(scene, "novel_true"), *_truth_args(scene)))
    ok(invoke(scene, "relight", "--name", "input_true", *_truth_args(scene), "--reference", str(scene / "image.exr")))
    novel, seen = _error(scene, "novel_true"), _error(scene, "input_true")
    assert novel < 1.1 * seen, (novel, seen)
    if bound is not None:
        assert novel < bound
    report = json.loads((scene / "out" / "novel_true.json").read_text())
    assert report["view"].startswith("view-") and report["compared_pixels"] > 40000
    assert (scene / ".wavelight" / "visibility" / f"{report['view']}-R32.h5").is_file()


@pytest.mark.slow
@pytest.mark.parametrize("name", ["spot_overcast", "bunny_sun"])
def test_new_view_with_the_recovered_light(mitsuba, name):
    """solve (defaults: wavelet, auto reflectance -> Lambertian on these), then the new view under
    the recovered light: within the issue's 4 % goal. Measured: spot_overcast 0.53 %, bunny_sun
    2.23 % (with the true light: 0.48 % and 2.22 %)."""
    scene = mitsuba(name)
    ok(invoke(scene, "solve"))
    ok(invoke(scene, *_novel_args(scene, "novel_recovered")))
    assert json.loads((scene / "out" / "novel_recovered.json").read_text())["light"] == "recovered"
    assert _error(scene, "novel_recovered") < 0.04
    # the photo's view through relight is solve's own relit view (one forward model)
    ok(invoke(scene, "relight"))
    a = images.read_image(scene / "out" / "relight.exr").pixels
    b = images.read_image(scene / "out" / "relit.exr").pixels
    np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-7)


def test_rotate_latlong_keeps_power_and_moves_features():
    rng = np.random.default_rng(0)
    env = rng.uniform(0, 1, size=(16, 32, 3))
    omega = cubemap.latlong_solid_angles(16)[..., None]
    for deg in (0.0, 11.25, 37.0, -90.0, 360.0):
        rot = cubemap.rotate_latlong(env, deg)
        assert np.sum(rot * omega) == pytest.approx(np.sum(env * omega), rel=1e-12)
    np.testing.assert_array_equal(cubemap.rotate_latlong(env, 360.0), env)
    # 90 deg = 8 columns: the texel at phi moves to phi + 90 deg
    np.testing.assert_array_equal(cubemap.rotate_latlong(env, 90.0)[:, 8], env[:, 0])
    spot = np.zeros((16, 32))
    spot[5, 3] = 1.0
    half = cubemap.rotate_latlong(spot, 0.5 * 360 / 32)  # half a column: shared by two columns
    np.testing.assert_allclose(half[5, 3:5], [0.5, 0.5])


@pytest.fixture
def sample(lambert_solved):
    return lambert_solved  # the shared sample after a Lambertian solve at R = 8 (conftest.py)


def test_relight_defaults_to_the_solve_resolution_and_a_new_light_scales(sample, tmp_path):
    scene = shutil.copytree(sample, tmp_path / "s")
    err = ok(invoke(scene, "relight"))
    assert f"{VIS_STAGE}: skipped" in err  # R = 8 from the solve, not the default 32
    base = images.read_image(scene / "out" / "relight.exr").pixels
    ok(invoke(scene, "relight", "--name", "brighter", "--light-exposure", "1"))
    np.testing.assert_allclose(images.read_image(scene / "out" / "brighter.exr").pixels, 2 * base, rtol=1e-6)
    ok(invoke(scene, "relight", "--name", "turned", "--rotate", "360"))
    np.testing.assert_allclose(images.read_image(scene / "out" / "turned.exr").pixels, base, rtol=2e-3, atol=1e-6)
    ok(invoke(scene, "relight", "--name", "quarter", "--rotate", "90"))
    turned = images.read_image(scene / "out" / "quarter.exr").pixels
    assert np.abs(turned - base).mean() > 0.05 * base.mean()  # a low sun moved round: the shading changes
    info = json.loads((scene / "out" / "quarter.json").read_text())
    assert info["rotate_deg"] == 90 and info["light"] == "recovered" and info["resolution"] == 8


def test_rerun_is_skipped_and_another_light_reruns(sample, tmp_path):
    scene = shutil.copytree(sample, tmp_path / "s")
    ok(invoke(scene, "relight"))
    assert "relight: skipped" in ok(invoke(scene, "relight"))
    assert "params changed: rotate" in ok(invoke(scene, "relight", "--rotate", "10"))


def _no_solution(scene):
    (scene / "out" / "coefficients.h5").unlink()


BAD = [
    ("no-solve-no-light", _no_solution, ["relight"], "coefficients.h5"),
    ("light-missing", None, ["relight", "--light", "nope.exr"], "nope.exr"),
    ("view-missing", None, ["relight", "--view", "nope.json"], "nope.json"),
    ("view-camera-without-view", None, ["relight", "--view-camera", "camera.json"], "--view"),
    ("bad-name", None, ["relight", "--name", "a/b"], "--name"),
    ("reference-wrong-size", lambda s: images.write_exr(s / "small.exr", np.zeros((10, 12, 3), np.float32)),
     ["relight", "--reference", "small.exr"], "small.exr"),
    ("mask-wrong-size", lambda s: images.write_png(s / "m.png", np.ones((10, 12, 3)), already_display=True),
     ["relight", "--reference-mask", "m.png"], "m.png"),
    ("corrupt-solution", lambda s: (s / "out" / "coefficients.h5").write_bytes(b"junk" * 100), ["relight"],
     "coefficients.h5"),
]


@pytest.mark.parametrize("mutate, args, culprit", [pytest.param(*c[1:], id=c[0]) for c in BAD])
def test_bad_input_one_error_line(sample, tmp_path, mutate, args, culprit):
    check_bad_input(sample, tmp_path, mutate, args, culprit)
