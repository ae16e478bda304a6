"""Tests for the forward model (pipelines.render) on hand-built visibility data."""

import math

import numpy as np
import pytest
from scipy.integrate import quad

from pipelines.geometry.camera import PixelSamples
from pipelines.light.cubemap import CubeMap
from pipelines.model.materials import Material
from pipelines.model.render import lobe_cosines, lobe_norm, pixels_to_image, render, specular_factors, transport
from pipelines.geometry.visibility import VisibilityData


def unit(v):
    v = np.asarray(v, float)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def make_samples(normals, views=None) -> PixelSamples:
    n = unit(np.atleast_2d(normals))
    v = n.copy() if views is None else unit(np.atleast_2d(views))
    P = len(n)
    return PixelSamples(pixel=np.column_stack([np.zeros(P), np.arange(P)]).astype(np.int32),
                        position=np.zeros((P, 3)), normal=n, geometric_normal=n.copy(), view=v,
                        face=np.zeros(P, np.int64))


def make_vis(samples, cube, V=None, supersample=1) -> VisibilityData:
    """VisibilityData in memory; V (P, N) in {0, 1} (bits) or [0, 1] (fractions), default all ones."""
    P = len(samples)
    V = np.ones((P, cube.n_texels)) if V is None else np.asarray(V)
    if supersample == 1:
        stored = np.packbits(V.astype(bool), axis=1, bitorder="little")
    else:
        stored = np.round(255.0 * V).astype(np.uint8)
    return VisibilityData(samples, cube, supersample, stored)


LAMBERT = Material()
UP, WALL_X, WALL_Y = [0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, -1.0, 0.0]


# -- Lambertian normalisation --------------------------------------------------------------------
@pytest.mark.parametrize("R", [16, 32, 64])
def test_white_upward_patch_under_unit_sky_renders_one(R):
    cube = CubeMap(R)
    vis = make_vis(make_samples([UP]), cube)
    out = render(vis, np.ones(cube.n_texels), LAMBERT)
    assert out.shape == (1, 3)
    np.testing.assert_allclose(out, 1.0, atol=1e-3)


@pytest.mark.parametrize("R", [16, 32, 64])
@pytest.mark.parametrize("wall", [WALL_X, WALL_Y, [-0.6, 0.8, 0.0]], ids=["x", "-y", "oblique"])
def test_vertical_wall_sees_half_the_sky(R, wall):
    """Hemisphere mode: a wall (horizontal normal) sees half of the upper hemisphere -> 0.5."""
    cube = CubeMap(R)
    out = render(make_vis(make_samples([wall]), cube), np.ones(cube.n_texels), LAMBERT)
    np.testing.assert_allclose(out, 0.5, atol=1e-3)


@pytest.mark.parametrize("R", [16, 64])
def test_wall_in_sphere_mode_with_sky_only_above(R):
    """Full-sphere cube map, radiance 1 on z > 0 texels only: same 0.5; the ground-lit wall too."""
    cube = CubeMap(R, hemisphere=False)
    sky = (cube.directions[:, 2] > 0).astype(float)
    samples = make_samples([WALL_X, UP, [0.0, 0.0, -1.0]])
    out = render(make_vis(samples, cube), sky, LAMBERT)
    np.testing.assert_allclose(out[0], 0.5, atol=1e-3)
    np.testing.assert_allclose(out[1], 1.0, atol=1e-3)
    np.testing.assert_allclose(out[2], 0.0, atol=1e-12)  # faces the ground: no sky
    # uniform light over the whole sphere: any orientation sees a full hemisphere
    full = render(make_vis(samples, cube), np.ones(cube.n_texels), LAMBERT)
    np.testing.assert_allclose(full, 1.0, atol=1e-3)


@pytest.mark.parametrize("tilt", [0.3, 0.8, 1.2])
def test_tilted_patch_sees_its_share_of_the_sky(tilt):
    """A patch tilted by a from the vertical under the upper sky: (1 + cos a) / 2."""
    cube = CubeMap(64)
    n = [math.sin(tilt), 0.0, math.cos(tilt)]
    out = render(make_vis(make_samples([n]), cube), np.ones(cube.n_texels), LAMBERT)
    np.testing.assert_allclose(out, (1 + math.cos(tilt)) / 2, atol=1e-3)


def test_rgb_albedo_and_light_scale_channels():
    cube = CubeMap(32)
    samples = make_samples([UP, WALL_X])
    vis = make_vis(samples, cube)
    kd = (0.2, 0.5, 0.9)
    out = render(vis, np.ones(cube.n_texels), Material(kd=kd))
    white = render(vis, np.ones(cube.n_texels), LAMBERT)
    np.testing.assert_allclose(out, white * np.array(kd), rtol=1e-6)
    np.testing.assert_allclose(out[0], kd, atol=1e-3)
    # RGB light: channel c scales by L_c; linear in the light
    L = np.ones((cube.n_texels, 3)) * np.array([3.0, 0.5, 0.0])
    out2 = render(vis, L, Material(kd=kd))
    np.testing.assert_allclose(out2, out * np.array([3.0, 0.5, 0.0]), rtol=1e-6)


def _subtexel_rule(cube, k):
    """Sub-texel directions (k*k, N, 3) and exact solid angles (k*k, N), in float64, from the face
    geometry (independent of CubeMap.quadrature)."""
    from pipelines.light.cubemap import face_rectangle_solid_angle

    R = cube.resolution
    dirs, weights = [], []
    for orow in range(k):
        for ocol in range(k):
            s0 = -1.0 + 2.0 * (cube.texel_col + ocol / k) / R
            t0 = -1.0 + 2.0 * (cube.texel_row + orow / k) / R
            weights.append(face_rectangle_solid_angle(s0, s0 + 2.0 / (R * k), t0, t0 + 2.0 / (R * k)))
            dirs.append(cube.face_directions(s0 + 1.0 / (R * k), t0 + 1.0 / (R * k)))
    return np.array(dirs), np.array(weights)


def projected_solid_angles(normals, cube, k=24):
    """(P, N) the diffuse transport's definition: max(0, N . integral of d over the texel)."""
    dirs, w = _subtexel_rule(cube, k)
    m = np.einsum("snk,sn->nk", dirs, w)
    return np.maximum(np.asarray(normals, float) @ m.T, 0.0)


def test_vector_solid_angle_gives_the_exact_cosine_integral():
    """For texels wholly in front of N, N . m equals the integral of N . d over the texel."""
    cube = CubeMap(8)
    normals = unit(np.random.default_rng(3).normal(size=(6, 3)) + [0, 0, 0.5])
    dirs, w = _subtexel_rule(cube, 32)
    cosines = np.einsum("pk,snk->psn", normals, dirs)
    exact = np.einsum("psn,sn->pn", np.maximum(cosines, 0), w)
    front = (cosines > 0).all(axis=1)
    approx = np.maximum(normals @ cube.vector_solid_angles.T, 0)
    np.testing.assert_allclose(approx[front], exact[front], rtol=5e-4)  # 16x16 vs 32x32 midpoint rules
    # straddling texels: the clamp is an approximation, within a texel's solid angle
    assert np.abs(approx - exact)[~front].max() < cube.solid_angles.max()
    # the texel-centre rule, by contrast, is off by O(1/R^2) even for texels in front
    centre = np.maximum(normals @ cube.directions.T, 0) * cube.solid_angles
    assert np.abs(centre - exact)[front].max() > 10 * np.abs(approx - exact)[front].max()


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_render_matches_the_sum_with_stored_visibility_bits(seed):
    """Random visibility bits (little bit order), random normals and light: I = sum L w V cos / pi."""
    rng = np.random.default_rng(seed)
    cube = CubeMap(8)
    normals = unit(rng.normal(size=(25, 3)) + [0, 0, 1.0])
    V = rng.random((25, cube.n_texels)) < 0.6
    L = rng.random((cube.n_texels, 3)) * 5.0
    vis = make_vis(make_samples(normals), cube, V)
    assert vis.encoding == "bits"
    np.testing.assert_array_equal(vis.dense(), V.astype(np.float32))
    kd = np.array([0.9, 0.6, 0.3])
    out = render(vis, L, Material(kd=tuple(kd)), rows=7)  # several blocks
    expected = kd * ((V * projected_solid_angles(normals, cube) / np.pi) @ L)
    np.testing.assert_allclose(out, expected, rtol=1e-4)


@pytest.mark.parametrize("model", ["lambert", "blinn-phong", "plastic"])
def test_render_in_blocks_on_both_cores_equals_one_block(model):
    """Blocks of rows formed on two threads (each its own transport) give what one block gives,
    per-pixel albedo and matte / scaled specular rows included."""
    rng = np.random.default_rng(3)
    cube = CubeMap(8)
    P = 41
    normals = unit(rng.normal(size=(P, 3)) + [0, 0, 1.5])
    views = unit(rng.normal(size=(P, 3)) * 0.3 + [0, 0, 1.0])
    V = rng.random((P, cube.n_texels)) < 0.7
    L = rng.random((cube.n_texels, 3)) * 3.0
    vis = make_vis(make_samples(normals, views), cube, V)
    m = Material(kd=(0.8, 0.6, 0.4), ks=(0.3, 0.3, 0.3), shininess=25.0, model=model, roughness=0.2)
    if model == "lambert":
        m = Material(kd=(0.8, 0.6, 0.4))
    albedo = rng.random((P, 3)) + 0.5
    specular = rng.choice([0.0, 1.0, 0.5], size=P)
    whole = render(vis, L, m, rows=P, albedo=albedo, specular=specular)
    blocks = render(vis, L, m, rows=5, albedo=albedo, specular=specular)
    assert np.abs(whole).max() > 0.1
    np.testing.assert_allclose(blocks, whole, rtol=1e-6, atol=1e-9)
    if model != "lambert":  # the matte rows were rendered without the lobe (and a plastic's coating)
        lobe_everywhere = render(vis, L, m, rows=5, albedo=albedo)
        matte = specular == 0
        assert np.abs(lobe_everywhere[matte] - blocks[matte]).min() > 1e-4
        if model == "blinn-phong":  # (a lobe only adds light; a coating also takes some off the base)
            assert (lobe_everywhere[matte] > blocks[matte]).all()


def test_render_of_no_pixels_is_empty():
    cube = CubeMap(8)
    empty = make_vis(make_samples(np.zeros((0, 3))), cube)
    assert empty.n_pixels == 0
    out = render(empty, np.ones(cube.n_texels), Material(kd=(0.5, 0.5, 0.5)))
    assert out.shape == (0, 3)


def test_half_visible_sky_halves_the_light():
    cube = CubeMap(32)
    d = cube.directions
    V = np.stack([np.ones(cube.n_texels), d[:, 1] > 0, d[:, 0] < 0]).astype(float)
    samples = make_samples([UP, UP, UP])
    out = render(make_vis(samples, cube, V), np.ones(cube.n_texels), LAMBERT)
    np.testing.assert_allclose(out[1], 0.5 * out[0], rtol=1e-6)
    np.testing.assert_allclose(out[2], 0.5 * out[0], rtol=1e-6)


def test_fraction_encoded_visibility_scales_the_light():
    cube = CubeMap(16)
    samples = make_samples([UP, UP])
    V = np.stack([np.full(cube.n_texels, 1.0), np.full(cube.n_texels, 128 / 255)])
    vis = make_vis(samples, cube, V, supersample=2)
    assert vis.encoding == "fraction"
    out = render(vis, np.ones(cube.n_texels), LAMBERT)
    np.testing.assert_allclose(out[1], out[0] * 128 / 255, rtol=1e-6)
    np.testing.assert_allclose(out[0], 1.0, atol=2e-3)


def test_sun_texel_gives_cosine_law():
    cube = CubeMap(32)
    k = int(cube.lookup(unit([0.3, 0.2, 0.9])))
    d = cube.directions[k]
    L = np.zeros(cube.n_texels)
    L[k] = 100.0
    normals = [UP, WALL_X, unit([1.0, 0.0, 1.0]), [0.0, 0.0, -1.0]]
    out = render(make_vis(make_samples(normals), cube), L, LAMBERT)
    expected = 100.0 * projected_solid_angles(unit(normals), cube)[:, k] / np.pi
    np.testing.assert_allclose(out[:, 0], expected, rtol=1e-4)
    # close to the point-light cosine law at the texel centre (a 2.8 degree texel)
    np.testing.assert_allclose(out[:3, 0], 100.0 * cube.solid_angles[k] * (unit(normals[:3]) @ d) / np.pi, rtol=1e-2)
    assert out[3, 0] == 0.0


def test_light_shape_is_checked():
    cube = CubeMap(4)
    vis = make_vis(make_samples([UP]), cube)
    with pytest.raises(ValueError):
        render(vis, np.ones(cube.n_texels + 1), LAMBERT)
    with pytest.raises(ValueError):
        render(vis, np.ones((cube.n_texels, 2)), LAMBERT)


# -- specular lobes ------------------------------------------------------------------------------
def blinn_phong_normal_incidence(n):
    """(n + 8) / (8 pi) int_hemisphere cos^n(theta / 2) cos(theta) dw (N = v: N.H = cos(theta / 2))."""
    f = lambda th: (n + 8) / (8 * np.pi) * 2 * np.pi * np.cos(th / 2) ** n * np.cos(th) * np.sin(th)
    return quad(f, 0.0, np.pi / 2, epsabs=1e-13, epsrel=1e-12, limit=200)[0]


@pytest.mark.parametrize("n", [1.0, 10.0, 30.0, 100.0])
@pytest.mark.parametrize("R", [32, 64])
def test_blinn_phong_normal_incidence_matches_quadrature(n, R):
    cube = CubeMap(R)
    mat = Material(kd=(0.0, 0.0, 0.0), ks=(1.0, 1.0, 1.0), shininess=n, model="blinn-phong")
    out = render(make_vis(make_samples([UP]), cube), np.ones(cube.n_texels), mat)
    expected = blinn_phong_normal_incidence(n)
    assert 1.0 < expected < 1.1  # the known value for these n (energy-normalised lobe)
    np.testing.assert_allclose(out, expected, rtol=1e-2)


@pytest.mark.parametrize("n", [1.0, 30.0, 100.0])
def test_normalised_phong_normal_incidence_is_one(n):
    """(n + 2) / (2 pi) int cos^n(theta) cos(theta) dw = 1 exactly."""
    cube = CubeMap(64)
    mat = Material(kd=(0.0, 0.0, 0.0), ks=(1.0, 1.0, 1.0), shininess=n, model="phong")
    out = render(make_vis(make_samples([UP]), cube), np.ones(cube.n_texels), mat)
    np.testing.assert_allclose(out, 1.0, rtol=1e-2)


@pytest.mark.parametrize("n", [2.0, 20.0])
def test_classic_phong_normal_incidence(n):
    """The paper's unnormalised term: ks int (R.d)^n dw = 2 pi / (n + 1) at normal incidence."""
    cube = CubeMap(64)
    mat = Material(kd=(0.0, 0.0, 0.0), ks=(1.0, 1.0, 1.0), shininess=n, model="phong-classic")
    out = render(make_vis(make_samples([UP]), cube), np.ones(cube.n_texels), mat)
    np.testing.assert_allclose(out, 2 * np.pi / (n + 1), rtol=1e-2)


def test_diffuse_plus_specular_adds_with_rgb_weights():
    cube = CubeMap(32)
    vis = make_vis(make_samples([UP, unit([0.3, 0.0, 1.0])], views=[UP, unit([-0.2, 0.4, 1.0])]), cube)
    L = np.random.default_rng(3).random(cube.n_texels) + 0.5
    kd, ks = (0.5, 0.25, 0.125), (0.1, 0.2, 0.4)
    both = render(vis, L, Material(kd=kd, ks=ks, shininess=20.0, model="blinn-phong"))
    diff = render(vis, L, Material(kd=(1.0, 1.0, 1.0)))
    spec = render(vis, L, Material(kd=(0.0, 0.0, 0.0), ks=(1.0, 1.0, 1.0), shininess=20.0, model="blinn-phong"))
    np.testing.assert_allclose(both, np.array(kd) * diff + np.array(ks) * spec, rtol=1e-5)
    assert np.all(spec > 0)


def test_specular_lobe_peaks_at_the_half_vector_and_vanishes_behind():
    cube = CubeMap(32)
    n = np.array([[0.0, 0.0, 1.0]])
    v = unit([[1.0, 0.0, 1.0]])
    cos = np.maximum(n @ cube.directions.T, 0.0)
    norm, dnorm = lobe_norm(50.0, "blinn-phong")
    assert dnorm == pytest.approx(1 / (8 * np.pi))
    lobe = norm * np.maximum(lobe_cosines(n, v, cube.directions, "blinn-phong"), 0.0) ** 50
    # the mirror direction of v about N has H = N: the peak value (n + 8) / (8 pi)
    k = int(np.argmax(lobe[0]))
    mirror = unit([-1.0, 0.0, 1.0])
    assert np.degrees(np.arccos(cube.directions[k] @ mirror)) < 3.0
    assert lobe[0, k] == pytest.approx(58 / (8 * np.pi), rel=1e-2)
    # the n-free factor A = V w max(0, N.d) is zero behind the normal
    A, c = specular_factors(np.ones((1, cube.n_texels), np.float32), n, v, cube, "blinn-phong")
    np.testing.assert_allclose(A[0], np.where(c[0] > 0, cos[0] * cube.solid_angles, 0.0), rtol=1e-5, atol=1e-12)
    assert np.all(A[0, cos[0] == 0] == 0)


def test_transport_blocks():
    cube = CubeMap(4)
    s = make_samples([UP, WALL_X])
    V = np.ones((2, cube.n_texels), np.float32)
    D, S = transport(V, s.normal, s.view, cube, LAMBERT)
    assert S is None and D.dtype == np.float32 and D.shape == (2, cube.n_texels)
    np.testing.assert_allclose(D, projected_solid_angles(s.normal, cube) / np.pi, rtol=5e-4)  # R=4: coarse
    D2, S2 = transport(V, s.normal, s.view, cube,
                       Material(ks=(0.5, 0.5, 0.5), shininess=5.0, model="blinn-phong"))
    np.testing.assert_allclose(D2, D)
    assert S2.shape == D.shape and np.all(S2 >= 0) and np.all(S2[D == 0] == 0)


def test_pixels_to_image():
    pix = np.array([[0, 1], [2, 3]], np.int32)
    img = pixels_to_image(np.array([[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]]), pix, 3, 4, background=-1.0)
    assert img.shape == (3, 4, 3) and img.dtype == np.float32
    np.testing.assert_array_equal(img[0, 1], [1, 2, 3])
    np.testing.assert_array_equal(img[2, 3], [4, 5, 6])
    assert np.count_nonzero(img == -1.0) == 3 * 4 * 3 - 6


# -- Material ------------------------------------------------------------------------------------
def test_material_from_json_blinnphong():
    m = Material.from_json({"type": "blinnphong", "kd": [0.6, 0.5, 0.4], "ks": [0.2, 0.3, 0.1], "n": 30})
    assert m.model == "blinn-phong"
    assert m.kd == (0.6, 0.5, 0.4) and m.ks == (0.2, 0.3, 0.1)
    assert m.shininess == 30.0 and m.specular


def test_material_from_json_diffuse():
    m = Material.from_json({"type": "diffuse", "kd": [0.8, 0.7, 0.2]})
    assert m.model == "lambert" and m.kd == (0.8, 0.7, 0.2)
    assert m.ks == (0.0, 0.0, 0.0) and not m.specular


@pytest.mark.parametrize("data,model", [
    ({}, "lambert"),
    ({"type": "lambertian", "kd": 0.5}, "lambert"),
    ({"model": "phong", "ks": 0.5, "shininess": 12}, "phong"),
    ({"model": "phong-classic", "n": 4}, "phong-classic"),
    ({"type": "Blinn_Phong", "ks": [0, 0, 0]}, "blinn-phong"),
])
def test_material_from_json_variants(data, model):
    m = Material.from_json(data)
    assert m.model == model
    assert len(m.kd) == 3 and len(m.ks) == 3
    if "kd" in data and np.ndim(data["kd"]) == 0:
        assert m.kd == (data["kd"],) * 3


def test_material_json_round_trip():
    m = Material(kd=(0.3, 0.2, 0.1), ks=(0.05, 0.05, 0.05), shininess=42.0, model="phong")
    again = Material.from_json(m.to_json())
    assert again == m
    assert not Material(ks=(0.0, 0.0, 0.0), model="blinn-phong").specular
    assert not Material(ks=(1.0, 1.0, 1.0), model="lambert").specular


@pytest.mark.parametrize("data", [
    {"kd": [-0.1, 0.5, 0.5]},
    {"kd": [math.nan, 1, 1]},
    {"kd": [math.inf, 1, 1]},
    {"kd": [1, 1]},
    {"kd": [1, 1, 1, 1]},
    {"kd": "white"},
    {"kd": {"r": 1}},
    {"type": "blinnphong", "ks": [0, -1, 0]},
    {"type": "blinnphong", "n": -3},
    {"type": "blinnphong", "n": math.nan},
    {"type": "blinnphong", "n": "shiny"},
    {"type": "blinnphong", "n": None},
    {"type": "blinnphong", "n": [30]},
    {"type": "ggx"},
], ids=["kd-negative", "kd-nan", "kd-inf", "kd-2", "kd-4", "kd-string", "kd-object", "ks-negative",
        "n-negative", "n-nan", "n-string", "n-null", "n-list", "unknown-type"])
def test_invalid_material_values_raise_value_error(data):
    with pytest.raises(ValueError):
        Material.from_json(data)


@pytest.mark.parametrize("kwargs", [dict(kd=(1.0, 1.0)), dict(ks=(0.0, -0.5, 0.0)), dict(shininess=-1.0),
                                    dict(shininess=math.inf), dict(model="cook-torrance")])
def test_invalid_material_constructor_raises(kwargs):
    with pytest.raises(ValueError):
        Material(**kwargs)


# -- the diffuse radiance as one product (`lambert_radiance`) -----------------------------------
@pytest.mark.parametrize("R", [8, 32])
def test_linear_diffuse_sum_is_the_clamped_transport(mitsuba_scene, R):
    """Visibility as wavelight casts it (0 wherever a texel is not castable): N . (V @ (m L)) / pi
    against diffuse_transport(V) @ L, float64 sums. At R = 32 the clamp it drops at texels that
    straddle a pixel's horizon changes less than float32 rounding does, and `render` takes it; at R = 8
    the slivers are larger (~3e-6) and `render` keeps the transport."""
    from pipelines.geometry.visibility import compute_visibility
    from pipelines.model.render import diffuse_transport, lambert_radiance, linear_diffuse

    scene = mitsuba_scene("spot_overcast")
    samples = scene.samples.take(slice(0, None, 7))
    cube = CubeMap(R)
    vis = compute_visibility(scene.backend, samples, cube)
    assert vis.castable_only
    V = vis.dense()
    L = np.random.default_rng(3).random((cube.n_texels, 3)) ** 3
    clamped = diffuse_transport(V, samples.normal, cube).astype(np.float64) @ L
    ref = (np.maximum(samples.normal @ cube.vector_solid_angles.T, 0.0) * V / np.pi) @ L  # float64
    linear = lambert_radiance(V, samples.normal, cube, L)
    rel = lambda a: float(np.sqrt(((a - ref) ** 2).sum() / (ref**2).sum()))
    assert rel(clamped) < 1e-7  # float32 rounding of the transport
    assert linear_diffuse(vis) == (R >= 32)
    if R >= 32:
        assert rel(linear) < 1e-6
        np.testing.assert_allclose(render(vis, L, LAMBERT), clamped, rtol=2e-5)
    else:
        assert 1e-7 < rel(linear) < 1e-4  # (what makes R < 32 keep the transport)
        np.testing.assert_allclose(render(vis, L, LAMBERT), clamped, rtol=1e-6)
    # the same rows without the guarantee (V may be 1 behind the normal): the transport, always
    loose = VisibilityData(samples, cube, 1, vis.stored)
    np.testing.assert_allclose(render(loose, L, LAMBERT), clamped, rtol=1e-6)


# -- a sparse light: the lit texels' columns alone (`render`) ---------------------------------------
@pytest.mark.parametrize("model, R", [("blinn-phong", 16), ("plastic", 16), ("blinn-phong", 32)])
def test_render_of_a_sparse_light_forms_only_its_lit_texels(mitsuba_scene, model, R):
    """A light with a tenth of its texels lit renders from their columns alone; against the full
    transports (every texel) in float64: the same to float32 rounding, with matte rows and rows at
    half their specular weight, and under plastic with grazing views, whose cap is that of the lobe
    over every texel (not only the lit ones). At R = 32 (Blinn-Phong) the diffuse part takes the
    linear route (`lambert_radiance` over every texel) while the lobe takes the lit texels' columns."""
    from pipelines.geometry.visibility import compute_visibility
    from pipelines.model import microfacet as mf
    from pipelines.model.render import SPARSE_LIGHT_SHARE, linear_diffuse, transport

    scene = mitsuba_scene("teapot_sun_phong")
    samples = scene.samples.take(slice(0, None, 11 if R == 16 else 23))
    cube = CubeMap(R)
    vis = compute_visibility(scene.backend, samples, cube)
    assert linear_diffuse(vis) == (R >= 32)
    rng = np.random.default_rng(5)
    L = np.zeros((cube.n_texels, 3))
    lit = rng.choice(cube.n_texels, cube.n_texels // 10, replace=False)
    L[lit] = rng.random((len(lit), 3)) * 10
    assert len(lit) <= SPARSE_LIGHT_SHARE * cube.n_texels
    material = (Material(model="plastic", kd=(0.6, 0.5, 0.4), ks=(1.0,) * 3, roughness=0.2)
                if model == "plastic" else Material(model="blinn-phong", kd=(0.6, 0.5, 0.4), ks=(0.3,) * 3, shininess=40))
    weight = np.ones(vis.n_pixels)
    weight[::5], weight[::7] = 0.5, 0.0
    nv = np.einsum("pk,pk->p", samples.normal, samples.view)
    if model == "plastic":
        assert (nv[weight > 0] < mf.GRAZING_NV).sum() >= 5  # (the cap is exercised)
    D, S = transport(vis.dense(), samples.normal, samples.view, cube, material, weight,
                     mf.samples_footprint(samples, slice(None), material))
    ref = np.asarray(material.kd) * (D.astype(np.float64) @ L) + np.asarray(material.ks) * (S.astype(np.float64) @ L)
    out = render(vis, L, material, specular=weight)
    assert float(np.sqrt(((out - ref) ** 2).sum() / (ref**2).sum())) < 1e-6
    # and lit everywhere (the full route), the same light with its dark texels at a negligible level
    dense = np.where(L > 0, L, 1e-30)
    np.testing.assert_allclose(render(vis, dense, material, specular=weight), out, rtol=1e-5, atol=1e-12)
