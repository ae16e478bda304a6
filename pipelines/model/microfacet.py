"""The microfacet dielectric (`plastic`): a rough dielectric coating over a diffuse base, as Mitsuba 3's
`roughplastic` (alpha > 0) and `plastic` (alpha = 0), both with nonlinear = false.

With v the direction to the camera, d a light direction, N the shading normal, h = (v + d)/|v + d|,
eta the coating's index of refraction relative to the outside:

    f(v, d) = ks F(v.h) D(h) G1(v, h) G1(d, h) / (4 (N.v)(N.d))
            + kd / (pi eta^2 (1 - Fdr)) t(N.v) t(N.d)

- D: GGX, D = 1 / (pi a^2 cos^4 (1 + tan^2 / a^2)^2), or Beckmann, D = exp(-tan^2 / a^2) / (pi a^2 cos^4)
  (theta_h from N); G1: Smith's for the same distribution (GGX exactly, 2 / (1 + sqrt(1 + a^2 tan^2));
  Beckmann by Mitsuba's rational fit, < 0.35 % off), separable: G = G1(v) G1(d);
- F: the unpolarised Fresnel reflectance of the dielectric (total internal reflection included);
- t(mu): the coating's transmittance at incidence cosine mu, 1 - F(mu) when smooth; when rough, the
  mean over the visible normals of (1 - F) G1 of the refracted direction, on Mitsuba's table of 64
  cosines (linear interpolation), computed by Mitsuba's own quadrature (`coating`);
- Fdr: the coating's mean reflectance from inside (internal reflection, diffuse incidence): smooth,
  Mitsuba's fit `fresnel_diffuse_reflectance(1 / eta)`; rough, 2 x the mean over the 64 cosines of
  mu R_int(mu) (Mitsuba's rule).
- ks = 1 is the physical coating (Mitsuba's specular_reflectance).

Energy: the specular lobe reflects at most F <= 1 of what arrives (a Smith microfacet lobe's albedo is
<= 1) and the base at most kd (1 - F) (the light the coating lets through, kd < 1): for kd <= 1 and
ks <= 1 the model never reflects more than it receives (checked numerically in the tests).

The lobe at texel resolution: a texel stands for a constant radiance over its solid angle, so the
transport wants the lobe integrated over the texel. Where the lobe is much wider than a texel the
centre value is that integral; where it is narrower (alpha ~ 0.01 at R = 32, and the smooth `plastic`)
the centre value aliases. The lobe is therefore evaluated with a texel-widened roughness
a_eff^2 = a^2 + w_i / (24 (v.h) cos^3 theta_h), the slope-space variance of the texel's footprint
(solid angle w_i, seen through the half vector) added to the distribution's (a Gaussian blur of the
lobe by the texel, exact in variance for Beckmann, its core for GGX; the lobe's integral is kept).
At R = 32 that adds ~0.01 in quadrature: alpha = 0.05 becomes 0.051, a smooth coating's mirror
becomes a lobe one texel wide. Shadowing G1 uses the true alpha.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

DISTRIBUTIONS = ("ggx", "beckmann")
DEFAULT_IOR = 1.49  # a typical plastic / glaze / varnish (Mitsuba's polypropylene; Blender's default 1.5)
IOR_RANGE = (1.05, 3.0)  # a dielectric coating's index relative to the outside medium
TABLE_SIZE = 64  # Mitsuba's MI_ROUGH_TRANSMITTANCE_RES
MIN_ALPHA = 1e-4  # Mitsuba clamps its roughness here
_MU = np.maximum(1e-6, np.linspace(0.0, 1.0, TABLE_SIZE))


def fresnel(cos_i, eta):
    """Unpolarised Fresnel reflectance of a dielectric interface (Mitsuba's `fresnel`): cos_i the
    incidence cosine (negative: from inside), eta the inside's index over the outside's. Returns
    (F, cos_t signed as Mitsuba's, eta_ti)."""
    c = np.asarray(cos_i, np.float64)
    outside = c >= 0
    eta_it = np.where(outside, eta, 1.0 / eta)
    eta_ti = 1.0 / eta_it
    ct2 = 1.0 - (1.0 - c * c) * eta_ti * eta_ti
    ci = np.abs(c)
    ct = np.sqrt(np.maximum(ct2, 0.0))
    with np.errstate(invalid="ignore", divide="ignore"):
        a_s = (ci - eta_it * ct) / (ci + eta_it * ct)
        a_p = (ct - eta_it * ci) / (ct + eta_it * ci)
    r = 0.5 * (a_s * a_s + a_p * a_p)
    r = np.where((ci == 0) | ~np.isfinite(r), 1.0, r)
    return r, np.where(outside, -ct, ct), eta_ti


def fresnel_outside(cos_i, eta: float) -> np.ndarray:
    """`fresnel`'s F for light arriving from outside (cos_i in [0, 1]) a denser medium (eta > 1), in
    float32 with in-place passes: the lobe's factors need it per (pixel, texel), where `fresnel`'s
    float64 temporaries cost more than the rest of `lobe_factors` together. No total internal
    reflection from outside: cos_t^2 = 1 - (1 - cos_i^2) / eta^2 >= 1 - 1 / eta^2 > 0."""
    if not eta > 1.0:
        return fresnel(cos_i, eta)[0].astype(np.float32)
    c = np.asarray(cos_i, np.float32)
    e = np.float32(eta)
    ct = c * c
    ct -= np.float32(1.0)
    ct *= np.float32(1.0 / (eta * eta))
    ct += np.float32(1.0)
    np.sqrt(ct, out=ct)
    t = ct * e  # eta cos_t
    r = c - t
    t += c
    r /= t  # a_s
    r *= r
    t = c * e  # eta cos_i
    p = ct - t
    t += ct
    p /= t  # a_p
    p *= p
    r += p
    r *= np.float32(0.5)
    return r


def fresnel_diffuse_reflectance(eta: float) -> float:
    """Mitsuba's fit of the diffuse (hemispherically averaged) Fresnel reflectance."""
    inv = 1.0 / eta
    if eta < 1:
        return 0.0636 * inv + eta * (eta * -1.4399 + 0.7099) + 0.6681
    return float(np.polyval([-1.36881, 4.98554, -7.80989, 6.75335, -3.4793, 0.919317], inv))


def smith_g1(tan2, alpha, distribution: str, derivative: bool = False):
    """Smith's G1 for a direction with tan^2 theta = tan2 (from the normal), roughness alpha
    (Mitsuba's; Beckmann by its rational fit); with `derivative`, also dG1 / d log alpha."""
    t = np.asarray(tan2)
    xy = (alpha * alpha) * t  # tan^2 theta alpha^2
    if distribution == "ggx":
        s = np.sqrt(1.0 + xy)
        g = 2.0 / (1.0 + s)
        if not derivative:
            return g
        return g, -g * g / 2.0 * xy / s
    with np.errstate(divide="ignore"):
        a = 1.0 / np.sqrt(xy)
    a = np.where(np.isfinite(a), a, 1e30)
    big = a >= 1.6
    a = np.where(big, 1.6, a)
    num = 3.535 * a + 2.181 * a * a
    den = 1.0 + 2.276 * a + 2.577 * a * a
    g = np.where(big, 1.0, num / den)
    if not derivative:
        return g
    dg_da = ((3.535 + 4.362 * a) * den - num * (2.276 + 5.154 * a)) / (den * den)
    return g, np.where(big, 0.0, -a * dg_da)  # da / d log alpha = -a


def smith_g1_f32(tan2: np.ndarray, alpha: float, distribution: str, derivative: bool = False):
    """`smith_g1` for float32 blocks of (pixel, texel) pairs, in a few in-place passes (the fit's and
    the render's inner loop: `smith_g1`'s temporaries cost it 6x as much); the same values to float32
    rounding. Beckmann's a = 1 / (alpha tan) is clamped at its cut (1.6, where the rational fit is
    1.00006 and g is set to 1), so that tan 0 needs no special case."""
    f32 = np.float32
    t = np.asarray(tan2, f32)
    if distribution == "ggx":
        xy = t * f32(alpha * alpha)
        s = xy + f32(1.0)
        np.sqrt(s, out=s)
        g = s + f32(1.0)
        np.divide(f32(2.0), g, out=g)
        if not derivative:
            return g
        # dG1 / d log alpha = -g^2 / 2 xy / s
        xy /= s
        xy *= g
        xy *= g
        xy *= f32(-0.5)
        return g, xy
    a = np.sqrt(t)
    a *= f32(alpha)
    with np.errstate(divide="ignore"):
        np.divide(f32(1.0), a, out=a)  # (tan 0: a = inf, clamped)
    np.minimum(a, f32(1.6), out=a)
    num = a * f32(2.181)
    num += f32(3.535)
    den = a * f32(2.577)
    den += f32(2.276)
    if derivative:  # dg/da = ((3.535 + 4.362 a) den - num (2.276 + 5.154 a)) / den^2 (num, den before x a)
        dnum = a * f32(4.362)
        dnum += f32(3.535)
        dden = a * f32(5.154)
        dden += f32(2.276)
    num *= a
    den *= a
    den += f32(1.0)
    if derivative:
        dnum *= den
        dden *= num
        dnum -= dden
        dnum /= den
        dnum /= den
        dnum *= a
        dnum *= f32(-1.0)  # da / d log alpha = -a
    num /= den
    cut = a >= f32(1.6)
    num[cut] = 1.0  # (the fit is 1.00006 there: `smith_g1`'s value exactly)
    if derivative:
        dnum[cut] = 0.0
    return (num, dnum) if derivative else num


def ndf(cos_h, alpha, distribution: str):
    """The distribution D(h) (per unit solid angle of h) for cos theta_h = cos_h."""
    c2 = np.asarray(cos_h, np.float64) ** 2
    t2 = (1.0 - c2) / np.maximum(c2, 1e-300)
    a2 = alpha * alpha
    if distribution == "ggx":
        return 1.0 / (np.pi * a2 * c2 * c2 * (1.0 + t2 / a2) ** 2)
    return np.exp(-t2 / a2) / (np.pi * a2 * c2 * c2)


# -- Mitsuba's coating tables ---------------------------------------------------------------------
def _concentric(u1, u2):
    x, y = 2.0 * u1 - 1.0, 2.0 * u2 - 1.0
    q13 = np.abs(x) < np.abs(y)
    r = np.where(q13, y, x)
    rp = np.where(q13, x, y)
    with np.errstate(invalid="ignore", divide="ignore"):
        phi = 0.25 * np.pi * rp / r
    phi = np.where(q13, 0.5 * np.pi - phi, phi)
    phi = np.where((x == 0) & (y == 0), 0.0, phi)
    return r * np.cos(phi), r * np.sin(phi)


def _visible_11(cos_i, u1, u2, distribution):
    """Mitsuba's sample_visible_11: slopes of the alpha = 1 distribution of visible normals (cos_i a
    column of incidence cosines, u1 and u2 rows of samples)."""
    if distribution == "ggx":
        px, py = _concentric(u1, u2)
        s = 0.5 * (1.0 + cos_i)
        py = np.sqrt(np.maximum(1.0 - px * px, 0.0)) * (1.0 - s) + py * s
        z = np.sqrt(np.maximum(1.0 - px * px - py * py, 0.0))
        sin_i = np.sqrt(np.maximum(1.0 - cos_i * cos_i, 0.0))
        norm = 1.0 / (sin_i * py + cos_i * z)
        return (cos_i * py - sin_i * z) * norm, px * norm
    from scipy.special import erf, erfinv

    tan_i = np.sqrt(np.maximum(1.0 - cos_i * cos_i, 0.0)) / cos_i
    cot_i = 1.0 / tan_i
    maxval = erf(cot_i)
    u1 = np.clip(u1, 1e-6, 1.0 - 1e-6)
    u2 = np.clip(u2, 1e-6, 1.0 - 1e-6)
    x = maxval - (maxval + 1.0) * erf(np.sqrt(-np.log(u1)))
    u1 = u1 * (1.0 + maxval + tan_i * np.exp(-cot_i * cot_i) / np.sqrt(np.pi))
    for _ in range(3):
        slope = erfinv(x)
        value = 1.0 + x + tan_i * np.exp(-slope * slope) / np.sqrt(np.pi) - u1
        x = x - value / (1.0 - slope * tan_i)
    return erfinv(x), np.broadcast_to(erfinv(2.0 * u2 - 1.0), x.shape)


def _coating_integral(alpha: float, eta: float, distribution: str, transmit: bool) -> np.ndarray:
    """Mitsuba's eval_transmittance (transmit) / eval_reflectance over the 64 table cosines: the mean
    over the visible normals (Gauss-Legendre, 32^2 nodes for eta > 1, else 128^2) of (1 - F) G1 of the
    refracted direction, or F G1 of the reflected one."""
    n = 32 if eta > 1 else 128
    x, w = np.polynomial.legendre.leggauss(n)
    u1, u2 = np.meshgrid(0.5 * x + 0.5, 0.5 * x + 0.5, indexing="xy")
    wt = (np.outer(w, w) * 0.25).ravel()
    u1, u2 = u1.ravel()[None, :], u2.ravel()[None, :]
    out = np.empty(TABLE_SIZE)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        for rows in np.array_split(np.arange(TABLE_SIZE), max(1, (TABLE_SIZE * n * n) // 262144)):
            mu = _MU[rows][:, None]
            wx, wz = np.sqrt(1.0 - mu * mu), mu
            # stretch (isotropic, wi in the x-z plane: phi = 0), sample the alpha = 1 slopes, unstretch
            norm = np.sqrt((alpha * wx) ** 2 + wz**2)
            sx, sy = _visible_11(wz / norm, u1, u2, distribution)
            mx, my = -alpha * sx, -alpha * sy
            inv = 1.0 / np.sqrt(mx * mx + my * my + 1.0)
            mx, my, mz = mx * inv, my * inv, inv
            dm = wx * mx + wz * mz
            f, cos_t, eta_ti = fresnel(dm, eta)
            if transmit:
                k = dm * eta_ti + cos_t
                ox, oy, oz = mx * k - wx * eta_ti, my * k, mz * k - wz * eta_ti
                ok = oz * wz < 0
                weight = 1.0 - f
            else:
                ox, oy, oz = 2.0 * dm * mx - wx, 2.0 * dm * my, 2.0 * dm * mz - wz
                ok = oz > 0
                weight = f
            xy = ox * ox + oy * oy
            g = smith_g1(xy / (oz * oz), alpha, distribution)
            g = np.where(xy == 0, 1.0, g)
            g = np.where((ox * mx + oy * my + oz * mz) * oz <= 0, 0.0, g)
            out[rows] = np.where(ok, g * weight, 0.0) @ wt
    return out


@dataclass(frozen=True)
class Coating:
    """What the diffuse base sees of the coating: t on the 64 cosines (rough) or 1 - F (smooth),
    Fdr and the base's constant 1 / (eta^2 (1 - Fdr))."""

    alpha: float
    eta: float
    distribution: str
    table: np.ndarray  # (64,) t at Mitsuba's cosines
    fdr: float

    @property
    def smooth(self) -> bool:
        return self.alpha <= 0

    @property
    def base_scale(self) -> float:
        return 1.0 / (self.eta**2 * (1.0 - self.fdr))

    @property
    def _table32(self) -> tuple[np.ndarray, np.ndarray]:
        """The table and its steps in float32 (`transmittance_f32`)."""
        return np.asarray(self.table, np.float32), np.diff(self.table).astype(np.float32)

    def transmittance_f32(self, mu: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        """`transmittance` for float32 blocks of cosines (into `out` when given, which may be mu): the
        same interpolation in float32 passes. The plastic base's inner loop, where `transmittance`'s
        float64 temporaries cost 20x Lambert's whole transport."""
        mu = np.asarray(mu, np.float32)
        if self.smooth:
            x = self.transmittance(mu).astype(np.float32)
        else:
            table, step = self._table32
            x = np.clip(mu, np.float32(0.0), np.float32(1.0))
            x *= np.float32(TABLE_SIZE - 1)
            i = x.astype(np.int32)
            np.minimum(i, TABLE_SIZE - 2, out=i)
            x -= i  # the fraction f
            x *= step[i]
            x += table[i]
            x *= mu > 0
        if out is None:
            return x
        out[...] = x
        return out

    def transmittance(self, mu):
        """t(mu) for incidence cosines mu in [0, 1] (0 below)."""
        mu = np.asarray(mu)
        if self.smooth:
            out = 1.0 - fresnel(np.clip(mu, 0.0, 1.0), self.eta)[0]
        else:
            x = np.clip(mu, 0.0, 1.0) * (TABLE_SIZE - 1)
            i = np.minimum(x.astype(np.int64), TABLE_SIZE - 2)
            out = self.table[i] + (self.table[i + 1] - self.table[i]) * (x - i)
        return np.where(mu > 0, out, 0.0)


@lru_cache(maxsize=256)
def coating(alpha: float, eta: float, distribution: str) -> Coating:
    """The coating of a material (cached: a rough one costs two quadratures, ~0.1-0.3 s)."""
    if distribution not in DISTRIBUTIONS:
        raise ValueError(f"unknown microfacet distribution {distribution!r}; choose one of {DISTRIBUTIONS}")
    alpha, eta = float(alpha), float(eta)
    if alpha <= 0:
        table = 1.0 - fresnel(_MU, eta)[0]
        return Coating(0.0, eta, distribution, table, fresnel_diffuse_reflectance(1.0 / eta))
    a = max(alpha, MIN_ALPHA)
    t = _coating_integral(a, eta, distribution, True)
    r = _coating_integral(a, 1.0 / eta, distribution, False)
    return Coating(alpha, eta, distribution, t, float(np.mean(r * _MU) * 2.0))


def transmittance_table(alpha: float, eta: float, distribution: str) -> np.ndarray:
    """t on the 64 table cosines alone (no Fdr: the cheap half of `coating`, for the fit)."""
    if alpha <= 0:
        return 1.0 - fresnel(_MU, eta)[0]
    return _transmittance_cached(float(alpha), float(eta), distribution)


@lru_cache(maxsize=512)
def _transmittance_cached(alpha, eta, distribution):
    return _coating_integral(max(alpha, MIN_ALPHA), eta, distribution, True)


def table_weights(mu: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mitsuba's linear interpolation on the table: t(mu) = (1 - f) t[i] + f t[i + 1]; returns (i, f)."""
    x = np.clip(mu, 0.0, 1.0) * (TABLE_SIZE - 1)
    i = np.minimum(x.astype(np.int64), TABLE_SIZE - 2)
    return i, (x - i)


def specular_albedo_table(alpha: float, eta: float, distribution: str) -> np.ndarray:
    """The coating's specular directional albedo E_s on the 64 table cosines: Mitsuba's
    eval_reflectance, the mean over the visible normals of F G1 of the reflected direction (the
    fraction of light from all directions the lobe reflects towards a view); F(mu) when smooth."""
    if alpha <= 0:
        return fresnel(_MU, eta)[0]
    return _reflectance_cached(float(alpha), float(eta), distribution)


@lru_cache(maxsize=512)
def _reflectance_cached(alpha, eta, distribution):
    return _coating_integral(max(alpha, MIN_ALPHA), eta, distribution, False)


_LOG_ALPHA_STEP = 0.05  # the fit's E_s tables: linear in log alpha between tables this far apart (cached)


def _log_alpha_grid(alpha: float, at):
    """at(alpha) linear in log alpha between its values on the grid of step _LOG_ALPHA_STEP around
    alpha (> 0), and its derivative with respect to log alpha."""
    x = np.log(max(float(alpha), MIN_ALPHA)) / _LOG_ALPHA_STEP
    k = int(np.floor(x))
    f = x - k
    lo, hi = (at(float(np.exp(j * _LOG_ALPHA_STEP))) for j in (k, k + 1))
    return (1.0 - f) * lo + f * hi, (hi - lo) / _LOG_ALPHA_STEP


def specular_albedo_interpolated(alpha: float, eta: float, distribution: str) -> tuple[np.ndarray, np.ndarray]:
    """E_s on the table cosines at alpha (> 0), linear in log alpha between cached tables on a grid of
    step _LOG_ALPHA_STEP, and its derivative with respect to log alpha: for the LM, whose every
    evaluation has another alpha (a Beckmann quadrature costs ~0.8 s; the grid's neighbours are
    reused)."""
    return _log_alpha_grid(alpha, lambda a: _reflectance_cached(a, float(eta), distribution))


def diffuse_reflectance_interpolated(alpha: float, eta: float, distribution: str) -> tuple[float, float]:
    """Fdr (the coating's reflectance of the diffuse base's light from below, as `coating`) at alpha
    (> 0), linear in log alpha between cached tables on the grid of `specular_albedo_interpolated`,
    and its derivative with respect to log alpha. At the default IOR the grid's values are read from
    `coating_tables` (each is a 128^2-node quadrature, 0.1-0.2 s; every plastic fit reads two)."""
    return _log_alpha_grid(alpha, lambda a: _fdr_on_grid(a, float(eta), distribution))


def _grid_fdr(alpha: float, eta: float, distribution: str) -> float:
    """Fdr at alpha as `coating` computes it (2 x the mean over the table's cosines of mu R_int)."""
    return float(np.mean(_reflectance_cached(alpha, 1.0 / float(eta), distribution) * _MU) * 2.0)


def _fdr_on_grid(alpha: float, eta: float, distribution: str) -> float:
    """`_grid_fdr` at a grid alpha exp(k _LOG_ALPHA_STEP): from `coating_tables` when it holds it (the
    default IOR, k in its range), else computed."""
    from . import coating_tables as ct

    values = ct.FDR_GRID.get(distribution)
    if values is not None and eta == ct.FDR_IOR and _LOG_ALPHA_STEP == ct.FDR_STEP:
        k = int(round(np.log(alpha) / _LOG_ALPHA_STEP))
        if abs(np.log(alpha) / _LOG_ALPHA_STEP - k) < 1e-9 and 0 <= k - ct.FDR_FIRST < len(values):
            return values[k - ct.FDR_FIRST]
    return _grid_fdr(alpha, eta, distribution)


GRAZING_NV = 0.2  # views with N.v below this get the lobe's energy cap (`grazing_cap`)


def grazing_cap(lobe_sum, nv, alpha: float, eta: float, distribution: str, table=None) -> np.ndarray:
    """min(1, E_s(N.v) / lobe_sum): the factor that keeps a grazing view's texel-sampled lobe within
    the energy the coating reflects there (`specular_albedo_table`).

    lobe_sum: per view, the lobe with ks = 1 summed over every texel unshadowed (sum_i w_i f_s N.d_i).
    At texel resolution the lobe is sampled at the texel centres with the texel's blur across the
    plane of incidence (1 / (N.v)^2 in slope space) and 1 / (4 N.v): towards N.v -> 0 that sum runs
    away from the lobe's integral, up to 2x at N.v = 0.05 and 3-470x at N.v = 0.004 at R = 32 (alpha 0 ..
    0.3; within ~20 % of it above N.v = 0.2), while the true lobe reflects at most E_s <= 1. A silhouette
    pixel seen that grazingly (an interpolated shading normal at a self-occluding edge, a few
    pixels in 10,000) then renders tens of times the photo and dominates the light's fit; capped,
    it renders what the coating can reflect."""
    nv = np.asarray(nv, np.float64)
    if table is None:  # (the LM passes `specular_albedo_interpolated`'s)
        table = specular_albedo_table(alpha, eta, distribution)
    E = np.interp(np.clip(nv, 0.0, 1.0), _MU, table)
    s = np.asarray(lobe_sum, np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(s > E, E / np.maximum(s, 1e-300), 1.0)


# -- the specular lobe in blocks (transport kernel and LM share it) ---------------------------------
TEXEL_BLUR = 0.25  # the light's blur inside a texel: variance TEXEL_BLUR x w_i per axis (w_i its solid angle)


FOOTPRINT_SPREAD = {"beckmann": 2.0, "ggx": 4.0}  # roughness^2 per unit of slope variance (the lobe's core)


def footprint_roughness(normals: np.ndarray, views: np.ndarray, jacobian: np.ndarray | None,
                        distribution: str) -> np.ndarray | None:
    """(P, 2) float32: the roughness^2 a pixel's footprint adds to its lobe along the lobe's two axes
    (along v's tangent, across it: `lobe_factors`), or None without normal Jacobians.

    A pixel averages the lobe over the normals its footprint sees: the normal turns by J (u, v) for
    (u, v) uniform over the pixel (`camera.normal_jacobian`), a tilt of variance
    s^2 = sum_a (J_a . t)^2 / 12 along a tangent t, which moves the half vector's slope as much. It is
    added to the variance of the distribution's core: Beckmann's slopes have alpha^2 / 2 per axis
    (exact: a Gaussian), GGX's core exp(-2 r^2 / alpha^2) alpha^2 / 4, so alpha^2 grows by 2 s^2 and
    4 s^2 (`FOOTPRINT_SPREAD`). Against the lobe averaged over the pixel's normals (turns of 0.15 and
    0.1 per pixel, tests/test_footprint.py) that keeps the peak within ~2 % at alpha 0.1 (13 % for
    Beckmann at 0.05, where the pixel's box shows), where the unwidened lobe's is 1.3-1.5x too high at
    alpha 0.1 and 2.3-3x at 0.05."""
    if jacobian is None:
        return None
    n = np.asarray(normals, np.float64)
    v = np.asarray(views, np.float64)
    J = np.asarray(jacobian, np.float64)
    t = v - np.einsum("pk,pk->p", n, v)[:, None] * n
    length = np.linalg.norm(t, axis=1)
    iso = length < 1e-6  # (seen head on: no axis along the view, half the turn's variance on each)
    t = t / np.where(iso, 1.0, length)[:, None]
    s = np.cross(n, t)
    ex = np.einsum("pk,pka->pa", t, J)
    ey = np.einsum("pk,pka->pa", s, J)
    k = FOOTPRINT_SPREAD[distribution] / 12.0
    out = np.column_stack([(ex * ex).sum(1), (ey * ey).sum(1)]) * k
    total = np.einsum("pka,pka->p", J, J) * k
    out[iso] = 0.5 * total[iso, None]
    return out.astype(np.float32)


def samples_footprint(samples, rows, material) -> np.ndarray | None:
    """`footprint_roughness` of some rows of `PixelSamples` under `material`'s lobe: None unless the
    material is a microfacet one (`plastic`) and the samples carry normal Jacobians."""
    from .materials import PLASTIC

    jac = getattr(samples, "normal_jacobian", None)
    if jac is None or material is None or material.model != PLASTIC:
        return None
    return footprint_roughness(np.asarray(samples.normal)[rows], np.asarray(samples.view)[rows], np.asarray(jac)[rows],
                               material.distribution)


def _footprint_columns(footprint, ndim: int):
    """A (P, 2) footprint's two widenings shaped to add to (P, N) blocks (a column each) or to (P,)
    point evaluations."""
    fp = np.asarray(footprint, np.float32)
    return (fp[:, :1], fp[:, 1:2]) if ndim == 2 else (fp[:, 0], fp[:, 1])


def lobe_factors(nd, nv, vd, w, eta, blur: float = TEXEL_BLUR, footprint=None):
    """Per (pixel, texel) parts of the lobe that do not depend on alpha, from N.d (nd), N.v (nv, a
    column), v.d (vd) and the texels' solid angles w (a row; 0 for a point evaluation), float32 blocks.

    Returns (A, x2, y2, wx, wy, t2d): A = w F(v.h) / (4 N.v cos^4 h) [0 where N.d or N.v <= 0]; the
    half vector's squared slopes in the plane of incidence (x2, along v's tangent) and across it (y2);
    the roughness^2 the texel adds along each (wx, wy); tan^2 of d (for G1). The radiance of light L
    through the lobe is L A Dn G1(v) G1(d) with Dn = D cos^4 h of roughness^2 (a^2 + wx, a^2 + wy)
    (`lobe_values`).

    The texel's blur: a texel's radiance is spread over its solid angle, which a lobe narrower than a
    texel must not alias. The light is blurred inside the texel with variance `blur` x w per axis of
    the light direction (1/4: a Gaussian that wide summed over texel centres one sqrt(w) apart is its
    integral to ~1.4 %, wherever its peak falls; the texel's own box has w/12 and ripples by ~40 %;
    a wider blur ripples less but softens a sun's highlight more, measured against Mitsuba in
    tests/test_plastic_mitsuba.py), mapped to the half vector (in the plane of incidence d turns twice
    as fast as h, across it 2 v.h times as fast) and to its slopes (1/cos^2 h along, 1/cos h across),
    and added to the distribution's slope variance (a^2 / 2 per axis: exact for Beckmann, the core
    for GGX). The lobe's integral is unchanged.

    `footprint`: None or the (b, 2) roughness^2 the pixels' footprints add along and across
    (`footprint_roughness`), added to (wx, wy)."""
    vh2 = np.maximum(0.5 * (1.0 + vd), 1e-12)  # (v.h)^2 = (1 + v.d) / 2
    vh = np.sqrt(vh2)
    s_ = nv + nd  # (v + d).N; |v + d| = 2 v.h
    nh = np.clip(s_ / (2.0 * vh), 1e-6, 1.0)
    c2 = nh * nh
    t2h = (1.0 - c2) / c2
    sv = np.sqrt(np.maximum(1.0 - nv * nv, 1e-12))
    with np.errstate(invalid="ignore", divide="ignore"):
        x = (sv + (vd - nv * nd) / sv) / np.maximum(s_, 1e-6)  # (v + d) . t_v / (v + d) . N
    t2h = np.minimum(t2h, 1e6)  # (theta_h < 89.94 deg: beyond, D is nil; keeps float32 finite)
    c2 = 1.0 / (1.0 + t2h)
    x2 = np.minimum(x * x, t2h)
    y2 = t2h - x2
    F = fresnel_outside(vh, eta)
    up = (nd > 0) & (nv > 0)
    A = np.where(up, w * F / (4.0 * np.maximum(nv, 1e-6) * c2 * c2), 0.0).astype(np.float32)
    var = blur * w / 4.0 * 2.0  # light-direction variance / 4 (h turns half as fast), x 2 (alpha^2 = 2 sigma^2)
    wx = (var / (c2 * c2)).astype(np.float32)
    wy = (var / (np.maximum(vh2, 1e-4) * c2)).astype(np.float32)  # across, d turns 2 v.h times as fast as h
    if footprint is not None:
        fx, fy = _footprint_columns(footprint, np.ndim(wx))
        wx = wx + fx
        wy = wy + fy
    ndc = np.clip(nd, 1e-6, 1.0)
    t2d = ((1.0 - ndc * ndc) / (ndc * ndc)).astype(np.float32)
    return A, x2.astype(np.float32), y2.astype(np.float32), wx, wy, t2d


def lobe_factors_f32(nd, nv, vd, w, eta, blur: float = TEXEL_BLUR, footprint=None):
    """`lobe_factors` for float32 blocks (nd, vd (b, N); nv (b, 1); w (1, N)), in in-place passes on
    five buffers where `lobe_factors` allocates ~30 temporaries: the same values to float32 rounding
    (the render's plastic transport and the fit's data, per (pixel, texel) pair)."""
    f32 = np.float32
    nd, vd = np.asarray(nd, f32), np.asarray(vd, f32)
    nv, w = np.asarray(nv, f32), np.asarray(w, f32)
    vh = vd + f32(1.0)
    vh *= f32(0.5)
    np.maximum(vh, f32(1e-12), out=vh)
    np.sqrt(vh, out=vh)  # v.h
    s_ = nd + nv  # (v + d).N = 2 v.h N.h
    c2 = np.divide(s_, vh, out=np.empty_like(nd))
    c2 *= f32(0.5)
    np.clip(c2, f32(1e-6), f32(1.0), out=c2)
    c2 *= c2  # cos^2 h
    t2h = np.subtract(f32(1.0), c2)
    t2h /= c2
    np.minimum(t2h, f32(1e6), out=t2h)  # (theta_h < 89.94 deg: beyond, D is nil)
    np.add(t2h, f32(1.0), out=c2)
    np.reciprocal(c2, out=c2)  # cos^2 h of the capped tan^2
    sv = np.sqrt(np.maximum(f32(1.0) - nv * nv, f32(1e-12)))
    x2 = nd * nv
    np.subtract(vd, x2, out=x2)
    x2 /= sv
    x2 += sv
    np.maximum(s_, f32(1e-6), out=s_)
    x2 /= s_  # the slope along: (v + d) . t_v / (v + d) . N
    x2 *= x2
    np.minimum(x2, t2h, out=x2)
    y2 = np.subtract(t2h, x2, out=t2h)
    A = fresnel_outside(vh, eta)
    A *= w
    A /= c2
    A /= c2
    A *= f32(0.25) / np.maximum(nv, f32(1e-6))
    A *= nd > 0
    A *= nv > 0
    var = (f32(blur) * w / f32(4.0) * f32(2.0)).astype(f32)
    wx = np.multiply(c2, c2)
    np.divide(var, wx, out=wx)
    wy = c2 * np.maximum(vh * vh, f32(1e-4))
    np.divide(var, wy, out=wy)
    if footprint is not None:
        fx, fy = _footprint_columns(footprint, np.ndim(wx))
        wx += fx
        wy += fy
    t2d = np.clip(nd, f32(1e-6), f32(1.0), out=vh)
    t2d *= t2d
    np.subtract(f32(1.0), t2d, out=s_)
    s_ /= t2d
    return A, x2, y2, wx, wy, s_


def lobe_values(x2, y2, wx, wy, alpha: float, distribution: str, out=None, derivative_out=None):
    """Dn = D(h) cos^4(h) of the anisotropic distribution with roughness^2 (alpha^2 + wx, alpha^2 + wy)
    along the slopes (x2, y2) (float32 blocks), into `out`; with `derivative_out`, also
    dDn / d log alpha there."""
    a2 = np.float32(alpha * alpha)
    if derivative_out is None:  # (the fit's and the render's inner loop: in place)
        ax = wx + a2
        ay = wy + a2
        norm = ax * ay
        np.sqrt(norm, out=norm)
        norm *= np.float32(np.pi)
        q = np.divide(x2, ax, out=ax if out is None else out)
        q += np.divide(y2, ay, out=ay)
        if distribution == "ggx":
            q += np.float32(1.0)
            q *= q
            q *= norm
            return np.divide(np.float32(1.0), q, out=q)
        np.negative(q, out=q)
        np.exp(q, out=q)
        q /= norm
        return q
    ax = wx + a2
    ay = wy + a2
    q = x2 / ax
    q += y2 / ay
    norm = np.sqrt(ax * ay)
    norm *= np.float32(np.pi)
    if distribution == "ggx":  # Dn = 1 / (pi ax ay (1 + x2/ax2 + y2/ay2)^2)
        q += np.float32(1.0)
        if derivative_out is not None:  # d log Dn / d ax2 = -1/(2 ax2) + 2 x2 / (ax2^2 q)
            np.divide(x2 / (ax * ax) + y2 / (ay * ay), q, out=derivative_out)
            derivative_out *= np.float32(2.0)
        res = np.multiply(q, q, out=np.empty_like(x2) if out is None else out)
        res *= norm
        np.divide(np.float32(1.0), res, out=res)
    else:  # Dn = exp(-(x2/ax2 + y2/ay2)) / (pi ax ay)
        if derivative_out is not None:  # d log Dn / d ax2 = x2 / ax2^2 - 1/(2 ax2)
            np.add(x2 / (ax * ax), y2 / (ay * ay), out=derivative_out)
        res = np.negative(q, out=np.empty_like(x2) if out is None else out)
        np.exp(res, out=res)
        res /= norm
    if derivative_out is not None:
        derivative_out -= np.float32(0.5) / ax
        derivative_out -= np.float32(0.5) / ay
        derivative_out *= res
        derivative_out *= np.float32(2.0) * a2
    return res


def eval_cos(kd, ks, alpha: float, eta: float, distribution: str, nv, nd, vd,
             footprint=None) -> tuple[np.ndarray, np.ndarray]:
    """The BRDF times the light's cosine, f(v, d) max(0, N.d), pointwise (no texel widening): the
    diffuse and the specular part for cosines N.v (nv), N.d (nd) and v.d (vd) of equal shapes;
    kd and ks scalars. What Mitsuba's `BSDF.eval` returns for roughplastic (the tests compare).
    `footprint`: (n, 2) a pixel footprint's widening of the lobe (`footprint_roughness`), or None."""
    nv, nd, vd = (np.asarray(x, np.float64) for x in (nv, nd, vd))
    coat = coating(alpha, eta, distribution)
    up = (nv > 0) & (nd > 0)
    diffuse = np.where(up, kd * coat.base_scale * coat.transmittance(nv) * coat.transmittance(nd) * nd / np.pi, 0.0)
    if alpha <= 0:
        return diffuse, np.zeros_like(diffuse)
    A, x2, y2, wx, wy, t2d = lobe_factors(nd, nv, vd, np.float64(1.0), eta, blur=0.0, footprint=footprint)
    a = max(float(alpha), MIN_ALPHA)
    g1v = smith_g1((1.0 - np.minimum(nv, 1.0) ** 2) / np.maximum(nv, 1e-6) ** 2, a, distribution)
    f64 = [np.asarray(v, np.float64) for v in (x2, y2, wx, wy)]
    spec = ks * A * lobe_values(*f64, a, distribution) * smith_g1(t2d, a, distribution) * g1v
    return diffuse, np.where(up, spec, 0.0)
