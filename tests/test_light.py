"""The light solve (pipelines.light) on synthetic photos rendered through OUR forward model.

The geometry is a reference scene's (spot_overcast: cow + ground plane, a deterministic subset of
its used pixels, ray-cast visibility from the `forward_render` fixture); the photos are
`render.render` of a known light with a white Lambert material, so the model is exact and every
error left is the solver's (or the float32 transport's, see `test_noise_free_recovery`).

Measured numbers quoted in the docstrings/comments are from the code as of this writing; the
bounds leave a margin of a few x (never orders of magnitude) above them.
"""

import h5py
import numpy as np
import pytest
from hypothesis import event, given
from hypothesis import strategies as st
from scipy import optimize
from scipy.optimize import nnls as scipy_nnls

from pipelines.light import haar
from pipelines.light import solution as lt
from pipelines.io import light_file
from pipelines.light.bases import sh
from pipelines.light import bases
from pipelines.light.cubemap import CubeMap
from pipelines.light.haar import HaarTree
from pipelines.light.system import LightSystem, SystemPart, build_normal_equations, holdout_mask
from pipelines.model.materials import Material
from pipelines.model.render import render, transport
from property_helpers import props
from test_nnls import kkt_tolerance, objective_tolerance
from test_render import make_vis

SCENE = "spot_overcast"
STEP = 4  # every 4th used pixel: 13,080 pixels
WHITE = Material()
SUN_DIRECTION = np.array([0.5, 0.3, 0.6]) / np.linalg.norm([0.5, 0.3, 0.6])  # 41 deg elevation


# -- helpers ------------------------------------------------------------------------------------
def rel_rmse(values, reference) -> float:
    """sqrt(mean((values - reference)^2)) / sqrt(mean(reference^2)) over all pixels and channels."""
    return float(np.sqrt(np.mean((values - reference) ** 2) / np.mean(reference**2)))


def light_error(light, truth, cube, select=None) -> float:
    """Solid-angle weighted relative L2 error of a texel light (on `select` texels)."""
    w = cube.solid_angles[:, None]
    sel = slice(None) if select is None else select
    return float(np.sqrt(np.sum(w[sel] * (light[sel] - truth[sel]) ** 2) / np.sum(w[sel] * truth[sel] ** 2)))


def sun_sky(cube, sun=50.0, sky=0.2):
    """One bright texel (the sun) over a dim constant sky: (N, 3), and the sun's texel."""
    k = int(cube.lookup(SUN_DIRECTION))
    L = np.full((cube.n_texels, 3), sky)
    L[k] = sun
    return L, k


def add_noise(clean, fraction, seed):
    """Gaussian noise of standard deviation `fraction` x the mean: (noisy, noise)."""
    noise = fraction * clean.mean() * np.random.default_rng(seed).normal(size=clean.shape)
    return clean + noise, noise


def exact_normal_equations(vis, photo, held) -> LightSystem:
    """G = T'T, h = T'b in float64 from the dense transport in one product (the library folds
    blocks of rows on worker threads): an independent reference system for the noise-free checks."""
    D, _ = transport(vis.dense(), vis.samples.normal, vis.samples.view, vis.cube, WHITE)
    T = D.astype(np.float64)

    def part(sel):
        Ts, b = T[sel], photo[sel]
        return SystemPart(Ts.T @ Ts, Ts.T @ b, (b**2).sum(axis=0), int(sel.sum()), np.ones(3))

    return LightSystem(part(~held), part(held), 0.0)


def objective(part: SystemPart, light: np.ndarray) -> float:
    """Sum over channels of |T L_c - b_c|^2 - b'b = L'GL - 2 h'L (no clamping at zero)."""
    return float(sum(light[:, c] @ part.gram(c) @ light[:, c] - 2.0 * part.h[:, c] @ light[:, c]
                     for c in range(light.shape[1])))


# -- fixtures -----------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def scene8(forward_render):
    """(visibility, cube, held-out mask) at R = 8 on every 4th used pixel of spot_overcast."""
    vis = forward_render(SCENE, 8, STEP).visibility
    return vis, vis.cube, holdout_mask(vis.samples.pixel, 0.1)


@pytest.fixture(scope="module")
def sun_sky8(scene8):
    """Noise-free photo of the sun + sky light at R = 8, with library and float64 systems."""
    vis, cube, held = scene8
    L, sun = sun_sky(cube)
    photo = render(vis, L, WHITE)
    return {"light": L, "sun": sun, "photo": photo,
            "ne": build_normal_equations(vis, photo, WHITE, held_out=held),
            "exact": exact_normal_equations(vis, photo, held)}


# -- 1. noise-free recovery ---------------------------------------------------------------------
@pytest.mark.parametrize("levels", ["auto", 4])
def test_noise_free_recovery_is_exact_on_an_exact_system(scene8, sun_sky8, levels):
    """Sun + sky rendered by our model, solved with `wavelet` at the same R = 8 (levels auto with
    10 % held out, and 4 levels = down to single texels on the 8 x 8 top tile) on float64 normal
    equations: relit 1.9e-7 (fit_rmse) / 3.2e-7 and 2.0e-7 (rendered), light 3.1e-6 / 2.9e-6."""
    vis, cube, held = scene8
    L, sun, photo = sun_sky8["light"], sun_sky8["sun"], sun_sky8["photo"]
    sol = bases.solve(sun_sky8["exact"], cube, "wavelet", levels=levels)
    assert sol.fit_rmse < 1e-6
    assert rel_rmse(render(vis, sol.light, WHITE), photo) < 1e-6
    _, unobservable = lt.observability(sun_sky8["exact"])
    assert not unobservable.any()
    assert light_error(sol.light, L, cube) < 1e-4
    assert int(np.argmax(sol.light[:, 0])) == sun
    np.testing.assert_allclose(sol.light[sun], L[sun], rtol=1e-4)
    if levels == 4:  # the tree reached single texels at the sun
        assert haar.tree_depth_image(sol.tree)[sun] == 3


@pytest.mark.parametrize("levels", ["auto", 4])
def test_noise_free_recovery(scene8, sun_sky8, levels):
    """The same through `build_normal_equations`, the library's path (float64 G): relit error
    below 1e-6 relative, the light on every texel, the sun to 1e-4."""
    vis, cube, held = scene8
    L, sun, photo = sun_sky8["light"], sun_sky8["sun"], sun_sky8["photo"]
    sol = bases.solve(sun_sky8["ne"], cube, "wavelet", levels=levels)
    assert sol.basis == "wavelet"
    assert sol.fit_rmse < 1e-6
    assert rel_rmse(render(vis, sol.light, WHITE), photo) < 1e-6
    assert light_error(sol.light, L, cube) < 1e-4
    assert int(np.argmax(sol.light[:, 0])) == sun
    np.testing.assert_allclose(sol.light[sun], L[sun], rtol=1e-4)
    assert sol.solver["kkt_residual"] <= 1e-6 and not sol.solver["fallback"]
    assert np.all(sol.light >= 0)


# -- 2. noise ------------------------------------------------------------------------------------
def test_noisy_fit_is_at_the_noise_floor(scene8):
    """1 % (of the mean) Gaussian noise: the relit error against the noisy photo equals the noise's
    own relative RMSE (measured ratio 0.995) and against the clean render it is 10x below the
    noise (measured 0.101x)."""
    vis, cube, held = scene8
    L, sun = sun_sky(cube)
    clean = render(vis, L, WHITE)
    photo, noise = add_noise(clean, 0.01, seed=1)
    ne = build_normal_equations(vis, photo, WHITE, held_out=held)
    sol = bases.solve(ne, cube, "wavelet", levels="auto")
    relit = render(vis, sol.light, WHITE)
    noise_level = rel_rmse(photo - noise, photo)  # |noise| / |photo|
    assert rel_rmse(relit, photo) == pytest.approx(noise_level, rel=0.1)
    assert sol.fit_rmse == pytest.approx(noise_level, rel=0.1)
    assert rel_rmse(relit, clean) < 0.3 * rel_rmse(clean + noise, clean)
    assert int(np.argmax(sol.light[:, 0])) == sun


# -- 3. discrete ---------------------------------------------------------------------------------
def _block_sun_light(cube, block):
    """Sky 0.2 + a sun 50 filling one `block` x `block` texel block: representable by `discrete`
    at face resolution R / block."""
    tree = haar.uniform_tree(cube, cube.resolution // block)
    P = haar.leaf_matrix(tree)
    values = np.full(tree.n_leaves, 0.2)
    values[int(P.tocsr()[int(cube.lookup(SUN_DIRECTION))].indices[0])] = 50.0
    return np.repeat(np.asarray(P @ values)[:, None], 3, axis=1)


def _check_discrete(vis, face_resolution, block, relit_bound):
    cube = vis.cube
    L = _block_sun_light(cube, block)
    photo = render(vis, L, WHITE)
    ne = build_normal_equations(vis, photo, WHITE, held_out=holdout_mask(vis.samples.pixel, 0.1))
    sol = bases.solve(ne, cube, "discrete", face_resolution=face_resolution)
    assert sol.basis == "discrete" and sol.details["face_resolution"] == face_resolution
    assert sol.n_coefficients == 3 * face_resolution**2
    assert sol.solver["kkt_residual"] <= 1e-6
    assert sol.solver["fallback"] is False
    assert np.all(sol.light >= 0)
    relit = rel_rmse(render(vis, sol.light, WHITE), photo)
    assert relit < relit_bound
    return sol, relit


@pytest.mark.parametrize("face_resolution, block", [pytest.param(32, 1, marks=pytest.mark.slow), (16, 2)])
def test_discrete_at_32(forward_render, face_resolution, block):
    """R = 32 (3,072 texels) on every 4th used pixel (13,080): discrete at 32 x 32 and at 16 x 16
    (a sun of 2 x 2 texels) complete at a KKT point (measured 1e-10 / 1e-15) and fit the light
    (measured relit error 2.4e-4 / 7.7e-5: the float32 G's floor, see test_noise_free_recovery).
    Measured 13 s / 0.7 s for the solves (22 s for the 32 x 32 test with its visibility: slow).

    Fewer pixels than unknowns (every 64th pixel: 818) make the NNLS crawl (minutes; see the
    report), so this keeps the system overdetermined."""
    vis = forward_render(SCENE, 32, STEP).visibility
    _check_discrete(vis, face_resolution, block, 1e-3)


@pytest.mark.slow
@pytest.mark.xfail(run=False, reason="too slow for the suite, not failing: on this noise-free light almost every "
                   "texel is positive, so the free set holds ~9,600 of 12,288 texels and each step factors a "
                   "dense 9,600^2 block (measured: 7 iterations, KKT 1e-9, ~3 min per channel, ~10 min in all); "
                   "the noisy-photo case runs in the suite (test_discrete_at_64_on_the_photo); use --runxfail")
def test_discrete_at_64(forward_render):
    """R = 64 (12,288 unknowns, G is 1.2 GB) on every 4th used pixel (13,080, so that G has full
    rank; building it takes ~50 s): completes, KKT residual <= 1e-6, no fallback, and fits a light
    it can represent (a sun of 2 x 2 texels over a constant sky)."""
    vis = forward_render(SCENE, 64, STEP).visibility
    _check_discrete(vis, 64, 2, 1e-3)


@pytest.mark.slow
def test_discrete_at_64_on_the_photo(forward_render):
    """discrete at 64 x 64 faces (12,288 unknowns, G is 1.2 GB) on the noisy Mitsuba photo at every
    8th used pixel (6,540): completes at a KKT point without fallback, and relights the view as
    well as the wavelet solve on the same system (the photo's noise and the model's floor, ~0.6 %)."""
    from pipelines.io import images

    fr = forward_render(SCENE, 64, 8)
    vis = fr.visibility
    rows, cols = vis.samples.pixel[:, 0], vis.samples.pixel[:, 1]
    photo = images.read_image(fr.scene.path / "image.exr").pixels[rows, cols].astype(np.float64)
    ne = build_normal_equations(vis, photo, WHITE, held_out=holdout_mask(vis.samples.pixel, 0.1))
    sol = bases.solve(ne, vis.cube, "discrete", face_resolution=64)
    assert sol.n_coefficients == 12288
    assert sol.solver["kkt_residual"] <= 1e-6 and sol.solver["fallback"] is False
    assert np.all(sol.light >= 0)
    wavelet = bases.solve(ne, vis.cube, "wavelet")
    relit = rel_rmse(render(vis, sol.light, WHITE), photo)
    assert relit < 0.01
    assert relit <= rel_rmse(render(vis, wavelet.light, WHITE), photo) * 1.02


# -- 4. unobservable directions ------------------------------------------------------------------
@pytest.fixture(scope="module")
def half_blind(scene8):
    """The scene with V = 0 for every texel whose direction has x < 0 (half the texels)."""
    vis, cube, held = scene8
    V = vis.dense()
    blind = cube.directions[:, 0] < 0
    V[:, blind] = 0
    vis_half = make_vis(vis.samples, cube, V)
    L, sun = sun_sky(cube)  # the sun is at x > 0
    photo = render(vis_half, L, WHITE)
    return vis_half, blind, photo, build_normal_equations(vis_half, photo, WHITE, held_out=held)


@pytest.mark.parametrize("basis", ["wavelet", "quadtree", "discrete", "sh", "points"])
def test_unobservable_texels_get_no_light(scene8, half_blind, basis):
    """96 of 192 texels no pixel sees (G_ii = 0): every basis solves, observability flags exactly
    those texels, the light is exactly 0 on them and the count is reported. The tree and discrete
    bases still fit the photo (measured relit 9.7e-5 / 1.4e-4; points 1.5e-3; sh 0.10)."""
    vis, cube, held = scene8
    vis_half, blind, photo, ne = half_blind
    assert blind.sum() == cube.n_texels // 2
    relative, unobservable = lt.observability(ne)
    np.testing.assert_array_equal(unobservable, blind)
    assert np.all(relative[blind] == 0) and relative[~blind].min() > 0.01
    sol = bases.solve(ne, cube, basis)
    assert sol.details["unobservable_texels"] == int(blind.sum())
    assert np.all(sol.light[blind] == 0.0)
    relit = rel_rmse(render(vis_half, sol.light, WHITE), photo)
    assert np.isfinite(sol.fit_rmse)
    if basis in ("wavelet", "quadtree", "discrete"):
        assert relit < 1e-3 and sol.fit_rmse < 1e-3
    if basis == "points":
        assert relit < 1e-2
    if basis != "sh":
        assert sol.solver["kkt_residual"] <= 1e-6 and not sol.solver["fallback"]


# -- 5. wavelet = quadtree at the same tree ------------------------------------------------------
@pytest.fixture(scope="module")
def partial_sky(scene8):
    """Sun + a sky only above 30 deg elevation, 1 % noise: coarse trees need bound leaves."""
    vis, cube, held = scene8
    L, _ = sun_sky(cube)
    L[cube.directions[:, 2] < 0.5] = 0.0
    photo, _ = add_noise(render(vis, L, WHITE), 0.01, seed=2)
    return build_normal_equations(vis, photo, WHITE, held_out=held)


def _wavelet_level1_tree(ne, cube):
    return bases.solve(ne, cube, "wavelet", levels=2).levels[1].tree


@pytest.mark.parametrize("tree_source", ["full_depth_1", "wavelet_level_1"])
def test_wavelet_qp_and_quadtree_reach_the_same_objective(scene8, partial_sky, tree_source):
    """On one tree: the leaf-value NNLS (the quadtree's solve, and what `wavelet` solves per level)
    against the paper's QP in wavelet coefficients, min w'(B'GB)w - 2h'Bw s.t. Bw >= 0, solved by
    SLSQP (a general constrained solver). Objectives agree to 1e-6 relative (measured 4e-16 on
    the 36-coefficient full depth-1 tree), and the wavelet coefficients of the leaf solution
    synthesise the same texel light. The constraints matter: some leaves are bound at zero."""
    vis, cube, held = scene8
    ne = partial_sky
    tree = HaarTree.full(cube.tile_sizes, 1) if tree_source == "full_depth_1" else _wavelet_level1_tree(ne, cube)
    assert 9 < tree.n_coefficients <= 64
    P = haar.leaf_matrix(tree)
    leaf_part = ne.fit.project(P)
    x, info = lt.solve_nonnegative(leaf_part)
    assert info["kkt_residual"] <= 1e-9
    assert min(info["n_bound"]) > 0  # an active constraint: the QP is not just least squares
    B = haar.basis_matrix(tree).toarray()  # texels x coefficients, built independently of P
    Q, q = B.T @ ne.fit.G @ B, B.T @ ne.fit.h
    scale = float(np.abs(np.diag(Q)).max())
    for c in range(3):
        res = optimize.minimize(lambda w: (w @ Q @ w - 2 * q[:, c] @ w) / scale, np.zeros(B.shape[1]),
                                jac=lambda w: (2 * Q @ w - 2 * q[:, c]) / scale, method="SLSQP",
                                constraints=[{"type": "ineq", "fun": lambda w: B @ w, "jac": lambda w: B}],
                                options={"maxiter": 2000, "ftol": 1e-16})
        w = res.x
        assert (B @ w).min() > -1e-8 * np.abs(B @ w).max()
        qp = w @ Q @ w - 2 * q[:, c] @ w
        leaf = x[:, c] @ leaf_part.G @ x[:, c] - 2 * leaf_part.h[:, c] @ x[:, c]
        assert leaf == pytest.approx(qp, rel=1e-6)
        assert leaf <= qp + 1e-9 * abs(qp)  # the active-set optimum is no worse than SLSQP's
    coefficients = haar.leaf_values_to_coefficients(x, tree)
    np.testing.assert_allclose(B @ coefficients, P @ x, rtol=0, atol=1e-9 * np.abs(x).max())
    np.testing.assert_allclose(haar.synthesise(coefficients, tree), P @ x, rtol=0, atol=1e-9 * np.abs(x).max())
    # and the solvers' own levels on that tree hold exactly this solution
    if tree_source == "wavelet_level_1":
        level = bases.solve(ne, cube, "wavelet", levels=2).levels[1]
        np.testing.assert_allclose(level.coefficients, coefficients, rtol=1e-6, atol=1e-9 * np.abs(x).max())
        np.testing.assert_allclose(level.light, P @ x, rtol=1e-6, atol=1e-9 * np.abs(x).max())


# -- 6. spherical harmonics ----------------------------------------------------------------------
def test_real_sh_is_orthonormal_on_the_sphere():
    """Order 2 (9 columns) on a full-sphere cube map with exact solid angles as weights:
    |Y'WY - I| measured 6.4e-3 / 1.6e-3 / 4.0e-4 at R = 8 / 16 / 32 (midpoint rule, O(1/R^2))."""
    cube = CubeMap(32, hemisphere=False)
    Y = sh.real_sh(2, cube.directions)
    assert Y.shape == (cube.n_texels, 9)
    gram = Y.T @ (cube.solid_angles[:, None] * Y)
    np.testing.assert_allclose(gram, np.eye(9), atol=1e-3)
    # Y_00 is the constant 1 / sqrt(4 pi); Y_10 = sqrt(3 / 4 pi) z
    np.testing.assert_allclose(Y[:, 0], 0.5 / np.sqrt(np.pi), rtol=1e-12)
    np.testing.assert_allclose(Y[:, 2], np.sqrt(3 / (4 * np.pi)) * cube.directions[:, 2], rtol=1e-10, atol=1e-14)


SH_TRUTH = np.array([1.0, 0.1, 0.4, -0.15, 0.05, 0.08, 0.1, -0.06, 0.07])  # positive: 0.14 .. 0.58


def test_sh_recovers_a_low_order_light(scene8):
    """A light that is itself an order-2 SH (positive everywhere, tinted RGB), noise-free: the
    plain SH fit recovers it (measured light error 1.8e-4, relit 4.3e-6; the projected system's
    condition number is 7.5e5)."""
    vis, cube, held = scene8
    Y = sh.real_sh(2, cube.directions)
    L = (Y @ SH_TRUTH)[:, None] * np.array([1.0, 0.8, 0.6])
    assert L.min() > 0
    photo = render(vis, L, WHITE)
    ne = build_normal_equations(vis, photo, WHITE, held_out=held)
    sol = bases.solve(ne, cube, "sh", sh_order=2)
    assert sol.basis == "sh" and sol.n_coefficients == 9
    assert light_error(sol.light, L, cube) < 1e-3
    assert rel_rmse(render(vis, sol.light, WHITE), photo) < 1e-4
    assert sol.details["negative_fraction"] == 0.0
    np.testing.assert_allclose(sol.coefficients[:, 0], SH_TRUTH, atol=1e-2)
    # the non-negative variant has nothing to change here
    plus = bases.solve(ne, cube, "sh", sh_nonnegative=True)
    assert plus.basis == "sh+" and light_error(plus.light, L, cube) < 1e-3


def test_nonnegative_sh_never_goes_negative(scene8, sun_sky8):
    """Sun + sky: plain order-2 SH rings negative (measured 27 % of the texels, min -2.28) for a
    fit error of 8.66 %; `sh_nonnegative` keeps every texel >= 0 (measured min -2e-17) and pays
    for it (9.99 %), never gaining on the unconstrained optimum."""
    vis, cube, held = scene8
    plain = bases.solve(sun_sky8["ne"], cube, "sh")
    plus = bases.solve(sun_sky8["ne"], cube, "sh", sh_nonnegative=True)
    assert plain.details["negative_fraction"] > 0.05 and plain.light.min() < 0
    assert plus.basis == "sh+" and plus.details["nonnegative"] is True
    assert plus.light.min() >= -1e-9
    assert plus.details["min_radiance"] >= -1e-9
    assert plus.fit_rmse >= plain.fit_rmse * (1 - 1e-9)
    assert plus.fit_rmse == pytest.approx(rel_rmse(render(vis, plus.light, WHITE), sun_sky8["photo"]), rel=1e-3)


# -- 7. points -----------------------------------------------------------------------------------
def test_points_find_three_suns(scene8):
    """Three suns (three texels, one of them coloured), no sky, noise-free: `points` with levels
    "auto" ends with exactly those three lights (measured: 6 candidates tried, 3 kept at zero),
    their irradiances (to 5e-5 relative measured) and a relit error of 3.7e-6."""
    vis, cube, held = scene8
    dirs = np.array([[0.5, 0.3, 0.6], [-0.6, 0.2, 0.4], [0.1, -0.7, 0.5]])
    suns = cube.lookup(dirs / np.linalg.norm(dirs, axis=1, keepdims=True))
    assert len(set(suns.tolist())) == 3
    L = np.zeros((cube.n_texels, 3))
    L[suns[0]] = 40.0
    L[suns[1]] = [20.0, 25.0, 30.0]
    L[suns[2]] = 10.0
    photo = render(vis, L, WHITE)
    ne = build_normal_equations(vis, photo, WHITE, held_out=held)
    sol = bases.solve(ne, cube, "points", levels="auto")
    points = sol.details["points"]
    found = [p["texel"] for p in points]
    assert sorted(found) == sorted(suns.tolist())
    for p in points:
        np.testing.assert_allclose(p["direction"], cube.directions[p["texel"]], atol=1e-12)
        expected = L[p["texel"]] * cube.solid_angles[p["texel"]]
        np.testing.assert_allclose(p["irradiance_rgb"], expected, rtol=1e-3)
    assert sol.fit_rmse < 1e-4
    assert rel_rmse(render(vis, sol.light, WHITE), photo) < 1e-4
    assert set(np.flatnonzero(sol.light.max(axis=1) > 0).tolist()) == set(suns.tolist())


# -- 8. held-out model selection -----------------------------------------------------------------
@pytest.fixture(scope="module")
def smooth_sky16(forward_render):
    """A smooth sky (0.5 + z + 0.3 x, no sun) at R = 16 with 1 % noise: refinement saturates."""
    vis = forward_render(SCENE, 16, STEP).visibility
    cube = vis.cube
    sky = 0.5 + cube.directions[:, 2] + 0.3 * cube.directions[:, 0]
    photo, _ = add_noise(render(vis, np.repeat(sky[:, None], 3, axis=1), WHITE), 0.01, seed=3)
    held = holdout_mask(vis.samples.pixel, 0.1)
    return vis, cube, build_normal_equations(vis, photo, WHITE, held_out=held)


@pytest.mark.parametrize("basis", ["wavelet", "quadtree"])
def test_auto_levels_stop_before_overfitting(smooth_sky16, basis):
    """Refining to single texels overfits the noise (measured held-out 0.984 % at 144
    coefficients -> 1.001 % at 768); "auto" stops early (measured 3 of 5 levels, keeping 36
    coefficients at 0.986 %) and keeps a level whose held-out error is within min_gain of the best
    seen and not worse than the last level's."""
    vis, cube, ne = smooth_sky16
    min_gain = 0.01
    auto = bases.solve(ne, cube, basis, levels="auto", min_gain=min_gain)
    full = bases.solve(ne, cube, basis, levels=64)  # until the tree stops changing
    assert full.levels[-1].n_coefficients == cube.n_texels
    held_full = [lv.held_out_rmse for lv in full.levels]
    assert held_full[-1] > min(held_full)  # the finest level is overfitted
    chosen = auto.levels[auto.chosen].held_out_rmse
    held_auto = [lv.held_out_rmse for lv in auto.levels]
    assert chosen <= auto.levels[-1].held_out_rmse * (1 + min_gain)
    assert chosen <= min(held_auto) * (1 + min_gain)
    assert chosen <= held_full[-1]
    assert len(auto.levels) < len(full.levels)
    assert auto.n_coefficients < cube.n_texels // 2
    # the first len(auto) levels are the same refinement in both runs
    for a, b in zip(auto.levels, full.levels):
        assert a.n_coefficients == b.n_coefficients and a.held_out_rmse == pytest.approx(b.held_out_rmse)


# -- 9. storage ----------------------------------------------------------------------------------
@pytest.mark.parametrize("basis", ["wavelet", "points"])
def test_solution_file_round_trip(scene8, sun_sky8, tmp_path, basis):
    vis, cube, held = scene8
    ne = sun_sky8["ne"]
    sol = bases.solve(ne, cube, basis, levels=3 if basis == "wavelet" else "auto")
    _, unobservable = lt.observability(ne)
    path = tmp_path / "light.h5"
    light_file.write_solution(path, sol, cube, unobservable, attrs={"scene": SCENE})
    light, cube_back, attrs = light_file.read_solution_light(path)
    assert cube_back == cube
    np.testing.assert_allclose(light, sol.light, rtol=1e-6, atol=0)  # stored as float32
    assert attrs["basis"] == basis and attrs["resolution"] == 8 and bool(attrs["hemisphere"])
    assert attrs["chosen_level"] == sol.chosen and attrs["scene"] == SCENE
    with h5py.File(path, "r") as f:
        np.testing.assert_array_equal(f["coefficients"][:], sol.coefficients)
        np.testing.assert_array_equal(f["unobservable"][:], unobservable)
        assert len(f["levels"]) == len(sol.levels)
        if basis == "wavelet":
            assert light_file.read_tree(f["tree"]) == sol.tree
            assert f["tree/coefficient_index"].shape == (sol.tree.n_coefficients, 5)
            assert f["tree/leaves"].shape == (sol.tree.n_leaves, 4)
            for lv in sol.levels:
                assert light_file.read_tree(f[f"levels/{lv.index:02d}/tree"]) == lv.tree
                assert f[f"levels/{lv.index:02d}"].attrs["fit_rmse"] == lv.fit_rmse
        else:
            assert "tree" not in f
            np.testing.assert_allclose(f["points/direction"][:], [p["direction"] for p in sol.details["points"]])
    with h5py.File(tmp_path / "other.h5", "w") as f:
        f.attrs["format"] = "something-else"
    with pytest.raises(ValueError):
        light_file.read_solution_light(tmp_path / "other.h5")


# == properties (hypothesis): the light solve on random small scenes =============================
#
# Random non-negative transports at a tiny cube map (12, 24 or 48 texels), a random non-negative
# light, noise, a held-out pixel set or none, and the three channel layouts of SystemPart (one G
# for all channels; G shared up to channel_scale a_c, T_c = a_c T, as build_normal_equations makes
# for proportional kd, ks; one G per channel). Entries are 0 or in [0.01, 1] (the dynamic range of
# the NNLS section: blind texels are exactly zero columns).

_CUBES: dict[tuple[int, bool], CubeMap] = {}


def cube_map(R: int, hemisphere: bool) -> CubeMap:
    if (R, hemisphere) not in _CUBES:
        _CUBES[R, hemisphere] = CubeMap(R, hemisphere)
    return _CUBES[R, hemisphere]


@st.composite
def light_scenes(draw):
    R, hemisphere = draw(st.sampled_from([(2, True), (2, False), (4, True)]))
    cube = cube_map(R, hemisphere)
    N = cube.n_texels
    m = draw(st.integers(1, 40))
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    density = draw(st.sampled_from([0.1, 0.4, 1.0]))

    def transport():
        return rng.uniform(0.01, 1.0, (m, N)) * (rng.random((m, N)) < density)

    T = transport()
    blind = np.zeros(N, bool)
    blind[draw(st.lists(st.integers(0, N - 1), max_size=N // 2))] = True
    kind = draw(st.sampled_from(["suns", "sky", "random", "zero"]))
    L = np.zeros((N, 3))
    if kind == "suns":
        L[rng.integers(0, N, rng.integers(1, 4))] = rng.uniform(1, 50, (1, 3))
    elif kind == "sky":
        L[:] = rng.uniform(0.1, 1.0, 3)
    elif kind == "random":
        L = rng.uniform(0, 1, (N, 3)) * (rng.random((N, 1)) < 0.5)
    layout = draw(st.sampled_from(["shared", "scaled", "per-channel"]))
    if layout == "shared":
        a = None
        Ts = [T, T, T]
    elif layout == "scaled":
        a = np.array(draw(st.lists(st.sampled_from([0.0, 0.25, 1.0]) | st.floats(0.01, 2.0), min_size=3, max_size=3)))
        Ts = [a[c] * T for c in range(3)]
    else:
        a = None
        Ts = [rng.uniform(0.2, 2.0) * T + 0.5 * transport() for _ in range(3)]
    Ts = [np.where(blind[None, :], 0.0, Tc) for Tc in Ts]
    clean = np.column_stack([Ts[c] @ L[:, c] for c in range(3)])
    noise = draw(st.sampled_from([0.0, 1e-3, 0.1, 1.0]))
    b = clean + noise * max(float(np.abs(clean).mean()), 1e-3) * rng.normal(size=(m, 3))
    held = rng.random(m) < draw(st.sampled_from([0.0, 0.0, 0.3]))

    def part(sel) -> SystemPart:
        bs = b[sel]
        bb = (bs**2).sum(axis=0)
        if layout == "per-channel":
            G = np.stack([Tc[sel].T @ Tc[sel] for Tc in Ts])
            h = np.column_stack([Ts[c][sel].T @ bs[:, c] for c in range(3)])
            return SystemPart(G, h, bb, int(sel.sum()))
        base = T[sel] * ~blind[None, :]
        h = base.T @ bs
        if a is not None:
            h = h * a[None, :]  # T_c = a_c T: h_c = a_c T'b_c, G_c = a_c^2 T'T
        return SystemPart(base.T @ base, h, bb, int(sel.sum()), a)

    ne = LightSystem(part(~held), part(held), 0.0)
    return {"cube": cube, "Ts": Ts, "b": b, "blind": blind, "ne": ne, "truth": L,
            "seed": int(rng.integers(0, 2**32))}


def direct_residual(Ts, b, light) -> float:
    """sum_c |T_c L_c - b_c|^2 over all pixels, from the transport itself (not from G)."""
    return float(sum(np.sum((Ts[c] @ light[:, c] - b[:, c]) ** 2) for c in range(3)))


def residual_tolerance(Ts, b, *lights) -> float:
    """Rounding of |TL - b|^2 and of the solves: 1e-9 of the sizes involved (the NNLS is exact to
    ~1e-14 of them; float64 G, no float32 anywhere here)."""
    size = float(np.sum(b**2)) + sum(float(sum(np.sum((Ts[c] @ L[:, c]) ** 2) for c in range(3))) for L in lights)
    return 1e-9 * size + 1e-300


BASIS_CASES = [("wavelet", False), ("quadtree", False), ("discrete", False), ("points", False), ("sh", True),
               ("sh", False)]


@props(60)
@pytest.mark.parametrize("basis, sh_nonnegative", BASIS_CASES)
@given(scene=light_scenes(), levels=st.sampled_from(["auto", 1, 2, 3]))
def test_light_solve_is_non_negative_and_fits_no_worse_than_no_light(basis, sh_nonnegative, scene, levels):
    cube, Ts, b, ne = scene["cube"], scene["Ts"], scene["b"], scene["ne"]
    sol = bases.solve(ne, cube, basis, levels=levels, sh_nonnegative=sh_nonnegative)
    light = sol.light
    assert light.shape == (cube.n_texels, 3) and np.all(np.isfinite(light))
    peak = float(np.abs(light).max(initial=0.0))
    if basis != "sh" or sh_nonnegative:  # plain SH is allowed negative lobes (the paper's baseline)
        assert light.min(initial=0.0) >= -1e-12 * peak, f"negative radiance {light.min():.3g} (peak {peak:.3g})"
    # texels no pixel sees get no light (module docstring: they stay zero in every output)
    assert np.all(light[scene["blind"]] == 0.0)
    ours, zero = direct_residual(Ts, b, light), float(np.sum(b**2))
    tol = residual_tolerance(Ts, b, light)
    assert ours <= zero + tol, f"worse than no light: {ours:.6g} > {zero:.6g}"
    event("lit" if np.any(light != 0) else "dark")
    # the reported error is the error of the light it returns
    both_bb = float(np.sum(b**2))
    if both_bb > 0:
        assert abs(sol.fit_rmse**2 * both_bb - ours) <= tol + 1e-9 * both_bb, (sol.fit_rmse**2 * both_bb, ours)
        both = ne.fit.combine(ne.held_out)
        assert abs(both.residual(light).sum() - ours) <= tol + 1e-9 * both_bb  # SystemPart.residual agrees
    if basis != "points":
        # a constant light is in the span of every other basis (SH's l = 0 term, a tree's roots, the
        # texels): no worse than the best non-negative constant light
        P = np.ones((cube.n_texels, 1))
        best = np.column_stack([P @ scipy_nnls(Ts[c] @ P, b[:, c])[0] for c in range(3)])
        assert ours <= direct_residual(Ts, b, best) + residual_tolerance(Ts, b, light, best), \
            "the best constant light is better"
    if basis in ("wavelet", "quadtree"):
        # the chosen tree refines the 9 (or 6) tile roots: no worse than the best constant per tile
        from pipelines.light import haar
        P = haar.leaf_matrix(haar.HaarTree.roots(cube.tile_sizes)).toarray()
        best = np.column_stack([P @ scipy_nnls(Ts[c] @ P, b[:, c], maxiter=1000)[0] for c in range(3)])
        assert ours <= direct_residual(Ts, b, best) + residual_tolerance(Ts, b, light, best), \
            "a tile-constant light is better"
    if basis == "points":
        # the final lights are the NNLS optimum on their own directions (re-solved on all pixels)
        on = np.flatnonzero(np.any(light > 0, axis=1))
        best = np.zeros_like(light)
        for c in range(3):
            best[on, c] = scipy_nnls(Ts[c][:, on], b[:, c], maxiter=1000)[0] if len(on) else 0.0
        assert ours <= direct_residual(Ts, b, best) + residual_tolerance(Ts, b, light, best), \
            "other intensities of the same point lights fit better"


@props(100)
@given(scene=light_scenes(), data=st.data())
def test_discrete_light_is_no_worse_than_random_non_negative_lights(scene, data):
    cube, Ts, b = scene["cube"], scene["Ts"], scene["b"]
    sol = bases.solve(scene["ne"], cube, "discrete")
    light = sol.light
    assert np.all(light >= 0) and np.all(np.isfinite(light))
    ours = direct_residual(Ts, b, light)
    rng = np.random.default_rng(scene["seed"])
    N = cube.n_texels
    scale = max(float(light.max(initial=0.0)), float(scene["truth"].max(initial=0.0)), 1.0)
    candidates = {"truth": scene["truth"], "zero": np.zeros((N, 3))}
    for k in range(data.draw(st.integers(1, 6), label="random probes")):
        kind = data.draw(st.sampled_from(["uniform", "sparse", "around", "one texel"]), label=f"probe {k}")
        if kind == "uniform":
            p = rng.uniform(0, scale, (N, 3))
        elif kind == "sparse":
            p = rng.uniform(0, 2 * scale, (N, 3)) * (rng.random((N, 1)) < 0.2)
        elif kind == "around":
            p = light + 10.0 ** rng.uniform(-6, 0) * scale * rng.normal(size=(N, 3))
        else:
            p = light.copy()
            p[rng.integers(N)] += 10.0 ** rng.uniform(-6, 0) * scale * rng.choice([-1, 1], 3)
        candidates[f"{kind} {k}"] = np.maximum(p, 0.0)
    for name, p in candidates.items():
        theirs = direct_residual(Ts, b, p)
        # KKT within 1e-7 of the gradient's scale (section 2) bounds how much any feasible light
        # can gain: 2 x 1e-7 (max|G| |L|_1 + max|h|) |p - L|_1 per channel, plus rounding
        gain = 0.0
        for c in range(3):
            G, h = Ts[c].T @ Ts[c], Ts[c].T @ b[:, c]
            gain += 2 * objective_tolerance(G, h, light[:, c], p[:, c], kkt_tolerance(G, h, light[:, c]))
        assert ours <= theirs + gain + residual_tolerance(Ts, b, light, p), f"{name}: {ours:.8g} > {theirs:.8g}"


def rescaled(ne: LightSystem, s: float) -> LightSystem:
    """The same scene photographed s times brighter: h -> s h, b'b -> s^2 b'b (G unchanged)."""
    def part(p: SystemPart) -> SystemPart:
        return SystemPart(p.G, s * p.h, s * s * p.bb, p.n_pixels, p.channel_scale)
    return LightSystem(part(ne.fit), part(ne.held_out), ne.seconds)


@props(25)
@pytest.mark.parametrize("basis, sh_nonnegative", [c for c in BASIS_CASES if c != ("sh", True)])
@given(scene=light_scenes(), k=st.sampled_from([-30, -10, 10, 30]))
def test_light_solve_is_brightness_equivariant(basis, sh_nonnegative, scene, k):
    """A photo 2^k times brighter gives a light 2^k times brighter: every threshold of the solve is
    relative (power-of-two scaling is exact in floating point, so only rounding could differ).
    Nonnegative SH is left out: SLSQP's stopping rule and its start are not scale-free (the fit
    of one scene differs between brightness 1 and 2^20), so only its fit is checked (above)."""
    cube, ne = scene["cube"], scene["ne"]
    one = bases.solve(ne, cube, basis, levels="auto", sh_nonnegative=sh_nonnegative).light
    s = 2.0**k
    other = bases.solve(rescaled(ne, s), cube, basis, levels="auto", sh_nonnegative=sh_nonnegative).light
    np.testing.assert_allclose(other, s * one, rtol=1e-9, atol=1e-12 * s * float(np.abs(one).max(initial=0.0)))


def test_nonnegative_sh_fits_no_worse_than_no_light_when_dim():
    """Was: light._sh_nonnegative ran SLSQP with an absolute ftol (1e-15) on an objective that
    scales with the photo's brightness squared: for a dim photo it stopped at its (shifted
    least-squares) start, here 4.6 x worse than no light at all."""
    cube = cube_map(2, True)
    N, m = cube.n_texels, 2
    rng = np.random.default_rng(5)
    T = rng.uniform(0.01, 1, (m, N)) * (rng.random((m, N)) < 0.4)
    L = np.zeros((N, 3))
    L[3] = 1.0
    b = (T @ L + 0.1 * rng.normal(size=(m, 3))) * 2.0**-30
    part = SystemPart(T.T @ T, T.T @ b, (b**2).sum(axis=0), m)
    empty = SystemPart(np.zeros((N, N)), np.zeros((N, 3)), np.zeros(3), 0)
    light = bases.solve(LightSystem(part, empty, 0.0), cube, "sh", sh_nonnegative=True).light
    assert np.all(light >= 0)
    assert direct_residual([T] * 3, b, light) <= float(np.sum(b**2)) * (1 + 1e-9)


def test_nonnegative_sh_on_one_dark_pixel():
    """One pixel, a slightly negative (noise) value: G is rank one, and no light is the best
    non-negative light. SLSQP must not wander off along G's null space, where G's rounding makes
    huge coefficients (~1e6) look better than zero while the light fits far worse (found by
    test_light_solve_is_non_negative_and_fits_no_worse_than_no_light; exact values matter)."""
    cube = cube_map(2, True)
    T = np.array([[0.5167034084532541, 0.950959059362676, 0.15271801659243742, 0.9491629526658715,
                   0.3187131374903806, 0.4290931844828499, 0.8294255678822373, 0.4151071450054697,
                   0.554097750796329, 0.037283522110637686, 0.7559779775880585, 0.5427618800870855]])
    b = np.full((1, 3), -1.7477209205516195e-07)
    part = SystemPart(T.T @ T, T.T @ b, (b**2).sum(axis=0), 1)
    empty = SystemPart(np.zeros((12, 12)), np.zeros((12, 3)), np.zeros(3), 0)
    light = bases.solve(LightSystem(part, empty, 0.0), cube, "sh", sh_nonnegative=True).light
    assert np.all(light >= 0)
    assert direct_residual([T] * 3, b, light) <= float(np.sum(b**2)) * (1 + 1e-9)
