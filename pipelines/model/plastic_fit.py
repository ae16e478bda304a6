"""The `plastic` reflectance fit with the light fixed: kd (RGB), ks (RGB) and log alpha by
Levenberg-Marquardt (bounded: trust-region reflective), for `reflectance.alternate` and `select`.

With the light fixed, pixel j's channel c renders

    I_jc = kd_c B_jc(alpha) + ks_c S_jc(alpha)
    B_jc = b(alpha) t(N.v_j) sum_i D_ij t(N.d_i) L_ic          (the base seen through the coating)
    S_jc = G1(v_j) sum_i A_ij Dn_ij(alpha) G1(d_i) L_ic        (the coating's lobe, `microfacet`)

D_ij = V max(0, N.m_i) / pi and A_ij = V w_i F(v.h) / (4 N.v cos^4 h) do not depend on alpha and are
computed once per light over the lit texels (`plastic_data`), with the slopes of the half vector and
N.d; an evaluation is then a few float32 passes over (pixel, lit texel) pairs. The base's constant
b(alpha) = 1 / (eta^2 (1 - Fdr(alpha))) costs a quadrature of its own, so the LM fits kd' = kd b(alpha)
and kd = kd' / b(alpha) at the end; t's derivative with respect to log alpha is the table's central
difference (the tables cost milliseconds), the lobe's is analytic. The IOR and the distribution are
the start's (given, or 1.49 and ggx). A scan over alpha (kd', ks >= 0 exact at each alpha) guards the
start, as the Blinn-Phong fit's scan over n does.

kd' and ks enter linearly: at a given alpha their best values (>= 0) are a 2-column NNLS per channel
(`_linear_fit`), so the fit is a search in log alpha alone over that profile (variable projection:
`method="profile"`, the default; parabolic interpolation in a bracket with Brent's safeguards, each
step one evaluation without derivatives: ~5-10 per fit where LM took 12-14 with them). LM over all
seven parameters (`method="lm"`) reaches the same optimum and is kept as the reference; the
derivatives serve both for the one-sigma uncertainties.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares, nnls

from ..geometry.visibility import decode
from ..threads import parallel_blocks
from . import microfacet as mf
from .materials import PLASTIC, Material

ALPHA_RANGE = (0.005, 1.0)  # a fitted alpha is kept inside this (log-parametrised bounds)
SCAN_ALPHA = (0.01, 0.02, 0.04, 0.07, 0.12, 0.2, 0.35, 0.6)  # the start's guard (factors <= 2)
MAX_PAIRS = 24_000_000  # (pixel, lit texel) pairs held (6 float32 arrays: ~580 MB)
_BLOCK = 256
_DLOG = 0.02  # the tables' central difference in log alpha
PROFILE_STEP = np.log(1.1)  # the profile search's first bracket around its start (log alpha)
PROFILE_XTOL = 1e-4  # and where it stops (log alpha: alpha to 0.01 %; its sigma is ~1e-3 and more)
PROFILE_MAX = 40  # evaluations a search may take (it needs ~5 from a bracket)


@dataclass
class PlasticData:
    """The LM's inputs for one light (see the module's docstring): per (row, lit texel) float32 arrays
    of the lobe's alpha-free parts, rows weighted by sqrt(weight); the base as Q, its sum over the
    lit texels against each of the 64 hat functions of the transmittance table's linear
    interpolation (t(N.d) = sum_k T_k(alpha) hat_k(N.d)), so that B'(alpha) = t(N.v) Q T(alpha)."""

    model: str
    distribution: str
    ior: float
    Q: np.ndarray  # (P, 64, 3) sum_i D_i hat_k(N.d_i) L_i, x sqrt(weight)
    lambert: np.ndarray  # (P, 3) sum_i D_i L_i (Lambert's shading), x sqrt(weight)
    A: np.ndarray  # V w F / (4 N.v cos^4 h), x sqrt(weight)
    x2: np.ndarray  # the half vector's slopes^2 along the plane of incidence
    y2: np.ndarray  # and across it
    wx: np.ndarray  # the texel blur's roughness^2 along
    wy: np.ndarray  # and across
    t2d: np.ndarray  # tan^2 of the light direction
    nv: np.ndarray  # (P,) N.v
    light: np.ndarray  # (K, 3)
    photo: np.ndarray  # (P, 3) x sqrt(weight)
    fit: np.ndarray  # (P,) bool
    n_pixels_available: int
    lit_texels: int
    rows: np.ndarray
    # grazing views (N.v < microfacet.GRAZING_NV): their positions in the rows and the lobe's factors
    # over every texel, unshadowed and unweighted, for the lobe's energy cap (`microfacet.grazing_cap`)
    graze: np.ndarray | None = None
    graze_factors: tuple | None = None

    def _caps(self, a: float, derivative: bool = False):
        """The grazing rows' energy caps at alpha (as `render.plastic_specular_transport`), and with
        `derivative` their derivatives with respect to log alpha (0 where a cap is inactive)."""
        if self.graze is None or not len(self.graze):
            return None
        A, x2, y2, wx, wy, t2d = self.graze_factors
        dist = self.distribution
        de = np.empty_like(x2) if derivative else None
        e = mf.lobe_values(x2, y2, wx, wy, a, dist, derivative_out=de)
        g = mf.smith_g1(t2d, a, dist, derivative=derivative)
        nv = self.nv[self.graze]
        g1v = mf.smith_g1((1.0 - np.minimum(nv, 1.0) ** 2) / np.maximum(nv, 1e-6) ** 2, a, dist,
                          derivative=derivative)
        if derivative:
            (g, dg), (g1v, dg1v) = g, g1v
            de *= np.asarray(g, np.float32)
            de += e * np.asarray(dg, np.float32)
            de *= A
            d_inner = de.sum(axis=1, dtype=np.float64)
        e *= np.asarray(g, np.float32)
        e *= A
        inner = e.sum(axis=1, dtype=np.float64)
        total = inner * g1v
        table, dtable = mf.specular_albedo_interpolated(a, self.ior, dist)
        caps = mf.grazing_cap(total, nv, a, self.ior, dist, table)
        if not derivative:
            return caps
        # c = E / total where active: d log c = d log E - d log total
        mu = np.clip(nv, 0.0, 1.0)
        dlogE = np.interp(mu, mf._MU, dtable) / np.maximum(np.interp(mu, mf._MU, table), 1e-300)
        dlog_total = (d_inner * g1v + inner * dg1v) / np.maximum(total, 1e-300)
        dcaps = np.where(caps < 1.0, caps * (dlogE - dlog_total), 0.0)
        return caps, dcaps

    def evaluate(self, alpha: float, derivative: bool = False):
        """(B', S) (P, 3) each: the base without b(alpha) and the lobe; with `derivative` also their
        derivatives with respect to log alpha."""
        a = float(alpha)
        dist = self.distribution
        T = mf.transmittance_table(a, self.ior, dist)
        tv = np.interp(self.nv, mf._MU, T) * (self.nv > 0)
        Bq = np.einsum("pkc,k->pc", self.Q, T)
        g1v = mf.smith_g1((1.0 - np.minimum(self.nv, 1.0) ** 2) / np.maximum(self.nv, 1e-6) ** 2, a, dist,
                          derivative=derivative)
        if derivative:
            dT = (mf.transmittance_table(a * np.exp(_DLOG), self.ior, dist)
                  - mf.transmittance_table(a * np.exp(-_DLOG), self.ior, dist)) / (2 * _DLOG)
            dtv = np.interp(self.nv, mf._MU, dT) * (self.nv > 0)
            dBq = np.einsum("pkc,k->pc", self.Q, dT)
            g1v, dg1v = g1v
        L = self.light.astype(np.float32)
        P = len(self.nv)
        S0 = np.empty((P, 3))
        dS0 = np.empty((P, 3)) if derivative else None

        def run(starts):
            for s in starts:
                sl = slice(s, min(P, s + _BLOCK))
                dDn = np.empty_like(self.x2[sl]) if derivative else None
                e = mf.lobe_values(self.x2[sl], self.y2[sl], self.wx[sl], self.wy[sl], a, dist, derivative_out=dDn)
                g = mf.smith_g1_f32(self.t2d[sl], a, dist, derivative=derivative)
                if derivative:
                    g, dg = g
                    dDn *= g
                    dDn += e * np.asarray(dg, np.float32)
                    dDn *= self.A[sl]
                    dS0[sl] = dDn @ L
                e *= np.asarray(g, np.float32)
                e *= self.A[sl]
                S0[sl] = e @ L

        parallel_blocks(run, list(range(0, P, _BLOCK)))
        B = Bq * tv[:, None]
        S = S0 * g1v[:, None]
        caps = self._caps(a, derivative)
        if not derivative:
            if caps is not None:
                S[self.graze] *= caps[:, None]
            return B, S
        dB = Bq * dtv[:, None] + dBq * tv[:, None]
        dS = dS0 * g1v[:, None] + S0 * dg1v[:, None]
        if caps is not None:  # the grazing rows: (c S)' = c S' + c' S
            c, dc = caps
            k = self.graze
            dS[k] = c[:, None] * dS[k] + dc[:, None] * S[k]
            S[k] *= c[:, None]
        return B, S, dB, dS


def plastic_data(vis, photo: np.ndarray, light: np.ndarray, material: Material, use=None, held_out=None,
                 rows=None, weights=None, max_pairs: int = MAX_PAIRS, albedo=None, lobe=None) -> PlasticData:
    """Precompute the LM's inputs for a light (N, 3), as `reflectance.specular_data` (same
    arguments; `material` gives the IOR and the distribution)."""
    from .reflectance import fit_inputs

    L, lit, P, use, held_out, rows, weights = fit_inputs(vis, light, use, held_out, rows, weights, max_pairs,
                                                          cap_given=True)
    s, cube = vis.samples, vis.cube
    K, n = len(lit), len(rows)
    arrays = {k: np.empty((n, K), np.float32) for k in ("A", "x2", "y2", "wx", "wy", "t2d")}
    Q = np.zeros((n, mf.TABLE_SIZE, 3))
    lam = np.empty((n, 3))
    dirs = cube.directions[lit].astype(np.float32)
    m = cube.vector_solid_angles[lit].astype(np.float32)
    w = cube.solid_angles[lit].astype(np.float32)[None, :]
    nv = np.einsum("pk,pk->p", s.normal[rows], s.view[rows])
    footprint = mf.samples_footprint(s, rows, material)  # (the roughness^2 each pixel's footprint adds)
    L32 = L[lit].astype(np.float32)
    # blocks of stored rows (the selected ones of each: `rows` is sorted), on both cores
    firsts = np.arange(0, P, 1024)
    bounds = np.searchsorted(rows, np.append(firsts, P))
    blocks = [b for b in range(len(firsts)) if bounds[b + 1] > bounds[b]]

    def run(todo):
        for b in todo:
            k = slice(int(bounds[b]), int(bounds[b + 1]))
            r = rows[k]
            V = decode(np.asarray(vis.stored[r]), cube.n_texels, vis.encoding)[:, lit].astype(np.float32)
            nrm = s.normal[r].astype(np.float32)
            vw = s.view[r].astype(np.float32)
            D = np.maximum(nrm @ m.T, 0.0) * V / np.float32(np.pi)
            lam[k] = D @ L32
            nd = nrm @ dirs.T
            x = np.clip(nd, 0.0, 1.0) * np.float32(mf.TABLE_SIZE - 1)  # the table's hat functions at N.d
            i = np.minimum(x.astype(np.int32), mf.TABLE_SIZE - 2)
            f = x - i
            nb, T = len(r), mf.TABLE_SIZE
            idx = (np.arange(nb, dtype=np.int64)[:, None] * T + i).ravel()
            lo_w, hi_w = (D * (1 - f)).ravel(), (D * f).ravel()
            for c in range(3):  # Q[row, j] += D (1 - f) L, Q[row, j + 1] += D f L (the two hats of each pair)
                Lc = np.broadcast_to(L32[None, :, c], D.shape).ravel()
                Q[k, :, c] += np.bincount(idx, lo_w * Lc, minlength=nb * T).reshape(nb, T)
                Q[k, :, c] += np.bincount(idx + 1, hi_w * Lc, minlength=nb * T + 1)[: nb * T].reshape(nb, T)
            A, x2, y2, wx, wy, t2d = mf.lobe_factors_f32(nd, nv[k, None].astype(np.float32), vw @ dirs.T, w, material.ior,
                                                         footprint=None if footprint is None else footprint[k])
            arrays["A"][k] = A * V
            arrays["x2"][k], arrays["y2"][k], arrays["wx"][k], arrays["wy"][k], arrays["t2d"][k] = x2, y2, wx, wy, t2d

    parallel_blocks(run, blocks)
    graze = np.flatnonzero(nv < mf.GRAZING_NV)
    graze_factors = None
    if len(graze):
        g_rows = rows[graze]
        all_dirs = cube.directions.astype(np.float32)
        nrm = s.normal[g_rows].astype(np.float32)
        graze_factors = mf.lobe_factors(nrm @ all_dirs.T, nv[graze, None].astype(np.float32),
                                        s.view[g_rows].astype(np.float32) @ all_dirs.T,
                                        cube.solid_angles.astype(np.float32)[None, :], material.ior,
                                        footprint=None if footprint is None else footprint[graze])
    values = np.asarray(photo, np.float64)[rows]
    if albedo is not None:  # per-pixel relative albedo (parts, textures) under the base
        a_rows = np.asarray(albedo, np.float64)[rows]
        Q *= a_rows[:, None, :]
        lam *= a_rows
    if lobe is not None:  # per-pixel factor on the lobe (a part's specular weight)
        arrays["A"] *= np.asarray(lobe, np.float32)[rows][:, None]
    if weights is not None:
        sw = np.sqrt(weights)
        arrays["A"] *= sw.astype(np.float32)[:, None]
        Q *= sw[:, None, None]
        lam *= sw[:, None]
        values = values * sw[:, None]
    a = arrays
    return PlasticData(PLASTIC, material.distribution, float(material.ior), Q, lam, a["A"], a["x2"], a["y2"], a["wx"],
                       a["wy"], a["t2d"], nv, L[lit], values, ~held_out[rows], int(use.sum()), K, rows, graze,
                       graze_factors)


def base_scale(alpha: float, ior: float, distribution: str) -> float:
    return mf.coating(float(alpha), float(ior), distribution).base_scale


def base_scale_slope(alpha: float, ior: float, distribution: str) -> float:
    """d log b / d log alpha, for the uncertainties only: b = 1 / (eta^2 (1 - Fdr)), with Fdr's
    slope between the cached tables around alpha (`microfacet.diffuse_reflectance_interpolated`), not two
    more quadratures (~0.1-0.3 s each) per fit."""
    fdr, dfdr = mf.diffuse_reflectance_interpolated(alpha, ior, distribution)
    return float(dfdr / max(1.0 - fdr, 1e-12))


def _linear_fit(data: PlasticData, alpha: float):
    """Best kd' (3) and ks (3) >= 0 at a fixed alpha (per channel a 2-column NNLS) and the squared
    residual over the fit rows."""
    f = data.fit
    B, S = data.evaluate(alpha)
    coef, sq = np.zeros(6), 0.0
    for c in range(3):
        design = np.column_stack([B[f, c], S[f, c]])
        scale = np.sqrt((design**2).sum(axis=0))
        scale[scale == 0] = 1.0
        x, rnorm = nnls(design / scale, data.photo[f, c], maxiter=50)
        coef[c], coef[3 + c] = x / scale
        sq += float(rnorm**2)
    return coef, sq


class _Profile:
    """The fit's squared residual at the best kd', ks >= 0 of each log alpha (`_linear_fit`),
    memoised, with the number of evaluations."""

    def __init__(self, data: PlasticData, lo: float, hi: float):
        self.data, self.lo, self.hi = data, lo, hi
        self.memo: dict = {}

    def __call__(self, la: float) -> float:
        return self.at(la)[1]

    def at(self, la: float):
        la = float(np.clip(la, self.lo, self.hi))
        if la not in self.memo:
            self.memo[la] = _linear_fit(self.data, float(np.exp(la)))
        return self.memo[la]

    def bracket(self, la0: float) -> tuple[float, float]:
        """An interval of log alpha around a local minimum, from la0: downhill in steps that double
        from PROFILE_STEP until the profile rises again (or alpha's range ends)."""
        la0 = float(np.clip(la0, self.lo, self.hi))
        f0 = self(la0)
        step = PROFILE_STEP
        for direction in (1.0, -1.0):
            la1 = float(np.clip(la0 + direction * step, self.lo, self.hi))
            if la1 != la0 and self(la1) < f0:
                break
        else:
            return max(la0 - step, self.lo), min(la0 + step, self.hi)
        prev, cur = la0, la1
        while True:
            step *= 2.0
            nxt = float(np.clip(cur + direction * step, self.lo, self.hi))
            if nxt == cur or self(nxt) >= self(cur):
                return (min(prev, nxt), max(prev, nxt)) if nxt != cur else (min(prev, cur), max(prev, cur))
            prev, cur = cur, nxt

    def minimum(self, lo: float, hi: float) -> float:
        """The minimum on [lo, hi] (log alpha) by successive parabolic interpolation through the
        three best points of a bracket, with golden-section steps where a parabola cannot be
        trusted (Brent's safeguards), reusing every point evaluated; the best point evaluated in
        [lo, hi] (not elsewhere: `fit_plastic` compares a local search's end with the scan's best)."""
        g = 0.5 * (3.0 - np.sqrt(5.0))
        a, c = float(lo), float(hi)
        inside = [la for la in self.memo if a < la < c]
        b = min(inside, key=self) if inside else a + g * (c - a)
        fa, fb, fc = self(a), self(b), self(c)
        if fb > min(fa, fc):  # not a bracket: the minimum is at (or next to) an end
            return a if fa <= fc else c
        last = prev = c - a
        for _ in range(PROFILE_MAX):
            if c - a <= 2.0 * PROFILE_XTOL or min(fa, fc) == fb:
                break  # (narrow enough, or flat: no lobe, every alpha fits alike)
            x = None
            den = (b - a) * (fb - fc) - (b - c) * (fb - fa)
            if den != 0.0:
                x = b - 0.5 * ((b - a) ** 2 * (fb - fc) - (b - c) ** 2 * (fb - fa)) / den
                if not (a < x < c) or abs(x - b) > 0.5 * prev:
                    x = None  # outside the bracket, or not shrinking fast enough: golden section
            if x is None:
                x = b + g * (c - b) if c - b > b - a else b - g * (b - a)
            elif abs(x - b) < PROFILE_XTOL:
                break  # the parabola's vertex is where we are
            prev, last = last, abs(x - b)
            fx = self(x)
            if fx < fb:
                if x < b:
                    c, fc = b, fb
                else:
                    a, fa = b, fb
                b, fb = x, fx
            elif x < b:
                a, fa = x, fx
            else:
                c, fc = x, fx
        return min((la for la in self.memo if lo <= la <= hi), key=lambda la: self.memo[la][1])

    def search(self, la0: float) -> float:
        return self.minimum(*self.bracket(la0))


def fit_plastic(data: PlasticData, start: Material, max_evaluations: int = 100, guard: bool = True,
                method: str = "profile"):
    """Fit kd, ks (RGB) and alpha with the light fixed; returns a `reflectance.SpecularFit` whose
    material is `plastic` (ks made grey, its colour moved into the light, as `fit_specular`).

    method : "profile" (a search in log alpha over the profile of the linear parameters: the
        module's docstring) or "lm" (Levenberg-Marquardt over all seven, the reference)."""
    if method not in ("profile", "lm"):
        raise ValueError(f"method must be profile or lm, got {method!r}")
    from .reflectance import LM_TOLERANCES, FitError, SpecularFit

    t0 = time.perf_counter()
    f = data.fit
    b = data.photo[f]
    scale = float(np.sqrt(np.mean(b**2))) or 1.0
    lo, hi = np.log(ALPHA_RANGE[0]), np.log(ALPHA_RANGE[1])
    nfev = 0
    cache: dict = {}

    def parts(la):  # every evaluation with its derivative: trf asks for the Jacobian at most points
        key = float(la)
        if key not in cache:
            if len(cache) > 3:
                cache.clear()
            cache[key] = data.evaluate(float(np.exp(la)), True)
        return cache[key]

    def residual(x):
        nonlocal nfev
        nfev += 1
        B, S = parts(x[6])[:2]
        r = x[:3][None, :] * B[f] + x[3:6][None, :] * S[f] - b
        return (r / scale).T.ravel()

    def jacobian(x):
        B, S, dB, dS = parts(x[6])
        B, S, dB, dS = B[f], S[f], dB[f], dS[f]
        m = len(B)
        J = np.zeros((3 * m, 7))
        for c in range(3):
            rows = slice(c * m, (c + 1) * m)
            J[rows, c] = B[:, c]
            J[rows, 3 + c] = S[:, c]
            J[rows, 6] = x[c] * dB[:, c] + x[3 + c] * dS[:, c]
        return J / scale

    def lm(x0):
        x0 = np.array(x0, float)
        x0[:6] = np.maximum(x0[:6], 1e-12)
        x0[6] = np.clip(x0[6], lo + 1e-9, hi - 1e-9)
        res = least_squares(residual, x0, jac=jacobian, method="trf", x_scale="jac",
                            bounds=([0.0] * 6 + [lo], [np.inf] * 6 + [hi]),
                            max_nfev=max_evaluations, **LM_TOLERANCES)
        return res.x, float(2 * res.cost) * scale**2

    a0 = float(np.clip(start.roughness if start.roughness > 0 else 0.1, *ALPHA_RANGE))
    if method == "lm":  # (the profile search needs no start for the linear parameters)
        b0 = base_scale(a0, data.ior, data.distribution)
        x0 = np.array([*(np.asarray(start.kd) * b0), *start.ks, np.log(a0)], float)
    path, message = "lm", "converged from the start"
    if method == "profile":
        profile = _Profile(data, lo, hi)
        path, message = "profile", "converged from the start"
        la = None
        if guard:
            # the scan's alphas on the profile: its best one's neighbours bracket the global basin; the
            # start's own basin is searched first when the start fits better than every scan point
            for a in SCAN_ALPHA:
                profile.at(np.log(a))
            scan = sorted(profile.memo)
            best = min(range(len(scan)), key=lambda i: profile.memo[scan[i]][1])
            sq_best = profile.memo[scan[best]][1]
            coef = profile.memo[scan[best]][0]
            if not np.any(coef[3:6] > 0) and sq_best <= profile(np.log(a0)):
                la, path = scan[best], "scan"
                message = "no specular term fits at any alpha of the scan (ks = 0): the data support no highlight"
            elif profile(np.log(a0)) <= sq_best:
                la = profile.search(np.log(a0))
            if la is None or (path != "scan" and profile(la) > sq_best):
                restarted = la is not None
                la = profile.minimum(scan[best - 1] if best > 0 else lo, scan[best + 1] if best + 1 < len(scan) else hi)
                path = "scan+profile"
                message = (f"the search from the start (alpha = {a0:g}) stopped in a worse local optimum; restarted "
                           f"at the scan's best alpha = {np.exp(scan[best]):g}" if restarted else
                           f"started at the scan's best alpha = {np.exp(scan[best]):g} (it fits better than "
                           f"alpha = {a0:g})")
        else:
            la = profile.search(np.log(a0))
        nfev = len(profile.memo)
        coef, sq = profile.at(la)
        x = np.array([*coef, float(np.clip(la, lo, hi))])
    elif guard:
        # alpha is the one nonlinear parameter: a scan over it (kd', ks >= 0 exact at each alpha) finds
        # the global optimum's basin; LM starts from the scan's best when that fits better than the
        # start, and from the scan's best again if LM from the start ends worse than it
        scan = [(_linear_fit(data, a), a) for a in SCAN_ALPHA]
        (coef, sq_best), a_best = min(scan, key=lambda t: t[0][1])
        xs = np.array([*coef, np.log(a_best)])
        sq_start = float(np.sum(residual(x0) ** 2)) * scale**2
        if not np.any(coef[3:6] > 0) and sq_best <= sq_start:
            x, sq, path = xs, sq_best, "scan"
            message = "no specular term fits at any alpha of the scan (ks = 0): the data support no highlight"
        else:
            from_scan = sq_best < sq_start
            x, sq = lm(xs if from_scan else x0)
            if from_scan:
                path, message = "scan+lm", f"started at the scan's best alpha = {a_best:g} (it fits better than " \
                                           f"alpha = {a0:g})"
            elif sq > sq_best:
                x2_, sq2 = lm(xs)
                if sq2 < sq:
                    x, sq, path = x2_, sq2, "scan+lm"
                    message = (f"LM from the start (alpha = {a0:g}) stopped in a worse local optimum; restarted at "
                               f"the scan's best alpha = {a_best:g}")
    else:
        x, sq = lm(x0)
    if not np.all(np.isfinite(x)):
        raise FitError("the plastic fit did not converge to finite parameters")
    alpha = float(np.exp(x[6]))
    at_bound = x[6] <= lo + 1e-6 or x[6] >= hi - 1e-6
    if at_bound:
        message += f"; alpha is at the end of its range {ALPHA_RANGE}"
    J = jacobian(x)
    r = residual(x)
    dof = max(len(r) - 7, 1)
    cov = (r @ r / dof) * np.linalg.pinv(J.T @ J)
    # kd = kd' / b(alpha): propagate with d log b / d log alpha
    bs = base_scale(alpha, data.ior, data.distribution)
    dlogb = base_scale_slope(alpha, data.ior, data.distribution)
    T = np.eye(7)
    T[:3, :3] /= bs
    T[:3, 6] = -np.maximum(x[:3], 0) / bs * dlogb
    cov = T @ cov @ T.T
    sd = np.sqrt(np.maximum(np.diag(cov), 0.0))
    kd = np.maximum(x[:3], 0.0) / bs
    ks_rgb = np.maximum(x[3:6], 0.0)
    sigma = {"kd": sd[:3].tolist(), "ks_rgb": sd[3:6].tolist(), "ks": float(np.sqrt(max(cov[3:6, 3:6].sum(), 0.0)) / 3),
             "alpha": float(alpha * sd[6]), "log_alpha": float(sd[6])}
    ks = float(ks_rgb.mean())
    light_scale = np.ones(3)
    if ks > 0 and np.all(ks_rgb > 3 * sd[3:6]):
        light_scale = ks_rgb / ks
    material = Material(kd=tuple(float(v) for v in kd / light_scale), ks=(ks, ks, ks), model=PLASTIC,
                        roughness=alpha, distribution=data.distribution, ior=data.ior)
    B, S = parts(x[6])[:2]
    pred = x[:3][None, :] * B + ks_rgb[None, :] * S

    def rel(sel):
        if not sel.any():
            return None
        return float(np.sqrt(((pred[sel] - data.photo[sel]) ** 2).sum() / max((data.photo[sel] ** 2).sum(), 1e-300)))

    return SpecularFit(material, light_scale, ks_rgb, sigma, rel(data.fit), rel(~data.fit),
                       {"kd": list(start.kd), "ks": list(start.ks), "alpha": a0, "distribution": data.distribution,
                        "ior": data.ior}, path, message, nfev, time.perf_counter() - t0, len(data.photo),
                       data.lit_texels)
