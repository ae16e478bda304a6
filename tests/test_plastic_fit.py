"""Fitting `plastic` (pipelines/model/plastic_fit.py, alternated by pipelines/model/reflectance.py) on
synthetic photos rendered through our forward model: the teapot geometry of tests/test_reflectance.py
(every 4th used pixel, R = 16), a warm sun over a bluish sky, 0.5 % noise.

Numbers quoted in docstrings were measured with the code as of this writing.
"""

from dataclasses import replace

import numpy as np
import pytest

from pipelines.model import plastic_fit as pf
from pipelines.model import reflectance as rf
from pipelines.model.materials import Material
from pipelines.model.render import render
from test_reflectance import RESOLUTION, SCENE, STEP, TRUE as BLINN, Synthetic, start_from

PLASTIC = Material(kd=(0.6, 0.5, 0.4), ks=(1.0, 1.0, 1.0), model="plastic", roughness=0.15, distribution="beckmann")
START = Material(kd=(0.5, 0.5, 0.5), ks=(0.5, 0.5, 0.5), model="plastic", roughness=0.1, distribution="beckmann")


@pytest.fixture(scope="module")
def vis16(forward_render):
    return forward_render(SCENE, RESOLUTION, STEP).visibility


@pytest.fixture(scope="module")
def coated(vis16):
    return Synthetic(vis16, PLASTIC, seed=5)


def _data(syn, material=START, light=None):
    return pf.plastic_data(syn.vis, syn.photo, syn.light if light is None else light, material, held_out=syn.held)


def test_plastic_data_reproduces_render(coated):
    """The LM's evaluation is the one forward model: kd b(alpha) B' + ks S equals render()."""
    data = _data(coated)
    for alpha in (0.03, 0.15, 0.5):
        m = replace(PLASTIC, roughness=alpha)
        B, S = data.evaluate(alpha)
        pred = np.asarray(m.kd) * pf.base_scale(alpha, m.ior, m.distribution) * B + S
        expected = render(coated.vis, coated.light, m)
        np.testing.assert_allclose(pred, expected, rtol=2e-3, atol=1e-5 * expected.max())


@pytest.mark.parametrize("distribution", ["ggx", "beckmann"])
def test_jacobian_in_log_alpha_matches_finite_differences(coated, distribution):
    data = _data(coated, replace(START, distribution=distribution))
    alpha, h = 0.12, 1e-2
    _, _, dB, dS = data.evaluate(alpha, derivative=True)
    Bp, Sp = data.evaluate(alpha * np.exp(h))
    Bm, Sm = data.evaluate(alpha * np.exp(-h))
    np.testing.assert_allclose(dS, (Sp - Sm) / (2 * h), rtol=2e-3, atol=2e-3 * np.abs(dS).max())
    np.testing.assert_allclose(dB, (Bp - Bm) / (2 * h), rtol=5e-3, atol=5e-3 * np.abs(dB).max())


@pytest.mark.parametrize("alpha0", [0.1, 0.02, 0.6])
def test_lm_recovers_kd_ks_alpha_with_the_light_fixed(coated, alpha0):
    """With the true light fixed, from alpha 0.1 (the default start), 0.02 and 0.6: alpha, ks and kd's
    colour within 1 %, the error at the noise floor, and sigma covers the error."""
    fit = pf.fit_plastic(_data(coated), replace(START, roughness=alpha0))
    m = fit.material
    assert m.model == "plastic" and m.distribution == "beckmann"
    assert m.roughness == pytest.approx(0.15, rel=0.01), fit.summary()
    ratio = np.asarray(m.kd) / np.asarray(PLASTIC.kd)
    np.testing.assert_allclose(ratio / ratio.mean(), 1.0, atol=0.01)
    assert float(np.mean(m.ks)) / float(np.mean(m.kd)) == pytest.approx(1.0 / 0.5, rel=0.01)
    assert abs(m.roughness - 0.15) < 4 * fit.sigma["alpha"] + 1e-4
    assert fit.fit_rmse < 1.1 * np.sqrt(np.mean(coated.noise**2) / np.mean(coated.photo**2))


@pytest.mark.parametrize("alpha0, guard", [(0.6, True), (0.04, False)])
def test_the_profile_search_reaches_lm_s_optimum(coated, alpha0, guard):
    """The default fit (a search in log alpha over the best kd', ks of each alpha: variable
    projection) ends where LM over all seven parameters does, the reference: alpha, kd and ks within
    0.05 %, the same error, with or without the scan's guard, from a start 4x off either way
    (the light a little off the truth's, so that the optimum is not the truth)."""
    light = coated.light * np.linspace(0.9, 1.1, len(coated.light))[:, None]
    data = _data(coated, light=light)
    start = replace(START, roughness=alpha0)
    ref = pf.fit_plastic(data, start, guard=guard, method="lm")
    fit = pf.fit_plastic(data, start, guard=guard, method="profile")
    assert fit.path.endswith("profile") and ref.path.endswith("lm")
    assert fit.material.roughness == pytest.approx(ref.material.roughness, rel=5e-4)
    np.testing.assert_allclose(fit.material.kd, ref.material.kd, rtol=5e-4)
    assert fit.material.ks[0] == pytest.approx(ref.material.ks[0], rel=5e-4)
    assert fit.fit_rmse == pytest.approx(ref.fit_rmse, rel=1e-6)
    assert fit.sigma["alpha"] == pytest.approx(ref.sigma["alpha"], rel=0.01)


def test_alternation_lowers_the_error_and_keeps_alpha(coated):
    """Light and plastic alternated from the true alpha with ks/kd 2x off (1 instead of 2): every
    round lowers the error and alpha stays near the truth. Measured: 0.150, 0.145, 0.141, 0.129,
    0.129, 0.128, 0.128 over the rounds (error 1.05 % -> 0.77 %). Before the grazing views' energy cap
    (`microfacet.grazing_cap`) the first LM halved alpha (0.073) and it crept back by ~0.005-0.01 a
    round: a few silhouette pixels seen at N.v ~ 0.01 rendered tens of times too bright and drove
    both the light and the lobe."""
    start = replace(START, roughness=0.15)
    result = rf.alternate(coated.vis, coated.photo, start, coated.solve_light, held_out=coated.held,
                          kd_reference=(0.5, 0.5, 0.5), max_rounds=6)
    m = result.material
    errors = [r.fit_rmse for r in result.rounds]
    alphas = [r.material.roughness for r in result.rounds]
    print(result.decision, list(zip(alphas, errors)), m)
    assert m.model == "plastic"
    assert all(b < a for a, b in zip(errors[1:], errors[2:])), errors
    assert min(alphas) > 0.12 and 0.12 < m.roughness < 0.16, alphas


def test_auto_chooses_plastic_on_a_plastic_scene(coated):
    """Measured: under each candidate's first light Blinn-Phong is ahead (held out 2.9 %, plastic-beckmann
    4.0 %, plastic-ggx 4.5 %: each plastic was fitted to Blinn-Phong's light), which is why the best of
    each family is alternated; alternated, plastic-beckmann 0.89 % against Blinn-Phong's 2.30 %."""
    result = rf.select(coated.vis, coated.photo, start_from(0.125, 20.0), coated.solve_light, held_out=coated.held,
                       kd_reference=(0.5, 0.5, 0.5), plastic_starts=[START, replace(START, distribution="ggx")])
    print(result.decision, result.material, [(r.material.roughness, r.fit_rmse, r.held_out_rmse) for r in result.rounds])
    assert result.material.model == "plastic", result.decision
    assert result.material.distribution == "beckmann"
    assert "plastic" in result.decision and "probe_plastic-ggx" in result.candidates


def test_auto_keeps_blinn_phong_on_a_blinn_phong_scene(vis16):
    """Measured: under each candidate's first light, Blinn-Phong 5.3 %, plastic-ggx 8.1 % held out."""
    syn = Synthetic(vis16, BLINN)
    result = rf.select(syn.vis, syn.photo, start_from(0.125, 20.0), syn.solve_light, held_out=syn.held,
                       kd_reference=(0.5, 0.5, 0.5), plastic_starts=[START, replace(START, distribution="ggx")])
    print(result.decision)
    assert result.material.model == "blinn-phong", result.decision
