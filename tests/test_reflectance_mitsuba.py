"""Reflectance fitting against an independent renderer: the Mitsuba 3 scenes in tests/data/scenes.

teapot_sun_phong was rendered with exactly DESIGN §2's Blinn-Phong (truth/material.json: kd 0.5,
ks 0.4, n 30; object and plane share it). The fit starts from the CLI's default (kd = 1, ks = 0.25,
n = 20) under `auto`, so kd = 1 fixes the scale: ks comes out as ks / kd (truth 0.8) and the light
as light x kd. Visibility at R = 32 on every 2nd used pixel (24,247 pixels) keeps the test at a
few minutes; the full-resolution numbers are in the README (same code, `wavelight solve`).

spot_overcast and bunny_sun are Lambertian (truth kd 0.8 / 0.7): `auto` must keep them so.
"""

import numpy as np
import pytest

from pipelines.io import images
from pipelines.light import bases as lt
from pipelines.model import reflectance as rf
from pipelines.light.system import build_normal_equations, holdout_mask
from pipelines.model.materials import Material

RESOLUTION = 32
HELD_OUT = 0.1
START = Material(kd=(1.0, 1.0, 1.0), ks=(0.25, 0.25, 0.25), shininess=20.0, model="blinn-phong")  # CLI default


class Scene:
    def __init__(self, forward_render, name: str, step: int):
        fr = forward_render(name, RESOLUTION, step)
        self.vis, self.cube, self.truth = fr.visibility, fr.visibility.cube, fr.scene.material
        s = self.vis.samples
        self.photo = images.read_image(fr.scene.path / "image.exr").pixels[s.pixel[:, 0], s.pixel[:, 1]].astype(float)
        self.held = holdout_mask(s.pixel, HELD_OUT)
        self.materials: list[Material] = []

    def solve_light(self, material: Material):
        self.materials.append(material)
        ne = build_normal_equations(self.vis, self.photo, material, held_out=self.held)
        return lt.solve(ne, self.cube, "wavelet"), ne

    def select(self) -> rf.Reflectance:
        return rf.select(self.vis, self.photo, START, self.solve_light, held_out=self.held,
                         kd_reference=START.kd)


@pytest.fixture(scope="module")
def teapot(forward_render):
    """`auto` on the teapot: about 3 min (5 specular normal-equation passes); the tests using it are slow."""
    scene = Scene(forward_render, "teapot_sun_phong", step=2)
    return scene, scene.select()


@pytest.mark.slow
def test_auto_picks_blinn_phong_on_the_glossy_teapot(teapot):
    _, result = teapot
    assert result.material.model == "blinn-phong", result.decision
    assert result.fit.ks_significant


@pytest.mark.slow
def test_teapot_ks_and_n_within_15_percent_from_the_default_start(teapot):
    """Measured (step 2): ks / kd 0.811 (truth 0.8), n 30.5 (truth 30), kd (0.99, 0.99, 1.02), after
    7 rounds (all pixels, `make bench`: 0.797, 31.0)."""
    scene, result = teapot
    m = result.material
    truth = scene.truth
    assert np.mean(m.ks) / np.mean(m.kd) == pytest.approx(np.mean(truth.ks) / np.mean(truth.kd), rel=0.15), m
    assert m.shininess == pytest.approx(truth.shininess, rel=0.15), m
    # grey truth: the fitted kd's colour stays grey within 5 % (the sky's colour is the light's)
    assert np.ptp(m.kd) / np.mean(m.kd) < 0.05 * 3


@pytest.mark.slow
def test_teapot_specular_fit_relights_far_better_than_lambertian(teapot):
    """Relit error over all used pixels: measured 7.50 % with the fitted Blinn-Phong term against
    39.6 % for the best Lambertian light (held-out 12.1 % against 38.7 %): the highlights cannot be
    explained by any light."""
    _, result = teapot
    lambert = result.rounds[0]
    assert lambert.material.model == "lambert"
    best = result.rounds[result.chosen_round]
    assert best.fit_rmse < 0.3 * lambert.fit_rmse
    assert best.held_out_rmse < 0.4 * lambert.held_out_rmse
    assert len(result.rounds) >= 3  # lambert, then at least light -> LM -> light


@pytest.mark.slow  # ~35-45 s each; make test keeps test_reflectance.py::test_auto_stays_lambertian_on_a_diffuse_scene
@pytest.mark.parametrize("name", ["spot_overcast", "bunny_sun"])
def test_auto_keeps_the_diffuse_scenes_lambertian(forward_render, name):
    """The probe (LM with the Lambertian light fixed) finds no specular term worth keeping. When
    its ks is not significant no specular light solve runs (one normal-equation pass, as for
    --reflectance lambert); when it is significant but gains too little on its own rows, the probe's
    material gets its own light once (bunny_sun with exactly cast visibility: one Blinn-Phong solve),
    and so do the significant plastic probes and then the plastic starts, and none of those lights
    may pay off either."""
    scene = Scene(forward_render, name, step=1)
    result = scene.select()
    assert result.material.model == "lambert", result.decision
    assert result.decision.startswith("lambert")
    models = [m.model for m in scene.materials]
    probe = result.candidates["probe"]
    if probe["ks_significant"]:
        assert models[:1] == ["lambert"] and set(models[1:]) <= {"blinn-phong", "plastic"}, models
        own = [c["gain_under_its_own_light"] for c in result.candidates.values() if "gain_under_its_own_light" in c]
        assert own and max(own) < 0.05, result.candidates
        assert len(models) == 1 + len(own), models  # one light per own-light test
    else:
        assert models == ["lambert"], models
