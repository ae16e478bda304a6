"""The microfacet dielectric `plastic` (pipelines/model/microfacet.py): its BRDF is Mitsuba 3's
roughplastic / plastic (nonlinear = false) point by point, it conserves energy, and the forward
model's texel-resolution lobe (`render.transport`) integrates like the BRDF it stands for."""

from __future__ import annotations

import json

import numpy as np
import pytest

from pipelines.light.cubemap import CubeMap
from pipelines.model import microfacet as mf
from pipelines.model import render
from pipelines.model.materials import MODELS, Material

IOR = 1.49


def _directions(rng, n, zmin=0.02):
    z = rng.uniform(zmin, 1.0, n)
    phi = rng.uniform(0.0, 2 * np.pi, n)
    s = np.sqrt(1 - z * z)
    return np.stack([s * np.cos(phi), s * np.sin(phi), z], -1)


def _hemisphere_quadrature(n_theta=400, n_phi=400):
    """Directions and weights (midpoint rule in cos theta and phi) over the upper hemisphere."""
    mu = (np.arange(n_theta) + 0.5) / n_theta
    phi = 2 * np.pi * (np.arange(n_phi) + 0.5) / n_phi
    m, p = np.meshgrid(mu, phi, indexing="ij")
    s = np.sqrt(1 - m * m)
    d = np.stack([s * np.cos(p), s * np.sin(p), m], -1).reshape(-1, 3)
    return d, np.full(len(d), 2 * np.pi / (n_theta * n_phi))


def test_plastic_is_registered():
    assert MODELS["plastic"].specular and MODELS["plastic"].lobe == "alpha"
    m = Material.from_json({"model": "plastic", "kd": 0.5, "alpha": 0.2, "distribution": "beckmann", "ior": 1.5})
    assert (m.roughness, m.distribution, m.ior, m.ks) == (0.2, "beckmann", 1.5, (1.0, 1.0, 1.0))
    assert Material.from_json(json.loads(json.dumps(m.to_json()))) == m
    # Mitsuba's own parameter names and defaults (roughplastic: beckmann, alpha 0.1, polypropylene in air)
    mi = Material.from_json({"type": "roughplastic", "diffuse_reflectance": [0.2, 0.3, 0.4]})
    assert (mi.roughness, mi.distribution, mi.kd) == (0.1, "beckmann", (0.2, 0.3, 0.4))
    assert mi.ior == pytest.approx(1.49 / 1.000277)
    assert Material.from_json({"type": "plastic"}).roughness == 0.0
    for bad in ({"model": "plastic", "alpha": -1}, {"model": "plastic", "ior": 0.5},
                {"model": "plastic", "distribution": "phong"}, {"type": "roughplastic", "nonlinear": True},
                {"model": "plastic", "alpha": 10**400}):
        with pytest.raises(ValueError):
            Material.from_json(bad)


@pytest.mark.parametrize("eta", [1.05, 1.49, 3.0])
def test_float32_fresnel_from_outside_is_fresnels(eta):
    # the lobe's per-(pixel, texel) Fresnel factor (`lobe_factors`) against the float64 reference,
    # over the whole incidence range including normal and grazing incidence
    c = np.concatenate([[0.0, 1e-7, 1e-3, 1.0], np.random.default_rng(3).random(4000)]).astype(np.float32)
    ref = mf.fresnel(c.astype(np.float64), eta)[0]
    got = mf.fresnel_outside(c, eta)
    assert got.dtype == np.float32
    np.testing.assert_allclose(got, ref, rtol=2e-5, atol=0)
    assert got[0] == pytest.approx(1.0) and got[3] == pytest.approx(((eta - 1) / (eta + 1)) ** 2, rel=1e-5)
    np.testing.assert_allclose(mf.fresnel_outside(c, 0.8), mf.fresnel(c.astype(np.float64), 0.8)[0], rtol=1e-6)


@pytest.mark.parametrize("distribution", ["ggx", "beckmann"])
@pytest.mark.parametrize("alpha", [0.0, 0.05, 0.3, 0.7])
def test_brdf_is_mitsubas_roughplastic(distribution, alpha):
    """f cos at random direction pairs (half of them near the mirror direction) against Mitsuba 3's
    BSDF.eval of roughplastic (alpha > 0) or plastic (alpha = 0: its non-delta part, the diffuse
    base), kd 0.5: measured to 2e-5 (float32 lobe factors)."""
    mi = pytest.importorskip("mitsuba")
    mi.set_variant("scalar_rgb")
    rng = np.random.default_rng(int(alpha * 100) + len(distribution))
    wi, wo = _directions(rng, 300), _directions(rng, 300)
    near = 2 * wi[:150, 2:3] * np.array([0.0, 0.0, 1.0]) - wi[:150] + rng.normal(0, max(alpha, 0.02) * 0.3, (150, 3))
    wo[:150] = near / np.linalg.norm(near, axis=1, keepdims=True)
    keep = wo[:, 2] > 0.01
    wi, wo = wi[keep], wo[keep]
    spec = {"type": "roughplastic", "distribution": distribution, "alpha": alpha} if alpha > 0 else {"type": "plastic"}
    bsdf = mi.load_dict({**spec, "int_ior": IOR, "ext_ior": 1.0, "nonlinear": False,
                         "diffuse_reflectance": {"type": "rgb", "value": [0.5, 0.5, 0.5]}})
    ref = []
    for a, b in zip(wi, wo):
        si = mi.SurfaceInteraction3f()
        si.wi = mi.Vector3f(*a)
        si.sh_frame = mi.Frame3f(mi.Vector3f(0, 0, 1))
        ref.append(bsdf.eval(mi.BSDFContext(), si, mi.Vector3f(*b))[0])
    ref = np.array(ref)
    d, s = mf.eval_cos(0.5, 1.0, alpha, IOR, distribution, wi[:, 2], wo[:, 2], np.sum(wi * wo, axis=1))
    rel = np.abs(d + s - ref) / ref
    assert rel.max() < 1e-4, (rel.max(), np.median(rel))


@pytest.mark.parametrize("distribution", ["ggx", "beckmann"])
def test_energy_is_conserved(distribution):
    """The directional albedo of kd = 1, ks = 1 (the physical coating): integral over the hemisphere
    of f cos at 160,000 directions, for view angles up to 89 deg: never above 1; for the smooth
    coating (Mitsuba's Fdr fit) it is 1 to 0.6 %; rough coatings lose what Smith shadowing takes,
    more for larger alpha."""
    d, w = _hemisphere_quadrature()
    for alpha in (0.05, 0.3, 1.0):
        albedo = []
        for theta in (0.0, 30.0, 60.0, 75.0, 89.0):
            t = np.radians(theta)
            v = np.array([np.sin(t), 0.0, np.cos(t)])
            diffuse, spec = mf.eval_cos(1.0, 1.0, alpha, IOR, distribution, np.full(len(d), v[2]), d[:, 2], d @ v)
            albedo.append(float(((diffuse + spec) * w).sum()))
        albedo = np.array(albedo)
        assert np.all(albedo <= 1.0 + 2e-3), (alpha, albedo)
        # (the lower bound up to 75 deg: at 89 deg the quadrature does not resolve a narrow lobe)
        assert np.all(albedo[:4] > {0.05: 0.95, 0.3: 0.6, 1.0: 0.15}[alpha]), (alpha, albedo)
        print(distribution, alpha, np.round(albedo, 4))
    # the smooth coating: diffuse (1 - F(v)) plus the mirror's F(v)
    for theta in (0.0, 45.0, 80.0):
        mu = np.cos(np.radians(theta))
        diffuse, _ = mf.eval_cos(1.0, 1.0, 0.0, IOR, distribution, np.full(len(d), mu), d[:, 2],
                                 d @ np.array([np.sqrt(1 - mu * mu), 0.0, mu]))
        total = float((diffuse * w).sum()) + float(mf.fresnel(mu, IOR)[0])
        assert total == pytest.approx(1.0, abs=6e-3)


@pytest.mark.parametrize("distribution", ["ggx", "beckmann"])
def test_transport_integrates_the_lobe(distribution):
    """The forward model on a R = 32 hemisphere under a uniform sky (V = 1, upward normal): the sum
    of a pixel's transport row is its directional albedo. It matches the BRDF's own integral to
    1.5 % for alpha 0.05 .. 1 and the smooth coating's 1 to 1.5 % for views up to 75 deg (the
    texel blur keeps a lobe narrower than a texel from aliasing); at 85 deg the blurred lobe of a
    smooth GGX coating overshoots (README: limits)."""
    cube = CubeMap(32, hemisphere=True)
    theta = np.radians([0.0, 30.0, 60.0, 75.0])
    views = np.stack([np.sin(theta), 0 * theta, np.cos(theta)], -1)
    normals = np.tile([0.0, 0.0, 1.0], (len(theta), 1))
    V = np.ones((len(theta), cube.n_texels), np.float32)
    d, w = _hemisphere_quadrature()
    for alpha in (0.0, 0.05, 0.3, 1.0):
        m = Material(kd=(1, 1, 1), ks=(1, 1, 1), model="plastic", roughness=alpha, distribution=distribution, ior=IOR)
        D, S = render.transport(V, normals, views, cube, m)
        got = D.sum(axis=1) + S.sum(axis=1)
        if alpha == 0:
            assert np.allclose(got, 1.0, atol=0.015), got
            continue
        want = []
        for v in views:
            diffuse, spec = mf.eval_cos(1.0, 1.0, alpha, IOR, distribution, np.full(len(d), v[2]), d[:, 2], d @ v)
            want.append(float(((diffuse + spec) * w).sum()))
        assert np.allclose(got, want, rtol=0.015), (alpha, got, want)


@pytest.mark.parametrize("distribution", mf.DISTRIBUTIONS)
def test_grazing_views_keep_the_lobes_energy(distribution, monkeypatch):
    """The texel-sampled lobe at views towards N.v -> 0 (silhouette pixels with interpolated shading
    normals): uncapped, summed over every texel unshadowed, it reflects many times the coating's
    specular albedo E_s (measured at R = 32 with the texel's blur across the plane of incidence
    mapped through v.h: up to 2x at N.v = 0.05, up to 4-180x at N.v = 0.004-0.01 for alpha 0 .. 0.3,
    by the view's direction); capped, a grazing view's lobe is min(that, E_s) row by row and the other views are
    untouched."""
    cube = CubeMap(32)
    rng = np.random.default_rng(3)
    mus = np.repeat([0.004, 0.01, 0.02, 0.05, 0.1, 0.3, 0.6], 4)
    n = rng.normal(size=(len(mus), 3))
    n[:, 2] = np.abs(n[:, 2]) + 1.0
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    t = np.cross(n, rng.normal(size=(len(mus), 3)))
    t /= np.linalg.norm(t, axis=1, keepdims=True)
    views = mus[:, None] * n + np.sqrt(1 - mus[:, None] ** 2) * t
    V = np.ones((len(mus), cube.n_texels), np.float32)
    graze = mus < mf.GRAZING_NV
    for alpha in (0.0, 0.05, 0.3):
        m = Material(kd=(1, 1, 1), ks=(1, 1, 1), model="plastic", roughness=alpha, distribution=distribution, ior=IOR)
        capped = render.plastic_specular_transport(V, n, views, cube, m)
        with monkeypatch.context() as mp:
            mp.setattr(mf, "GRAZING_NV", 0.0)
            raw = render.plastic_specular_transport(V, n, views, cube, m)
        E = np.interp(mus, mf._MU, mf.specular_albedo_table(alpha, IOR, distribution))
        total, raw_total = capped.sum(axis=1), raw.sum(axis=1)
        assert np.max(raw_total[mus == 0.004] / E[mus == 0.004]) > 3, (alpha, raw_total / E)  # the run-away
        np.testing.assert_allclose(total[graze], np.minimum(raw_total, E)[graze], rtol=1e-4)
        np.testing.assert_array_equal(capped[~graze], raw[~graze])


@pytest.mark.parametrize("distribution", ["ggx", "beckmann"])
def test_the_fits_diffuse_reflectance_follows_the_coating(distribution):
    """The fit's Fdr between cached tables (`diffuse_reflectance_interpolated`: the uncertainties'
    d log b / d log alpha) against the coating's own quadrature at alpha and either side: Fdr within
    1e-3 and its slope within 15 % or 5e-4 of the central difference (a chord of the grid's cell,
    0.05 in log alpha: measured -0.00135 against -0.00115 at alpha 0.013, -0.0062 against -0.0068 at
    0.07 Beckmann; in kd's sigma it weighs ~1e-2 x sigma(log alpha))."""
    for alpha in (0.013, 0.07, 0.23):
        fdr, slope = mf.diffuse_reflectance_interpolated(alpha, 1.49, distribution)
        h = 0.02
        up, down = (mf.coating(alpha * np.exp(s * h), 1.49, distribution).fdr for s in (1, -1))
        assert fdr == pytest.approx(mf.coating(alpha, 1.49, distribution).fdr, abs=1e-3)
        assert slope == pytest.approx((up - down) / (2 * h), rel=0.15, abs=5e-4), (alpha, slope, (up - down) / (2 * h))


@pytest.mark.parametrize("distribution", ["ggx", "beckmann"])
def test_the_shipped_fdr_grid_is_the_quadratures(distribution, monkeypatch):
    """`coating_tables` (tools/make_coating_tables.py) holds the default IOR's Fdr on the fit's grid:
    grid points across its range (the smallest alpha, the fits' usual range, alpha 1 and the point
    above it) are the quadrature's values, and the interpolated Fdr and slope at off-grid alphas are
    those computed without the table; another IOR is computed."""
    from pipelines.model import coating_tables as ct

    values = ct.FDR_GRID[distribution]
    assert ct.FDR_IOR == mf.DEFAULT_IOR and ct.FDR_STEP == mf._LOG_ALPHA_STEP
    assert np.exp(ct.FDR_FIRST * ct.FDR_STEP) <= mf.MIN_ALPHA and np.exp((ct.FDR_FIRST + len(values) - 1) * ct.FDR_STEP) > 1.0
    for k in (ct.FDR_FIRST, -92, -60, -46, -30, -12, 0, ct.FDR_FIRST + len(values) - 1):
        a = float(np.exp(k * ct.FDR_STEP))
        assert values[k - ct.FDR_FIRST] == pytest.approx(mf._grid_fdr(a, mf.DEFAULT_IOR, distribution), rel=1e-12), k
    shipped = [mf.diffuse_reflectance_interpolated(a, mf.DEFAULT_IOR, distribution) for a in (0.0071, 0.13, 0.41)]
    asked = []
    quadrature = mf._grid_fdr
    monkeypatch.setattr(mf, "_grid_fdr", lambda a, eta, d: asked.append(eta) or 0.5)
    mf.diffuse_reflectance_interpolated(0.29, mf.DEFAULT_IOR, distribution)
    assert asked == []  # (from the table)
    assert mf.diffuse_reflectance_interpolated(0.13, 1.7, distribution)[0] == 0.5 and asked == [1.7, 1.7]
    monkeypatch.setattr(mf, "_grid_fdr", quadrature)
    monkeypatch.setattr(ct, "FDR_GRID", {})
    computed = [mf.diffuse_reflectance_interpolated(a, mf.DEFAULT_IOR, distribution) for a in (0.0071, 0.13, 0.41)]
    np.testing.assert_allclose(shipped, computed, rtol=1e-12)


@pytest.mark.parametrize("distribution", ["ggx", "beckmann"])
def test_the_float32_inner_loops_are_the_reference_functions(distribution):
    """The in-place float32 versions used per (pixel, texel) pair (`lobe_factors_f32`,
    `smith_g1_f32`, `Coating.transmittance_f32`, `lobe_values` without temporaries) give the
    reference functions' values to float32 rounding, at the mirror direction (N.v = 1), grazing views,
    texels below the horizon and tan 0 included."""
    rng = np.random.default_rng(3)
    cube = CubeMap(16)
    n = _directions(rng, 64, zmin=0.0)
    v = _directions(rng, 64, zmin=-0.3)
    v[:3], v[3] = n[:3], np.array([n[3, 1], -n[3, 0], 0.0]) / np.hypot(n[3, 0], n[3, 1])  # N.v = 1; N.v = 0
    d = cube.directions.astype(np.float32)
    nd, vd = n.astype(np.float32) @ d.T, v.astype(np.float32) @ d.T
    nv = np.einsum("pk,pk->p", n, v).astype(np.float32)[:, None]
    w = cube.solid_angles.astype(np.float32)[None, :]
    ref = mf.lobe_factors(nd, nv, vd, w, IOR)
    new = mf.lobe_factors_f32(nd, nv, vd, w, IOR)
    for a, b in zip(ref, new):
        assert b.dtype == np.float32 and np.all(np.isfinite(b))
        np.testing.assert_allclose(b, a, rtol=1e-6, atol=1e-6 * np.abs(a).max())
    A, x2, y2, wx, wy, t2d = ref
    t2d[0, :4] = 0.0  # tan 0
    for alpha in (0.01, 0.15, 0.6):
        g, dg = mf.smith_g1(t2d, alpha, distribution, derivative=True)
        g32, dg32 = mf.smith_g1_f32(t2d, alpha, distribution, derivative=True)
        np.testing.assert_allclose(g32, g, rtol=1e-6, atol=1e-6)
        np.testing.assert_allclose(dg32, dg, rtol=1e-5, atol=1e-6)
        np.testing.assert_array_equal(mf.smith_g1_f32(t2d, alpha, distribution), g32)
        lobe = mf.lobe_values(x2, y2, wx, wy, alpha, distribution)
        ref_lobe = mf.lobe_values(x2.astype(np.float64), y2, wx, wy, alpha, distribution,
                                  derivative_out=np.empty(x2.shape))  # (the reference path, in float64)
        np.testing.assert_allclose(lobe, ref_lobe, rtol=1e-5, atol=1e-6 * ref_lobe.max())
        coat = mf.coating(alpha, IOR, distribution)
        np.testing.assert_allclose(coat.transmittance_f32(nd), coat.transmittance(nd), rtol=1e-6, atol=1e-7)
