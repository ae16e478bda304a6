"""The robust pass (`pipelines/light/robust.py`; `solve --robust/--no-robust`, `--clipped bound|drop`).

Its numerics on synthetic residuals (Gaussian noise keeps every pixel, gross outliers go, an edge the
prediction places a pixel off is not an outlier, a speck beside it is, at most MAX_DOWN_SHARE go), and on the sample scene at R = 8:
a clean photo is solved once, exactly as without the pass; a photo with dust specks and glints over
2 % of its pixels gets most of its light back (probe errors against the true light).
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from cli_helpers import RES, copy_scene, invoke, ok, vis_file
from pipelines.light import robust


def _noisy(n=20000, seed=0):
    rng = np.random.default_rng(seed)
    y = rng.uniform(0.05, 1.0, n)
    pred = np.repeat(y[:, None], 3, axis=1) * np.array([1.0, 0.9, 0.8])
    sigma = 0.01 * np.sqrt(y)[:, None]  # shot noise: brighter, noisier
    return pred, pred + sigma * rng.standard_normal(pred.shape), rng


def _weights(values, pred, clipped=None, span=None):
    clipped = np.zeros(values.shape, bool) if clipped is None else clipped
    span = np.repeat(pred[..., None], 2, axis=-1) if span is None else span  # (no edges)
    model = robust.noise_model(values, clipped, pred, span)
    return robust.weights(model, values, clipped, pred, span), model


def test_taper_is_one_up_to_the_threshold_and_zero_from_twice_it():
    w = robust.taper(np.array([0.0, 3.9, 4.0, 4.4, 6.0, 7.9, 8.0, 50.0]), 4.0)
    assert np.all(w[:3] == 1.0) and np.all(w[-2:] == 0.0)
    assert 1.0 > w[3] > w[4] > w[5] > 0.0  # a smooth taper in between
    assert w[3] == pytest.approx((1 - 0.1**2) ** 2)


def test_gaussian_noise_keeps_every_pixel():
    pred, values, _ = _noisy()
    w, model = _weights(values, pred)
    assert model.threshold == robust.INLIER_Z
    assert np.all(w == 1.0), f"{int((w < 1).sum())} of {len(w)} noise-only pixels down-weighted"
    # sigma(y) follows the noise that grows with brightness: ~0.01 sqrt(y)
    s = np.interp([0.25, 0.81], model.brightness, model.sigma)
    np.testing.assert_allclose(s, 0.01 * np.sqrt([0.25, 0.81]), rtol=0.25)


def test_gross_outliers_get_no_weight_and_the_rest_keep_theirs():
    pred, values, rng = _noisy(seed=1)
    bad = rng.choice(len(values), len(values) // 100, replace=False)  # 1 %: dust specks, glints
    values[bad[::2]] *= 0.1
    values[bad[1::2]] *= 5.0
    w, _ = _weights(values, pred)
    assert np.all(w[bad] == 0.0)
    good = np.setdiff1d(np.arange(len(values)), bad)
    assert (w[good] == 1.0).mean() > 0.9999


def test_at_most_max_down_share_is_down_weighted_when_the_model_fits_poorly_everywhere():
    pred, _, rng = _noisy(seed=2)
    values = pred * (1 + 0.05 * rng.standard_cauchy((len(pred), 1)))  # heavy tails everywhere: the model's
    w, model = _weights(values, pred)
    assert model.threshold > robust.INLIER_Z
    assert (w < 1).mean() <= robust.MAX_DOWN_SHARE + 1e-4
    assert (w < 1).mean() > robust.MAX_DOWN_SHARE - 0.005  # (the cap, not fewer: the tails are beyond 4 sigma)


def test_an_edge_placed_a_pixel_off_is_not_an_outlier_but_a_far_one_is():
    H, W = 40, 60
    r, c = np.mgrid[:H, :W]
    pixels = np.column_stack([r.ravel(), c.ravel()])
    step = lambda at: np.where(c.ravel() < at, 0.1, 0.8)  # noqa: E731  (a shadow edge)
    pred = np.repeat(step(30)[:, None], 3, axis=1)
    rng = np.random.default_rng(3)
    span = robust.edge_span(pixels, pred)
    near = np.abs(c.ravel() - 29.5) <= robust.EDGE_PIXELS
    # the step's range within EDGE_PIXELS of it, widened by EDGE_SLACK, and by PEAK_WIDTHS of it past
    # the end of the range the pixel's own prediction is at (its plateau: a sharper edge there is a blur)
    slack, peak = robust.EDGE_SLACK * 0.7, robust.PEAK_WIDTHS * 0.7
    np.testing.assert_allclose(span[near, :, 0], 0.1 - slack - np.where(pred[near] == 0.1, peak, 0.0))
    np.testing.assert_allclose(span[near, :, 1], 0.8 + slack + np.where(pred[near] == 0.8, peak, 0.0))
    np.testing.assert_allclose(span[~near], np.repeat(pred[~near, :, None], 2, axis=-1))
    seg = (r.ravel() >= 10) & (r.ravel() < 15)  # a few rows where the photo's edge is elsewhere (1 % of the pixels)
    for shift, off in ((1, False), (robust.EDGE_PIXELS + 4, True)):
        values = np.where(seg, step(30 + shift), step(30))
        values = np.repeat(values[:, None], 3, axis=1) + 0.002 * rng.standard_normal(pred.shape)
        clipped = np.zeros(values.shape, bool)
        model = robust.noise_model(values, clipped, pred, span)
        w = robust.weights(model, values, clipped, pred, span)
        wrong = seg & (c.ravel() >= 30) & (c.ravel() < 30 + shift)  # the pixels the edge is misplaced over
        assert model.threshold == robust.INLIER_Z
        if off:  # EDGE_PIXELS + 4: the pixels beyond EDGE_PIXELS of the predicted edge are outliers, the others not
            assert np.all(w[wrong & ~near] == 0.0) and np.all(w[wrong & near] == 1.0)
        else:
            assert np.all(w[wrong] == 1.0)
        assert np.all(w[~wrong] == 1.0)


def test_a_speck_beside_an_edge_is_an_outlier_but_a_value_the_edge_takes_nearby_is_not():
    # a dark speck on the lit side of a shadow edge, darker than the shadow itself, is not a misplaced
    # edge: no shift of the prediction within EDGE_PIXELS gives it (a value inside the step's range is)
    H, W = 40, 60
    r, c = np.mgrid[:H, :W]
    pixels = np.column_stack([r.ravel(), c.ravel()])
    pred = np.repeat(np.where(c.ravel() < 30, 0.3, 0.8)[:, None], 3, axis=1)  # a shadow lit by the sky
    rng = np.random.default_rng(4)
    values = pred + 0.002 * rng.standard_normal(pred.shape)
    speck = (c.ravel() == 31) & (r.ravel() >= 5) & (r.ravel() < 8)  # lit side, beside the edge
    inside = (c.ravel() == 31) & (r.ravel() >= 20) & (r.ravel() < 23)
    values[speck] = 0.05  # darker than the shadow beside it, beyond the slack (0.3 - 0.25 x 0.5)
    values[inside] = 0.5  # between the shadow and the lit side: a blurred or misplaced edge
    span = robust.edge_span(pixels, pred)
    w, model = _weights(values, pred, span=span)
    assert model.threshold == robust.INLIER_Z
    assert np.all(w[speck] == 0.0)
    assert np.all(w[~speck] == 1.0)
    # the exempt pixels (clipped ones: a bound is judged by the noise alone) have no edge range
    exempt = robust.edge_span(pixels, pred, exempt=inside)
    np.testing.assert_allclose(exempt[inside], np.repeat(pred[inside, :, None], 2, axis=-1))


def test_a_peak_sharper_than_the_prediction_s_is_not_an_outlier_but_a_glint_on_it_is():
    # a highlight whose core the light's texels blur (teapot_plastic_sun, alpha 0.05: 11 clean pixels,
    # 5.8 % of the squared error, were down-weighted before peaks had their own allowance)
    H, W = 40, 60
    r, c = np.mgrid[:H, :W]
    pixels = np.column_stack([r.ravel(), c.ravel()])
    d2 = ((r - 20.0) ** 2 + (c - 30.0) ** 2).ravel()
    pred = np.repeat((0.2 + 0.5 * np.exp(-d2 / (2 * 3.0**2)))[:, None], 3, axis=1)  # the blurred highlight
    rng = np.random.default_rng(5)
    values = np.repeat((0.2 + 0.7 * np.exp(-d2 / (2 * 2.0**2)))[:, None], 3, axis=1)  # the photo's, sharper
    values += 0.002 * rng.standard_normal(values.shape)
    glint = (r.ravel() == 21) & (c.ravel() == 30)
    values[glint] = 3.0
    span = robust.edge_span(pixels, pred)
    w, _ = _weights(values, pred, span=span)
    core = d2 <= 2.0
    assert np.all(w[core & ~glint] == 1.0) and w[glint] == 0.0
    # without the peak's allowance its core would go: the allowance is what keeps it
    plain = np.repeat(pred[..., None], 2, axis=-1)
    assert np.all(_weights(values, pred, span=plain)[0][core] < 1.0)


def test_a_clipped_channel_is_a_lower_bound():
    values = np.array([[1.0, 0.5, 0.2], [1.0, 0.5, 0.2]])
    clipped = np.array([[True, False, False], [True, False, False]])
    pred = np.array([[1.4, 0.5, 0.2], [0.6, 0.5, 0.2]])
    np.testing.assert_allclose(robust.lower_bound_targets(values, clipped, pred), [[1.4, 0.5, 0.2], [1.0, 0.5, 0.2]])
    # only a prediction below the bound is an error (the hinge)
    np.testing.assert_allclose(robust.residual_rms(values, clipped, pred), [0.0, np.sqrt(0.4**2 / 3)])


# -- on the sample scene (R = 8) ------------------------------------------------------------------

@pytest.fixture(scope="module")
def solved(baseline, tmp_path_factory):
    """The baseline scene after one default `solve -R 8`. Read-only: copy it to change it."""
    scene = copy_scene(baseline, tmp_path_factory.mktemp("robust") / "scene")
    ok(invoke(scene, "solve", "--resolution", RES))
    return scene


def _report(scene) -> dict:
    return json.loads((scene / "out" / "solve_report.json").read_text())


def _probe_errors(scene) -> dict:
    from pipelines.io import images, light_file
    from pipelines.io.scene_files import read_pose
    from pipelines.light import cubemap
    from pipelines.metrics import probe_errors

    light, cube, _ = light_file.read_solution_light(scene / "out" / "coefficients.h5")
    env = images.read_latlong(scene / "truth" / "env_latlong.exr")
    fine = cubemap.CubeMap(32)
    view = read_pose(scene / "pose.json").camera_centre
    return probe_errors(light, cube, cubemap.latlong_to_cube(env, fine), fine, view)


def _specks(scene, share=0.02, seed=3) -> int:
    """Dark specks and bright glints (3 x 3 blobs, 20x apart in brightness) over `share` of the used
    pixels of the scene's photo; returns how many used pixels they cover."""
    from pipelines.io import images
    from pipelines.io.visibility_file import read_visibility

    img = images.read_image(scene / "image.exr").pixels.copy()
    pix = read_visibility(vis_file(scene)).samples.pixel
    used = np.zeros(img.shape[:2], bool)
    used[pix[:, 0], pix[:, 1]] = True
    rng = np.random.default_rng(seed)
    mean = float(img[used].mean())
    hit = np.zeros_like(used)
    for k, i in enumerate(rng.choice(len(pix), int(share * len(pix) / 9), replace=False)):
        y, x = pix[i]
        img[max(y - 1, 0):y + 2, max(x - 1, 0):x + 2] = 0.05 * mean if k % 2 else 8.0 * mean
        hit[max(y - 1, 0):y + 2, max(x - 1, 0):x + 2] = True
    images.write_exr(scene / "image.exr", img)
    return int((hit & used).sum())


def _spoiled_mask(scene):
    """Where the spoiled photo differs from the sample's own photo (the specks and glints)."""
    from pipelines.io import images

    from cli_helpers import SAMPLE

    return np.any(images.read_image(scene / "image.exr").pixels != images.read_image(SAMPLE / "image.exr").pixels,
                  axis=2)


def test_a_clean_photo_is_solved_once_and_as_without_the_pass(solved, tmp_path):
    """On the clean sample photo no pixel moves 1 % of the squared error: no second solve, and the
    light is bit for bit that of --no-robust."""
    import h5py

    scene = solved
    rep = _report(scene)["robust"]
    assert rep["applied"] and rep["rounds"] == 0 and rep["influence"] < 0.01
    assert rep["down_weighted_pixels"] <= 0.001 * rep["pixels"]  # measured 0
    plain = copy_scene(scene, tmp_path / "plain")
    ok(invoke(plain, "solve", "--resolution", RES, "--no-robust"))
    assert _report(plain)["robust"]["applied"] is False
    assert (scene / "out" / "robust_weights.png").is_file() and not (plain / "out" / "robust_weights.png").exists()
    with h5py.File(scene / "out" / "coefficients.h5") as a, h5py.File(plain / "out" / "coefficients.h5") as b:
        np.testing.assert_array_equal(a["light"][()], b["light"][()])


def test_specks_and_glints_do_not_drag_the_light(solved, tmp_path):
    """2 % of the used pixels spoiled: the plain fit's diffuse probe is 3.5x the clean one's (6.38 %
    against 1.83 %, measured); the robust pass down-weights most of them and comes back to 2.60 %."""
    clean = _probe_errors(solved)["diffuse"]
    scene = copy_scene(solved, tmp_path / "specks")
    spoiled = _specks(scene)
    ok(invoke(scene, "solve", "--resolution", RES, "--no-robust"))
    plain = _probe_errors(scene)["diffuse"]
    err = ok(invoke(scene, "solve", "--resolution", RES))
    fixed = _probe_errors(scene)["diffuse"]
    rep = _report(scene)["robust"]
    assert "robust pass 1:" in err and "robust fit:" in err
    assert plain > 2.5 * clean, (plain, clean)  # (the test means something: the specks do drag the light)
    assert fixed < 0.5 * plain and fixed < 1.7 * clean, (fixed, plain, clean)
    assert 1 <= rep["rounds"] <= 3
    # out/robust_weights.png shows where: the pixels it takes weight off are the spoiled ones
    from pipelines.io import images
    from pipelines.io.visibility_file import read_visibility

    pix = read_visibility(vis_file(scene)).samples.pixel
    lost = images.read_image(scene / "out" / "robust_weights.png").pixels.max(axis=2)[pix[:, 0], pix[:, 1]] > 0.5
    spoiled_px = _spoiled_mask(scene)[pix[:, 0], pix[:, 1]]
    assert (lost & spoiled_px).sum() >= 0.9 * lost.sum() and lost.sum() >= 0.5 * spoiled_px.sum(), (
        int(lost.sum()), int((lost & spoiled_px).sum()), int(spoiled_px.sum()))
    assert 0.6 * spoiled <= rep["down_weighted_pixels"] <= robust.MAX_DOWN_SHARE * rep["pixels"] + 1, (
        rep["down_weighted_pixels"], spoiled)


def test_the_solve_under_the_robust_weights_takes_over_the_systems_before(solved, tmp_path, monkeypatch):
    """Solving again under the robust weights, the tree systems of the solve before are taken over,
    corrected for the few rows whose weight changed (`rows.RowsPart.adopt`), not projected afresh:
    the light, its level and its errors are those of the solve that projects them afresh (to the
    rounding of the float32 exploration)."""
    from pipelines.light import rows as rows_module

    scene = copy_scene(solved, tmp_path / "specks")
    _specks(scene)
    taken = []
    adopt = rows_module.RowsPart.adopt

    def counted(self, other):
        n = adopt(self, other)
        taken.append(n)
        return n

    monkeypatch.setattr(rows_module.RowsPart, "adopt", counted)
    ok(invoke(scene, "solve", "--resolution", RES))
    over, over_probe = _report(scene), _probe_errors(scene)
    assert over["robust"]["rounds"] >= 1 and any(n for n in taken), taken  # (rows changed, systems taken over)
    monkeypatch.setattr(rows_module, "ADOPT_SHARE", -1.0)  # (nothing taken over: every system projected afresh)
    taken.clear()
    ok(invoke(scene, "solve", "--resolution", RES, "--force"))
    fresh, fresh_probe = _report(scene), _probe_errors(scene)
    assert not any(n is not None for n in taken)
    assert over["robust"]["rounds"] == fresh["robust"]["rounds"]
    assert over["robust"]["down_weighted_pixels"] == fresh["robust"]["down_weighted_pixels"]
    a, b = over["solution"], fresh["solution"]
    assert a["chosen_level"] == b["chosen_level"], (a["chosen_level"], b["chosen_level"])
    assert abs(a["held_out_rmse"] - b["held_out_rmse"]) <= 1e-3 * b["held_out_rmse"], (a["held_out_rmse"], b["held_out_rmse"])
    for k in ("diffuse", "glossy"):
        assert abs(over_probe[k] - fresh_probe[k]) <= 0.02 * fresh_probe[k], (k, over_probe, fresh_probe)


# -- a glossy scene: the specular term refitted under the weights -------------------------------------

def _spoil(photo, pixels, share=0.02, seed=5):
    """A copy of `photo` (LoadedImage) with dark specks and bright glints (3 x 3 blobs) over `share`
    of the used `pixels`."""
    from dataclasses import replace

    img = photo.pixels.copy()
    rng = np.random.default_rng(seed)
    mean = float(img[pixels[:, 0], pixels[:, 1]].mean())
    for k, i in enumerate(rng.choice(len(pixels), int(share * len(pixels) / 9), replace=False)):
        y, x = pixels[i]
        img[max(y - 1, 0):y + 2, max(x - 1, 0):x + 2] = 0.05 * mean if k % 2 else 8.0 * mean
    return replace(photo, pixels=img)


@pytest.mark.slow  # ~45 s: three glossy solves at R = 16
def test_glossy_fit_under_specks(forward_render):
    """teapot_sun_phong (Mitsuba, Blinn-Phong) at R = 16, --reflectance blinn-phong: 2 % of the pixels
    spoiled drag the plain fit's light and lobe; the robust pass (light and LM refitted under its
    weights) comes back near the clean photo's."""
    from pipelines.controllers.solve import ReflectanceOptions, SolveOptions, solve_scene
    from pipelines.io import images
    from pipelines.metrics import probe_errors
    from pipelines.model.materials import Material

    fr = forward_render("teapot_sun_phong", 16)
    photo = images.read_image(fr.scene.path / "image.exr")
    spoiled = _spoil(photo, fr.visibility.samples.pixel)
    view = fr.scene.pose.camera_centre

    def solve(ph, robust_on):
        r = solve_scene(fr.visibility, ph, Material(), SolveOptions(robust=robust_on), ReflectanceOptions("blinn-phong"))
        return r, probe_errors(r.solution.light, fr.visibility.cube, fr.light, fr.visibility.cube, view)

    clean, p_clean = solve(photo, True)
    plain, p_plain = solve(spoiled, False)
    fixed, p_fixed = solve(spoiled, True)
    # measured: clean 1.46 / 8.71 % (n 31.0), spoiled plain 3.66 / 10.90 % (n 28.3), robust 1.46 / 8.91 % (n 29.3).
    # (At R = 16 the light cannot hold the sun's peak: 0.8 % of the clean photo's pixels, the highlight's
    # core, are brighter than any prediction near them, and the clean photo is solved once more under
    # their weights; at the default R = 32 it is not: benchmarks/RESULTS.md, robust fit.)
    assert clean.report["robust"]["down_weighted_pixels"] <= 0.01 * clean.report["robust"]["pixels"]
    assert p_plain["diffuse"] > 2 * p_clean["diffuse"] and p_plain["glossy"] > 1.2 * p_clean["glossy"]
    assert p_fixed["diffuse"] < 1.2 * p_clean["diffuse"], (p_fixed, p_clean)
    assert p_fixed["glossy"] < p_plain["glossy"] - 0.3 * (p_plain["glossy"] - p_clean["glossy"]), (p_fixed, p_plain)
    assert any(r.kind == "robust" for r in fixed.reflectance.rounds)  # the LM refitted under the weights
    assert fixed.report["robust"]["down_weighted_pixels"] <= robust.MAX_DOWN_SHARE * fixed.report["robust"]["pixels"] + 1
    n = [m.material.shininess for m in (clean, plain, fixed)]
    assert abs(np.log(n[2] / n[0])) < abs(np.log(n[1] / n[0])) + 0.05, n


@pytest.mark.slow  # ~25 s: two glossy solves at R = 16
def test_auto_chooses_again_under_the_robust_weights(forward_render):
    """With --reflectance auto, the model is chosen again under the robust weights: the spoiled
    pixels took part in the first choice. At R = 16 that first choice is already right under these
    spoils (Blinn-Phong, seeds 1, 2, 3, 5); the case where the glints chose plastic is at R = 32
    (benchmarks/RESULTS.md, robust fit: seed 2's matte probe 3.5 -> 0.64 %, too slow for a test).
    This checks that auto chose again, on rows that no longer see the glints, and that the result
    has the clean photo's accuracy. Measured at R = 16, seeds 1, 2, 3, 5: plain 3.07 / 2.42 / 3.21 /
    3.88 % diffuse probe, robust 1.48 / 1.49 / 1.40 / 1.44 %, the clean photo's 1.46 %."""
    from pipelines.controllers.solve import ReflectanceOptions, SolveOptions, solve_scene
    from pipelines.io import images
    from pipelines.metrics import probe_errors
    from pipelines.model.materials import Material

    fr = forward_render("teapot_sun_phong", 16)
    photo = images.read_image(fr.scene.path / "image.exr")
    view = fr.scene.pose.camera_centre

    def solve(ph):
        r = solve_scene(fr.visibility, ph, Material(), SolveOptions(), ReflectanceOptions("auto"))
        return r, probe_errors(r.solution.light, fr.visibility.cube, fr.light, fr.visibility.cube, view)

    clean, p_clean = solve(photo)
    fixed, p_fixed = solve(_spoil(photo, fr.visibility.samples.pixel, seed=2))
    assert clean.material.model == fixed.material.model == "blinn-phong"
    assert "chosen again under the robust weights" in fixed.reflectance.decision
    # the candidates reported are the second choice's: its Lambertian held-out error is that of rows
    # without the glints (the first choice's was ~4x higher), near the clean photo's
    lam = fixed.reflectance.candidates["lambert"]["held_out_rmse"]
    assert lam < 1.5 * clean.reflectance.candidates["lambert"]["held_out_rmse"], (
        lam, clean.reflectance.candidates["lambert"])
    assert p_fixed["diffuse"] < 1.2 * p_clean["diffuse"], (p_fixed, p_clean)
    assert p_fixed["glossy"] < 1.15 * p_clean["glossy"], (p_fixed, p_clean)


@pytest.mark.slow  # ~40 s: two solves of a 320 x 240 textured scene at R = 32
def test_a_model_that_cannot_follow_the_texture_keeps_the_plain_solve(tmp_path):
    """spot_textured_sun with one uniform material: 0.3 % of the pixels (where the texture is far
    from grey) hold 27 % of the squared error; down-weighting them raises the plain relit error
    28.01 -> 29.33 % (and moved the sun from 0.9 to 40 deg off), so the check keeps the plain solve:
    the same light as --no-robust, bit for bit, and the report says why."""
    import h5py

    from pathlib import Path

    src = Path(__file__).parent / "data" / "scenes" / "spot_textured_sun"
    scene = copy_scene(src, tmp_path / "robust")
    plain = copy_scene(src, tmp_path / "plain")
    args = ("solve", "--reflectance", "lambert", "--single-material", "--single-view")
    err = ok(invoke(scene, *args))
    ok(invoke(plain, *args, "--no-robust"))
    rep = _report(scene)["robust"]
    assert rep["rounds"] >= 1 and rep["kept"] is False, rep
    p = rep["plain_relit_rmse"]
    assert p["after"] > 1.02 * p["before"]
    assert "robust pass not kept" in err and not (scene / "out" / "robust_weights.png").exists()
    assert _report(scene)["relit"]["relative_rmse_vs_photo"] == pytest.approx(p["before"], rel=1e-9)
    with h5py.File(scene / "out" / "coefficients.h5") as a, h5py.File(plain / "out" / "coefficients.h5") as b:
        np.testing.assert_array_equal(a["light"][()], b["light"][()])


def test_a_few_specks_that_do_not_steer_the_light_refit_its_tree_alone(solved, tmp_path, monkeypatch):
    """Four dead pixels move more than 1 % of the squared error but hardly the light: the chosen
    level's tree refitted under the weights moves the prediction by less than ROBUST_STILL of the
    noise, so its levels and model are kept, not explored again. The reference is the solve that
    explores them again (ROBUST_STILL = 0): held-out error within 3 %, probes within 5 %. A 2 %
    spoiled photo takes the whole re-solve (below)."""
    from pipelines.controllers import solve as solve_module

    from pipelines.io import images
    from pipelines.io.visibility_file import read_visibility

    scene = copy_scene(solved, tmp_path / "few")
    # four dead pixels (0 in every channel) on the object
    img = images.read_image(scene / "image.exr").pixels.copy()
    pix = read_visibility(vis_file(scene)).samples.pixel
    lit = pix[img[pix[:, 0], pix[:, 1]].mean(axis=1) > np.median(img[pix[:, 0], pix[:, 1]])]
    dead = lit[np.random.default_rng(11).choice(len(lit), 4, replace=False)]
    img[dead[:, 0], dead[:, 1]] = 0.0
    images.write_exr(scene / "image.exr", img)
    err = ok(invoke(scene, "solve", "--resolution", RES))
    quick, quick_probe = _report(scene), _probe_errors(scene)
    rep = quick["robust"]
    assert rep["rounds"] >= 1 and rep["down_weighted_pixels"] >= 4, rep  # (the test means something: the pass ran)
    assert rep["refit_change_sigmas"][0] < solve_module.ROBUST_STILL, rep
    assert "its levels and model kept" in err
    monkeypatch.setattr(solve_module, "ROBUST_STILL", 0.0)
    err = ok(invoke(scene, "solve", "--resolution", RES, "--force"))
    full, full_probe = _report(scene), _probe_errors(scene)
    assert "its levels and model kept" not in err
    # (the level may differ: these pixels also steered the first exploration, whose records are kept;
    # measured: level 2 kept against level 3 explored again, held-out 3.877 % against 3.836 %,
    # probes 1.53 / 14.08 % against 1.56 / 14.37 %)
    a, b = quick["solution"], full["solution"]
    assert abs(a["held_out_rmse"] - b["held_out_rmse"]) <= 0.03 * b["held_out_rmse"], (a["held_out_rmse"],
                                                                                      b["held_out_rmse"])
    for k in ("diffuse", "glossy"):
        assert abs(quick_probe[k] - full_probe[k]) <= 0.05 * full_probe[k], (k, quick_probe, full_probe)


def test_specks_that_steer_the_light_are_solved_again_in_full(solved, tmp_path):
    """2 % of the pixels spoiled: the refit on the kept tree moves the prediction by more than
    ROBUST_STILL of the noise, so the levels (and auto's model, once the weights settle) are explored
    again."""
    from pipelines.controllers import solve as solve_module

    scene = copy_scene(solved, tmp_path / "specks")
    _specks(scene)
    err = ok(invoke(scene, "solve", "--resolution", RES))
    rep = _report(scene)["robust"]
    assert rep["refit_change_sigmas"][0] >= solve_module.ROBUST_STILL, rep
    assert "robust pass 1: the light refitted" not in err and "robust pass 1:" in err
    # auto chose Lambert first: its second choice waits until the weights settle (the first pass's
    # weights, judged against a light the specks bent, catch 209 of the 254 pixels the last one
    # down-weights), so the Lambertian candidate it compares is the final light's (measured: held-out
    # 4.393 % against the final 4.393 %; chosen on the first pass's weights, 9.88 % against 4.37 %)
    assert "robust pass 1: the light moved by" in err and "chosen again once the weights settle" in err
    chosen = json.loads((scene / "out" / "reflectance.json").read_text())
    assert "chosen again under the robust weights" in chosen["decision"], chosen["decision"]
    final = _report(scene)["solution"]["held_out_rmse"]
    assert chosen["candidates"]["lambert"]["held_out_rmse"] <= 1.02 * final, (chosen["candidates"]["lambert"], final)
