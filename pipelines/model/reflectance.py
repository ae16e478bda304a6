"""Reflectance: the specular parameters by Levenberg-Marquardt, alternating with the light solve.

The paper (§5-6) solves the light under a guessed specular model, fits ks and n with the light
fixed, and solves the light again. Here:

* `specular_data` evaluates, once per light, the parts of the forward model (`render`) that do not
  depend on the parameters, over the texels that carry light (a solved light is exactly zero
  almost everywhere a sun dominates, so this is cheap): the diffuse shading D L (kd = 1) and, per
  pixel and lit texel, the factor A and the lobe cosine c of `render.specular_factors`.
* `fit_specular` fits kd (RGB), ks (RGB) and log n by `scipy.optimize.least_squares(method="lm")`
  with an analytic Jacobian:  I_c = kd_c (D L)_c + ks_c norm(n) sum_i A_i c_i^n L_ic; then ks is
  made grey (highlights carry the light's colour) by moving its colour into the light, which is
  what makes kd's colour observable (`SpecularFit`). Starts that LM cannot bring home (n far
  off, a lobe too narrow to see any highlight, a worse local optimum) are caught by a scan over
  n (the best kd, ks >= 0 for each n are a small NNLS) that gives a new start. Uncertainties come
  from the Jacobian (conditional on the light).
* `alternate` runs light -> LM -> light ... until the objective stops improving; `select` decides
  between the Lambertian model and a specular one on held-out pixels (`auto`).

Scale: light x albedo is only known as a product. After every LM fit the material is rescaled so
that the mean of kd equals the mean of the reference kd (the user's --kd, default 1), and the
light takes the inverse factor, leaving every rendered pixel unchanged.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from typing import Callable

import numpy as np
from scipy.optimize import least_squares, nnls

from ..geometry.visibility import VisibilityData, decode
from .materials import PLASTIC, SPECULAR_MODELS, Material
from ..threads import parallel_blocks
from .render import (KERNEL_ROWS, diffuse_transport, lambert_radiance, lambert_weights, linear_diffuse, lobe_norm,
                     specular_factors)

SHININESS_RANGE = (0.5, 20000.0)  # a fitted n outside this is no specular lobe we can resolve
SCAN_SHININESS = tuple(2.0 ** k for k in range(0, 14))  # 1 .. 8192: the restart scan over n
# the LM fits' stopping tolerances (relative): a step that moves the parameters by < 1e-6 or the cost
# by < 1e-8 changes nothing the fits report (the parameters' one-sigma errors are ~1e-3 relative or
# more, and an alternation round stops at a 1e-3 change of the error); tighter ones cost evaluations
# (teapot_sun_phong's plastic rounds: 15-29 evaluations at 1e-10 / 1e-12)
LM_TOLERANCES = {"xtol": 1e-6, "ftol": 1e-8, "gtol": 1e-8}
# auto's probe skips its LM when the scan's best ks is below this many sigma (`fit_specular`'s
# `screen`): LM could not bring it to the 3 sigma a significant term needs
PROBE_SCREEN = 2.0
# `lobe_ratio`: a round's ks / kd_c searched within a factor e^RATIO_SPAN of its own (a first light
# under a probe's material fitted to the Lambertian light can be 4x off in a channel: suzanne's
# blue), to the precision this many golden-section steps reach (0.618^17 of the span: ~0.2 % in t;
# `parts.bounded_search`, Brent's method, gets there in fewer NNLS solves on the round's tree)
RATIO_SPAN = float(np.log(16.0))
RATIO_EVALUATIONS = 17
ROUND_TOL = 1e-3  # alternation stops when a round lowers the relative RMSE by less than this
RHO_FLOOR = 0.8  # `_heads_for`: the remaining decrease taken as at least 4x the last step
HELD_OUT_MARGIN = 0.02  # an alternation's round whose held-out error is this much above the lowest is not kept
BEAT_MARGIN = 0.05  # a trailing auto candidate stops once its error heads for this much above the leader's
# plastic's runner-up distribution is alternated too when its first light's held-out error is within
# this of the best one's: one light solve cannot tell GGX's long tails from Beckmann's (spot_plastic_sun,
# GGX alpha 0.15: 2.268 against Beckmann's 2.250 %; Beckmann alternated alone ends at alpha 0.133, held-out
# 2.05 %, the glossy probe 6.6 %; GGX alternated too wins at alpha 0.147, held-out 1.71 %, glossy probe 1.5 %)
DISTRIBUTION_TIE = 0.05
EARLY_REACH = 2.0  # `_reach`: before `_heads_for` can tell a ratio, each round left may gain this x the last step
MAX_PAIRS = 48_000_000  # (pixel, lit texel) pairs held for the LM (2 float32 arrays: ~400 MB)
LIT_TOL = 0.0  # texels whose light is exactly zero (all channels) add nothing and are skipped
_CHUNK = 4096  # pixel rows per evaluation chunk (keeps temporaries small)
MIN_FIT_PIXELS = 30  # a specular fit has 7 unknowns (kd, ks RGB and n): fewer pixels cannot pin them


class FitError(ValueError):
    """The specular fit found nothing it can report (e.g. no lit texel, no usable pixel)."""


@dataclass
class SpecularData:
    """Everything the LM needs for one light: evaluation without another pass over visibility.

    diffuse : (P, 3) D L, the radiance with kd = 1 and no specular term.
    A, log_c : (P, K) float32 specular factors over the lit texels (log of the lobe cosine;
        pairs with c = 0 have A = 0 and log_c = -80, so c^n underflows to 0 without infinities).
    light : (K, 3) the lit texels' radiance.
    photo : (P, 3); fit : (P,) bool, True for fitted pixels, False for held-out ones.
    rows : (P,) indices of these pixels in the visibility data.
    """

    model: str
    diffuse: np.ndarray
    A: np.ndarray
    log_c: np.ndarray
    light: np.ndarray
    photo: np.ndarray
    fit: np.ndarray
    n_pixels_available: int
    lit_texels: int
    rows: np.ndarray

    def specular(self, shininess: float, derivative: bool = False):
        """(P, 3) sum_i A_i c_i^n L_i norm(n) and, if asked, its derivative with respect to log n."""
        norm, dnorm = lobe_norm(shininess, self.model)
        n32 = np.float32(shininess)
        L = self.light.astype(np.float32)
        EL = np.empty((len(self.A), 3))
        ELc = np.empty((len(self.A), 3)) if derivative else None
        b = KERNEL_ROWS

        def run(starts):  # E = A exp(n log c) in blocks, on scratch that stays in cache
            E = np.empty((b, self.A.shape[1]), np.float32)
            for a in starts:
                sl = slice(a, a + b)
                e = E[: len(self.A[sl])]
                np.multiply(self.log_c[sl], n32, out=e)
                np.exp(e, out=e)
                e *= self.A[sl]
                EL[sl] = e @ L
                if derivative:
                    e *= self.log_c[sl]
                    ELc[sl] = e @ L

        parallel_blocks(run, list(range(0, len(self.A), b)))
        S = norm * EL
        if not derivative:
            return S
        return S, shininess * (dnorm * EL + norm * ELc)

    def predict(self, kd, ks: float, shininess: float) -> np.ndarray:
        return np.asarray(kd)[None, :] * self.diffuse + ks * self.specular(shininess)

    def rmse(self, kd, ks: float, shininess: float, which: str = "fit") -> float | None:
        """Relative RMSE over the fit (or held-out) pixels, all channels."""
        sel = self.fit if which == "fit" else ~self.fit
        if not sel.any():
            return None
        r = self.predict(kd, ks, shininess)[sel] - self.photo[sel]
        return float(np.sqrt((r**2).sum() / max((self.photo[sel] ** 2).sum(), 1e-300)))


def _pixel_subset(candidates: np.ndarray, k: int) -> np.ndarray:
    """Indices of about k of the candidate pixels, evenly spread over their order (deterministic)."""
    idx = np.flatnonzero(candidates)
    if len(idx) <= k:
        return idx
    return idx[np.unique(np.linspace(0, len(idx) - 1, k).round().astype(np.int64))]


def fit_inputs(vis, light, use, held_out, rows, weights, max_pairs: int, cap_given: bool = False):
    """What a specular fit with the light fixed works on (Blinn-Phong's and plastic's): the light
    per channel (N, 3), its lit texels, the pixel count, the used and held-out masks, and the rows
    in increasing order with their weights: the given ones less the unused (with `cap_given`, an
    evenly spread part of them, weights rescaled, when rows x lit texels exceed `max_pairs`), else an evenly spread subset
    of the used pixels. Raises FitError when there is nothing to fit."""
    L = np.asarray(light, dtype=np.float64)
    if L.ndim == 1:
        L = np.repeat(L[:, None], 3, axis=1)
    lit = np.flatnonzero(np.any(np.abs(L) > LIT_TOL, axis=1))
    if len(lit) == 0:
        raise FitError("the light is zero everywhere: there is no highlight to fit")
    P = vis.n_pixels
    use = np.ones(P, bool) if use is None else np.asarray(use, bool)
    held_out = np.zeros(P, bool) if held_out is None else np.asarray(held_out, bool)
    n_fit = int((use & ~held_out).sum())
    if n_fit < MIN_FIT_PIXELS:
        raise FitError(f"{n_fit} pixels are left to fit the reflectance to; a specular term (7 unknowns) needs "
                       f"at least {MIN_FIT_PIXELS}")
    if rows is None:
        rows = _pixel_subset(use, max(1, max_pairs // len(lit)))
        weights = None
    else:
        keep = use[rows]
        rows = np.asarray(rows, np.int64)[keep]
        weights = None if weights is None else np.asarray(weights, np.float64)[keep]
        if cap_given and len(rows) * len(lit) > max_pairs:  # an evenly spread part of the rows' order
            pick = _pixel_subset(np.ones(len(rows), bool), max(1, max_pairs // len(lit)))
            w = None if weights is None else weights * weights.sum() / max(weights[pick].sum(), 1e-300)
            rows, weights = rows[pick], None if w is None else w[pick]
        order = np.argsort(rows)
        rows = rows[order]
        weights = None if weights is None else weights[order]
    return L, lit, P, use, held_out, rows, weights


def specular_data(vis: VisibilityData, photo: np.ndarray, light: np.ndarray, model: str,
                  use: np.ndarray | None = None, held_out: np.ndarray | None = None,
                  max_pairs: int = MAX_PAIRS, rows: np.ndarray | None = None,
                  weights: np.ndarray | None = None, albedo: np.ndarray | None = None,
                  lobe: np.ndarray | None = None) -> SpecularData:
    """Precompute the LM's inputs for a light (N, 3) over the used pixels.

    Only texels with light are kept; if pixels x lit texels exceeds `max_pairs`, an evenly spread
    subset of the pixels is used (reported as n_pixels_available vs len(photo)). `rows` (indices
    of used pixels) fixes the pixels instead, each standing for `weights` pixels: the fit then
    minimises the weighted residual (every term of a row is scaled by sqrt(weight)). `albedo`: (P, 3)
    per-pixel relative albedo (parts, textures): the diffuse shading is albedo x D L, and the fitted
    kd a colour multiplying it. `lobe`: (P,) per-pixel factor on the specular term (each part's
    specular weight, `parts.PixelAlbedo.specular_weight`), None: 1.
    """
    if model not in SPECULAR_MODELS:
        raise ValueError(f"no specular term in model {model!r}; use one of {SPECULAR_MODELS}")
    L, lit, P, use, held_out, rows, weights = fit_inputs(vis, light, use, held_out, rows, weights, max_pairs)
    s = vis.samples
    cube = vis.cube
    diffuse = np.empty((len(rows), 3))
    A = np.empty((len(rows), len(lit)), np.float32)
    log_c = np.empty((len(rows), len(lit)), np.float32)
    lambert_w, linear = lambert_weights(cube, L), linear_diffuse(vis)
    # blocks of stored rows, keeping the selected ones (`rows` is sorted), on both cores
    firsts = np.arange(0, P, _CHUNK)
    bounds = np.searchsorted(rows, np.append(firsts, P))

    def run(todo):
        for b in todo:
            k = slice(int(bounds[b]), int(bounds[b + 1]))
            r = rows[k]
            V = decode(np.asarray(vis.stored[r]), cube.n_texels, vis.encoding)
            if linear:
                diffuse[k] = lambert_radiance(V, s.normal[r], cube, L, lambert_w)
            else:
                diffuse[k] = diffuse_transport(V, s.normal[r], cube).astype(np.float64) @ L
            Ab, c = specular_factors(V[:, lit], s.normal[r], s.view[r], cube, model, lit)
            A[k] = Ab
            with np.errstate(divide="ignore"):
                log_c[k] = np.where(c > 0, np.log(np.maximum(c, 1e-35)), -80.0)

    parallel_blocks(run, [b for b in range(len(firsts)) if bounds[b + 1] > bounds[b]])
    values = np.asarray(photo, np.float64)[rows]
    if albedo is not None:
        diffuse *= np.asarray(albedo, np.float64)[rows]
    if lobe is not None:
        A *= np.asarray(lobe, np.float32)[rows][:, None]
    if weights is not None:
        sw = np.sqrt(weights)
        diffuse *= sw[:, None]
        A *= sw.astype(np.float32)[:, None]
        values = values * sw[:, None]
    return SpecularData(model, diffuse, A, log_c, L[lit], values, ~held_out[rows], int(use.sum()), len(lit), rows)


@dataclass
class SpecularFit:
    """Result of one LM fit with the light fixed.

    The LM fits ks per channel; a specular term is assumed grey (dielectric: highlights have the
    light's colour), so a coloured ks says the light's colour is off by `light_scale` (per channel).
    `material` has that colour moved into the light: ks grey (the mean), kd_c / light_scale_c. It
    renders the same pixels as the fit with the light multiplied by `light_scale`. This jumps the
    colour mode that alternation alone would only creep along (the light re-absorbs kd's colour).
    When ks is not significant the colour cannot be told apart and light_scale is 1.
    """

    material: Material
    light_scale: np.ndarray  # (3,) per-channel light factor that goes with `material`
    ks_rgb: np.ndarray  # (3,) ks as fitted per channel (before the colour transfer)
    sigma: dict  # one-sigma uncertainties {"kd": [3], "ks_rgb": [3], "ks": float, "n": float, "log_n": float}
    fit_rmse: float
    held_out_rmse: float | None
    start: dict
    path: str  # "lm", "scan+lm" or "scan" (how the optimum was reached)
    message: str
    evaluations: int
    seconds: float
    pixels: int
    lit_texels: int

    @property
    def ks_significant(self) -> bool:
        """ks is more than three standard deviations above zero."""
        ks = float(np.mean(self.material.ks))
        return ks > 0 and ks > 3 * self.sigma.get("ks", np.inf)

    def summary(self) -> dict:
        m = self.material
        lobe = {"alpha": m.roughness, "distribution": m.distribution, "ior": m.ior} if m.model == PLASTIC else \
            {"n": m.shininess}
        return {"model": m.model, "kd": list(m.kd), "ks": float(np.mean(m.ks)), **lobe,
                "ks_rgb_fitted": self.ks_rgb.tolist(),
                "light_colour_scale": self.light_scale.tolist(), "sigma": self.sigma,
                "fit_rmse": self.fit_rmse, "held_out_rmse": self.held_out_rmse, "start": self.start,
                "path": self.path, "message": self.message, "evaluations": self.evaluations,
                "seconds": self.seconds, "pixels": self.pixels, "lit_texels": self.lit_texels,
                "ks_significant": self.ks_significant}


def _valid(x: np.ndarray) -> bool:
    n = np.exp(x[6]) if np.isfinite(x[6]) and x[6] < 50 else np.inf
    return bool(np.all(np.isfinite(x)) and np.all(x[:6] >= 0) and SHININESS_RANGE[0] <= n <= SHININESS_RANGE[1])


def _linear_fit(data: SpecularData, shininess: float) -> tuple[np.ndarray, float]:
    """Best kd (3) and ks (3) >= 0 for a fixed n (per channel a 2-column NNLS over the fit pixels)
    and the squared residual."""
    f = data.fit
    S = data.specular(shininess)[f]
    D = data.diffuse[f]
    kd, ks, sq = np.zeros(3), np.zeros(3), 0.0
    for c in range(3):
        design = np.column_stack([D[:, c], S[:, c]])
        scale = np.sqrt((design**2).sum(axis=0))
        scale[scale == 0] = 1.0
        x, rnorm = nnls(design / scale, data.photo[f, c], maxiter=50)
        kd[c], ks[c] = x / scale
        sq += float(rnorm**2)
    return np.concatenate([kd, ks]), sq


def fit_specular(data: SpecularData, start: Material, max_evaluations: int = 200, guard: bool = True,
                 screen: float | None = None) -> SpecularFit:
    """Fit kd (RGB), ks (RGB) and n with the light fixed, by Levenberg-Marquardt in (kd, ks, log n),
    then move ks's colour into the light (see SpecularFit).

    Starts from `start` (its kd, ks and n). With `guard`, a scan over n (kd, ks >= 0 exact for each
    n) guards the start: LM starts from the scan's best when it fits better; if LM leaves the
    feasible region (kd or ks < 0, n outside SHININESS_RANGE, non-finite) or ends worse than the
    scan's best, it restarts there; if that fails too, the scan's best point (feasible by
    construction) is returned with a message saying so. Without `guard` (a start that is already
    an optimum of a nearby problem, e.g. the previous alternation round's) the scan runs only if LM
    leaves the feasible region. Never returns NaNs.

    `screen` (with `guard`; auto's probe, which only asks whether ks is significant): when the scan's
    best ks is below `screen` one-sigma errors (the same Jacobian estimate as at the end), LM is not
    run and the scan's best is returned. LM's optimum lies within half the scan's step of a scan
    point (a factor 2^0.5 in n; cos^n and cos^(1.41 n) lobes correlate at 0.985 over the
    hemisphere), so it could raise ks / sigma by a few per cent, not from below 2 to the 3 that
    `ks_significant` asks. Not when the start fits better than every scan point. On a diffuse scene under a
    sky (spot_overcast) the LM it spares wandered 37 evaluations over an n that ks ~ 0 leaves free.
    """
    t0 = time.perf_counter()
    f = data.fit
    b = data.photo[f]
    scale = float(np.sqrt(np.mean(b**2))) or 1.0
    nfev = 0

    def residual(x):
        nonlocal nfev
        nfev += 1
        n = float(np.exp(np.clip(x[6], -10, 12)))
        r = x[:3][None, :] * data.diffuse[f] + x[3:6][None, :] * data.specular(n)[f] - b
        return (r / scale).T.ravel()

    def jacobian(x):
        n = float(np.exp(np.clip(x[6], -10, 12)))
        S, dS = data.specular(n, derivative=True)
        S, dS = S[f], dS[f]
        m = len(S)
        J = np.zeros((3 * m, 7))
        for c in range(3):
            rows = slice(c * m, (c + 1) * m)
            J[rows, c] = data.diffuse[f, c]
            J[rows, 3 + c] = S[:, c]
            J[rows, 6] = x[3 + c] * dS[:, c]
        return J / scale

    def lm(x0):
        with np.errstate(over="ignore", invalid="ignore", under="ignore"):
            res = least_squares(residual, x0, jac=jacobian, method="lm", x_scale="jac",
                                max_nfev=max_evaluations, **LM_TOLERANCES)
        return res.x

    def covariance(x):
        """One-sigma errors from the Jacobian at x (conditional on the light): (cov, sd, sd of mean ks)."""
        J = jacobian(x)
        r = residual(x)
        dof = max(len(r) - 7, 1)
        cov = (r @ r / dof) * np.linalg.pinv(J.T @ J)
        return cov, np.sqrt(np.maximum(np.diag(cov), 0.0)), float(np.sqrt(max(cov[3:6, 3:6].sum(), 0.0)) / 3)

    screened = None  # the scan's best point's covariance, when the screen stops there
    start_n = float(start.shininess)
    if not start_n > 0:
        raise FitError(f"the start shininess must be > 0, got {start_n}")
    x0 = np.array([*start.kd, *start.ks, np.log(start_n)], float)
    path, message = "lm", "converged from the start"
    if not guard:
        x = lm(x0)
        if not _valid(x):  # the start led out of the feasible region: guard after all
            guard = True
    if guard:
        # n is the one nonlinear parameter: a scan over it (kd, ks >= 0 solved exactly for each n)
        # finds the basin of the global optimum, whatever the start. LM starts from the scan's best
        # when that fits better than the start (a start far off, or a lobe far too narrow that fits
        # a few pixels' noise), and restarts from it if LM from the start leaves the feasible region.
        scan = [(_linear_fit(data, n), n) for n in SCAN_SHININESS]
        (coef, sq_best), n_best = min(scan, key=lambda t: t[0][1])
        xs = np.array([*coef, np.log(n_best)])
        sq_start = float(np.sum(residual(x0) ** 2)) * scale**2 if _valid(x0) else np.inf
        at_scan = covariance(xs) if screen is not None else None
        if not np.any(coef[3:6] > 0) and sq_best <= sq_start:
            x, path = xs, "scan"
            message = "no specular term fits at any n of the scan (ks = 0): the data support no highlight"
        elif at_scan is not None and sq_best <= sq_start and float(np.mean(coef[3:6])) < screen * at_scan[2]:
            x, path, screened = xs, "scan", at_scan
            message = (f"the scan's best (n = {n_best:g}) has ks {float(np.mean(coef[3:6])):.3g} +- {at_scan[2]:.2g}, "
                       f"below {screen:g} sigma: no significant specular term within reach of LM (not run)")
        else:
            from_scan = sq_best < sq_start
            x = lm(xs if from_scan else x0)
            if from_scan:
                path, message = "scan+lm", f"started at the scan's best n = {n_best:g} (it fits better than n = {start_n:g})"
            if not _valid(x) or float(np.sum(residual(x) ** 2)) * scale**2 > sq_best:
                again = lm(xs) if not from_scan else None
                if again is not None and _valid(again):
                    x, path = again, "scan+lm"
                    message = f"LM from the start (n = {start_n:g}) left the feasible region or stopped in a worse " \
                              f"local optimum; restarted at the scan's best n = {n_best:g}"
                else:
                    x, path = xs, "scan"
                    message = f"LM did not improve on the scan's best n = {n_best:g}: kept that (within a factor 2^0.5)"
    n = float(np.exp(x[6]))
    kd, ks_rgb = np.maximum(x[:3], 0.0), np.maximum(x[3:6], 0.0)
    cov, sd, sd_ks_mean = covariance(x) if screened is None else screened
    sigma = {"kd": sd[:3].tolist(), "ks_rgb": sd[3:6].tolist(), "ks": sd_ks_mean, "n": float(n * sd[6]),
             "log_n": float(sd[6])}
    ks = float(ks_rgb.mean())
    light_scale = np.ones(3)
    if ks > 0 and np.all(ks_rgb > 3 * sd[3:6]):
        light_scale = ks_rgb / ks  # grey ks: its colour is the light's
    material = Material(kd=tuple(float(v) for v in kd / light_scale), ks=(ks, ks, ks), shininess=n, model=data.model)
    pred = kd[None, :] * data.diffuse + ks_rgb[None, :] * data.specular(n)

    def rel(sel):
        if not sel.any():
            return None
        return float(np.sqrt(((pred[sel] - data.photo[sel]) ** 2).sum() / max((data.photo[sel] ** 2).sum(), 1e-300)))

    fit_rmse = rel(data.fit)
    return SpecularFit(material, light_scale, ks_rgb, sigma, fit_rmse, rel(~data.fit),
                       {"kd": list(start.kd), "ks": list(start.ks), "n": start_n}, path, message, nfev,
                       time.perf_counter() - t0, len(data.photo), data.lit_texels)


def normalise(material: Material, light: np.ndarray, kd_reference) -> tuple[Material, np.ndarray, float]:
    """Rescale (kd, ks) so that mean(kd) = mean(kd_reference), the light by the inverse factor.

    Returns the material, the light and the factor s (material / s, light * s): renders unchanged.
    """
    ref = float(np.mean(kd_reference))
    mean_kd = float(np.mean(material.kd))
    if ref <= 0 or mean_kd <= 1e-9 * max(ref, float(np.max(material.ks))):
        return material, light, 1.0
    s = mean_kd / ref
    m = replace(material, kd=tuple(k / s for k in material.kd), ks=tuple(k / s for k in material.ks))
    return m, light * s, s


# -- alternation -----------------------------------------------------------------------------
@dataclass
class Round:
    """One light solve under a material (and the LM fit that produced the material, if any)."""

    index: int
    material: Material
    fit_rmse: float  # the light's relative RMSE over all used pixels
    held_out_rmse: float | None  # at the light's chosen level, over the held-out pixels
    light_seconds: float
    fit: SpecularFit | None = None
    # "probe": auto's probe (LM with round 0's light fixed, no light solve): its errors are over the
    # probe's rows, compared with Lambert's over the same rows (`lambert_rmse_same_rows`), not with round 0's
    kind: str = "round"
    lambert_rmse_same_rows: float | None = None
    # kd's colour and ks found with the light re-solved after the round's light (`lobe_ratio`): the
    # ratios ks / kd_c before and after and the drop of the round rows' residual (None: not applied)
    ratio: dict | None = None

    def summary(self) -> dict:
        out = {"round": self.index, "kind": self.kind, "material": self.material.to_json(), "fit_rmse": self.fit_rmse,
               "held_out_rmse": self.held_out_rmse, "light_seconds": self.light_seconds}
        if self.kind == "probe":
            out["lambert_rmse_same_rows"] = self.lambert_rmse_same_rows
            out["note"] = ("the probe: the specular term fitted with round 0's light fixed, scored on the probe's "
                           "rows against Lambert on the same rows (lambert_rmse_same_rows); no light was solved")
        if self.fit is not None:
            out["lm"] = self.fit.summary()
        if self.ratio is not None:
            out["ratio"] = self.ratio
        return out


@dataclass
class Reflectance:
    """The chosen material with its light solution, and how it was reached."""

    material: Material
    solution: object  # light.LightSolution (light scaled to match `material`)
    context: object  # whatever solve_light returned with the solution (e.g. normal equations)
    rounds: list[Round]
    chosen_round: int
    mode: str
    decision: str
    candidates: dict = field(default_factory=dict)
    seconds: float = 0.0

    @property
    def fit(self) -> SpecularFit | None:
        return self.rounds[self.chosen_round].fit

    def summary(self) -> dict:
        m = self.material
        fit = self.fit
        kd_mean = float(np.mean(m.kd))
        lobe = {"alpha": m.roughness, "distribution": m.distribution, "ior": m.ior} if m.model == PLASTIC else \
            {"n": m.shininess}
        out = {"model": m.model, "kd": list(m.kd), "ks": list(m.ks), **lobe,
               "ks_over_kd": (float(np.mean(m.ks)) / kd_mean) if kd_mean > 0 else None,
               "mode": self.mode, "decision": self.decision, "candidates": self.candidates,
               "uncertainty": fit.sigma if fit is not None else None,
               "kd_colour_observable": bool(fit is not None and fit.ks_significant),
               "chosen_round": self.chosen_round, "rounds": [r.summary() for r in self.rounds],
               "seconds": self.seconds}
        if fit is not None:
            out["uncertainty_note"] = ("one sigma from the LM Jacobian with the light fixed (conditional on "
                                       "the light; the light's own uncertainty is not included)")
        return out


SolveLight = Callable[[Material], tuple[object, object]]  # material -> (LightSolution, context)


def _params(m: Material) -> np.ndarray:
    return np.array([*m.kd, float(np.mean(m.ks)), np.log(max(m.lobe_value, 1e-12))])


def lobe_range(model: str) -> tuple[float, float]:
    """The fitted lobe parameter's range: n for the Phong family, alpha for plastic."""
    if model == PLASTIC:
        from .plastic_fit import ALPHA_RANGE

        return ALPHA_RANGE
    return SHININESS_RANGE


def lm_data(vis: VisibilityData, photo: np.ndarray, light: np.ndarray, material: Material, use=None, held_out=None,
            rows=None, weights=None, albedo=None, lobe=None):
    """The LM's inputs for `material`'s model under a light (`specular_data`, or `plastic_fit.plastic_data`)."""
    if material.model == PLASTIC:
        from .plastic_fit import plastic_data

        return plastic_data(vis, photo, light, material, use, held_out, rows=rows, weights=weights, albedo=albedo,
                            lobe=lobe)
    return specular_data(vis, photo, light, material.model, use, held_out, rows=rows, weights=weights, albedo=albedo,
                         lobe=lobe)


def lm_fit(data, start: Material, guard: bool = True, screen: float | None = None) -> "SpecularFit":
    """`fit_specular`, or `plastic_fit.fit_plastic` for plastic's data (which has no `screen`)."""
    if data.model == PLASTIC:
        from .plastic_fit import fit_plastic

        return fit_plastic(data, start, guard=guard)
    return fit_specular(data, start, guard=guard, screen=screen)


def _extrapolate(fitted: list[np.ndarray], material: Material) -> Material:
    """Speed up the alternation's slow, steady drift (the light re-absorbs part of the highlight each
    round, so ks creeps up geometrically): when the last two LM steps point the same way, jump
    towards the limit of the geometric series, theta + d rho / (1 - rho), rho = (d.d') / (d'.d')
    capped at 0.75 (at most 3 steps ahead). The next round's LM starts from the light solved
    under the jump and corrects any overshoot; rounds are judged by their error, so a bad jump
    costs a round, never the result."""
    if len(fitted) < 3:
        return material
    d_prev, d = fitted[-2] - fitted[-3], fitted[-1] - fitted[-2]
    denom = float(d_prev @ d_prev)
    if denom <= 0:
        return material
    rho = float(d @ d_prev) / denom
    if not 0.0 < rho < 1.0:
        return material
    rho = min(rho, 0.75)
    x = fitted[-1] + d * rho / (1.0 - rho)
    lo, hi = lobe_range(material.model)
    if not (np.all(np.isfinite(x)) and np.all(x[:4] >= 0) and lo <= np.exp(min(x[4], 50.0)) <= hi):
        return material
    fitted[-1] = x  # the next step is measured from where the light was solved
    return replace(material, kd=tuple(float(v) for v in x[:3]), ks=(float(x[3]),) * 3).with_lobe(float(np.exp(x[4])))


def lobe_ratio(pieces: dict, material: Material, kd_reference, span: float = RATIO_SPAN,
               evaluations: int = RATIO_EVALUATIONS) -> tuple[Material, dict]:
    """The material's kd colour and ks with its lobe kept, the light re-solved for each (variable
    projection): per channel c only the ratio t_c = ks / kd_c is observable (the light absorbs kd_c),
    and it is found by a bounded search (`parts.bounded_search`) in log t_c within `span` of the
    material's own, each evaluation an NNLS of the leaf-space system `rows.lobe_pieces` gives
    (G(t) = DD + t (X + X') + t^2 SS, h(t) = hD_c + t hS_c). Returns the material with kd_c = ks / t_c,
    ks grey, normalised to mean(kd) = mean(kd_reference), and what was found.

    The alternation's LM fits ks with the light fixed, and the light, fitted to the photo under the
    ks before, holds part of the highlight: ks and kd's colour creep towards their joint optimum
    round after round (teapot_plastic_sun: ks/kd 1.48 -> 2.11 and blue kd 1.04 -> 0.73 over 9
    rounds, the truth 2.22 and 0.67, still moving when the rounds ran out). Here the light follows
    each candidate ratio, so the ratio lands where the joint fit wants it."""
    from ..light.nnls import nnls_gram
    from .parts import bounded_search

    kd = np.asarray(material.kd, np.float64)
    ks = float(np.mean(material.ks))
    C = len(kd)
    if not (ks > 0 and np.all(kd > 0)):  # (no lobe, or a channel without its diffuse part: nothing to trade)
        return material, {"ratio_before": None, "ratio": None, "residual_drop": 0.0}
    G0, X, SS = pieces["DD"], pieces["X"] + pieces["X"].T, pieces["SS"]
    t0 = ks / kd
    t, before, after = t0.copy(), np.zeros(C), np.zeros(C)
    for c in range(C):
        free = [None]

        def f(x, c=c):
            tc = float(np.exp(x))
            r = nnls_gram(G0 + tc * X + tc * tc * SS, pieces["hD"][:, c] + tc * pieces["hS"][:, c],
                          initial_free=free[0])
            free[0] = r.x > 0
            return float(pieces["bb"][c] + 2.0 * r.objective)

        before[c] = f(np.log(t0[c]))
        x = bounded_search(f, float(np.log(t0[c])), span, evaluations)
        t[c], after[c] = np.exp(x), f(x)
    inv = 1.0 / t
    ks_new = float(np.mean(kd_reference)) / float(np.mean(inv))
    m = replace(material, kd=tuple(float(v) for v in ks_new * inv), ks=(ks_new,) * 3)
    info = {"ratio_before": t0.tolist(), "ratio": t.tolist(),
            "residual_drop": float(1.0 - after.sum() / max(before.sum(), 1e-300))}
    return m, info


def alternate(vis: VisibilityData, photo: np.ndarray, start: Material, solve_light: SolveLight,
              use: np.ndarray | None = None, held_out: np.ndarray | None = None, kd_reference=None,
              max_rounds: int = 8, tol: float = ROUND_TOL, progress=None, rows=None, first=None,
              albedo=None, beat: float | None = None, lobe=None, ratio=None) -> Reflectance:
    """Light under `start` (or `first`, its (solution, context) already solved) -> LM -> light -> ...
    until a round lowers the all-pixel RMSE by < tol.

    `ratio(material, solution)`: after each light solve, (material, solution, context, what was
    found) with kd's colour and ks found with the light re-solved for each (`lobe_ratio`), or None
    (nothing better): the round then keeps those.

    The round of the lowest fit error among those whose held-out error is within HELD_OUT_MARGIN of
    the lowest is kept (`_chosen`); the rounds stop on the fit error; at most `max_rounds` LM fits. `rows`: (pixel indices,
    weights) the LM fits, or `rows(light, kd)` giving them for a round's light and diffuse albedo
    (default: an evenly spread subset of the used pixels, `specular_data`). `albedo`: None, or a
    callable giving the current (P, 3) per-pixel relative albedo (the light solve may refit it);
    `lobe` likewise the (P,) per-pixel factor on the specular term (the parts' specular weights).
    `beat`: another candidate's held-out error (`select`): the alternation stops as soon as its own
    held-out error heads for more than BEAT_MARGIN above it (`_heads_for`), as it cannot win.
    """
    t0 = time.perf_counter()
    kd_ref = start.kd if kd_reference is None else kd_reference
    if start.model not in SPECULAR_MODELS:
        raise ValueError(f"alternation needs a specular model, got {start.model!r}")
    ts = time.perf_counter()
    sol, ctx = solve_light(start) if first is None else first  # (`first`: round 0's light, already solved)
    material = start
    better = ratio(material, sol) if ratio is not None else None
    if better is not None:
        material, sol, ctx, found = better
    rounds = [Round(0, material, sol.fit_rmse, sol.held_out_rmse, time.perf_counter() - ts,
                    ratio=None if better is None else found)]
    kept = [(sol, ctx)]
    if progress:
        progress(rounds[0])
    best = lowest = 0  # the chosen round (`_chosen`), the round of the lowest fit error
    fitted: list[np.ndarray] = []  # LM results (kd, ks, log n) of the rounds so far
    for k in range(1, max_rounds + 1):
        chosen = rows(sol.light, material.kd) if callable(rows) else rows
        data = lm_data(vis, photo, sol.light, material, use, held_out, **_rows(chosen), albedo=_now(albedo),
                       lobe=_now(lobe))
        fit = lm_fit(data, material, guard=k == 1)
        data = None  # (the LM's inputs go before the light's system is built: memory)
        material, _, _ = normalise(fit.material, sol.light, kd_ref)
        fitted.append(_params(material))
        fitted_material = material
        material = _extrapolate(fitted, material)
        jumped = material is not fitted_material
        ts = time.perf_counter()
        sol, ctx = solve_light(material)
        better = ratio(material, sol) if ratio is not None else None
        if better is not None:
            material, sol, ctx, found = better
            fitted[-1] = _params(material)  # (the next step is measured from where the light was solved)
        rounds.append(Round(k, material, sol.fit_rmse, sol.held_out_rmse, time.perf_counter() - ts, fit,
                            ratio=None if better is None else found))
        kept.append((sol, ctx))
        if progress:
            progress(rounds[-1])
        previous = rounds[lowest].fit_rmse
        if rounds[k].fit_rmse < previous:
            lowest = k
        best = _chosen(rounds)
        eligible = _eligible(rounds)  # only the lights of rounds that may still be chosen are kept (memory)
        kept = [kk if i in eligible else None for i, kk in enumerate(kept)]
        if previous - rounds[k].fit_rmse < tol * previous and not (
                jumped and rounds[k].fit_rmse > previous * (1.0 + tol)):
            # (a jump that overshot gets one more round, its LM corrects it; not one that landed within
            # tol of the best: spot_plastic_sun's last five rounds were such jumps, alpha 0.1506 ->
            # 0.1501, the error 1.609 -> 1.610 %, each taken for an overshoot until the rounds ran out)
            break
        # (the geometric limit not before round 3: the first rounds' steps tell little of the later
        # ones, which `_extrapolate`'s jumps speed up; before it, the most the rounds left could gain
        # at EARLY_REACH x the last step each)
        limit = how = None
        if beat is not None:
            limit, how = (_heads_for(rounds), "geometric") if k >= 3 else \
                (_reach(rounds, max_rounds - k), f"at most {max_rounds - k} more round(s) of {EARLY_REACH:g}x its last step")
        if limit is not None and limit > beat * (1.0 + BEAT_MARGIN):
            sol, ctx = kept[best]
            return Reflectance(rounds[best].material, sol, ctx, rounds, best, start.model,
                               f"alternation stopped after {k} LM round(s): its held-out error heads for "
                               f"{100 * limit:.3f} % ({how}), above the other candidate's {100 * beat:.3f} %",
                               seconds=time.perf_counter() - t0)
    sol, ctx = kept[best]
    return Reflectance(rounds[best].material, sol, ctx, rounds, best, start.model,
                       f"alternation stopped after {len(rounds) - 1} LM round(s); round {best} has the lowest fit "
                       f"error{' of those within ' + format(100 * HELD_OUT_MARGIN, 'g') + ' % of the lowest held-out error' if rounds[best].held_out_rmse is not None else ''}",
                       seconds=time.perf_counter() - t0)


def _eligible(rounds: list[Round]) -> set[int]:
    """The rounds that may be chosen: those whose held-out error is within HELD_OUT_MARGIN of the
    lowest (every round when nothing is held out)."""
    held = [r.held_out_rmse for r in rounds]
    if any(h is None for h in held):
        return set(range(len(rounds)))
    floor = min(held) * (1.0 + HELD_OUT_MARGIN)
    return {i for i, h in enumerate(held) if h <= floor}


def _chosen(rounds: list[Round]) -> int:
    """The round an alternation keeps: the lowest fit error among the rounds whose held-out error is
    within HELD_OUT_MARGIN of the lowest (`_eligible`).

    Not the fit error alone: an alternation can keep lowering it by a hair while the lobe collapses
    into a needle and the light grows point sources under the highlight, which predicts pixels it
    was not fitted to worse (DiLiGenT 068: Beckmann alpha 0.030 -> 0.005, fit 13.491 -> 13.466 %,
    held-out 5.42 -> 6.15 %). Not the held-out error alone: between rounds that predict the held-out
    pixels alike it is noise, and the later rounds' lower fit error is the better light
    (teapot_sun_phong at R = 16: held-out 13.126 % at round 3, 13.158 % at round 6, the diffuse probe
    2.85 % and 1.57 %)."""
    return min(_eligible(rounds), key=lambda i: (rounds[i].fit_rmse, i))


def _heads_for(rounds) -> float | None:
    """Where the rounds' held-out errors (fit errors without held-out pixels) are heading, at the
    lowest: the lowest so far when the last round did not lower it; else, when the last two steps
    shrink (ratio rho < 0.9), the limit of a geometric series of the last step d, e - d r / (1 - r)
    with r = max(rho, RHO_FLOOR) (one ratio says little: `_extrapolate`'s jumps make a step large
    and the next small, then the steps go on); None while it cannot tell (fewer than three rounds,
    a step that did not shrink)."""
    if len(rounds) < 3:
        return None
    e = [r.held_out_rmse if r.held_out_rmse is not None else r.fit_rmse for r in rounds[-3:]]
    d_prev, d = e[0] - e[1], e[1] - e[2]
    if d <= 0:
        return min(r.held_out_rmse if r.held_out_rmse is not None else r.fit_rmse for r in rounds)
    if d_prev <= 0 or d / d_prev >= 0.9:
        return None
    rho = max(d / d_prev, RHO_FLOOR)
    return e[2] - d * rho / (1.0 - rho)


def _reach(rounds, remaining: int) -> float | None:
    """The lowest error (held-out, else fit) an alternation could still reach if each of its
    `remaining` LM rounds lowered it by EARLY_REACH x its last round's step: a bound for the first
    rounds, before `_heads_for` can measure how the steps shrink (they do as it converges; a jump of
    `_extrapolate` can make one larger, hence the factor); None when the last round did not lower it."""
    if len(rounds) < 2:
        return None
    e = [r.held_out_rmse if r.held_out_rmse is not None else r.fit_rmse for r in rounds[-2:]]
    d = e[0] - e[1]
    if d <= 0:
        return None
    return e[1] - EARLY_REACH * remaining * d


def _now(albedo):
    return albedo() if callable(albedo) else albedo


def _rows(rows) -> dict:
    return {} if rows is None else {"rows": rows[0], "weights": rows[1]}


def fixed(material: Material, solve_light: SolveLight, mode: str, decision: str, progress=None) -> Reflectance:
    """No fit: the light under a material taken as it is (--reflectance given / lambert)."""
    t0 = time.perf_counter()
    sol, ctx = solve_light(material)
    r = Round(0, material, sol.fit_rmse, sol.held_out_rmse, time.perf_counter() - t0)
    if progress:
        progress(r)
    return Reflectance(material, sol, ctx, [r], 0, mode, decision, seconds=time.perf_counter() - t0)


def select(vis: VisibilityData, photo: np.ndarray, start: Material, solve_light: SolveLight,
           use: np.ndarray | None = None, held_out: np.ndarray | None = None, kd_reference=None,
           min_gain: float = 0.05, max_rounds: int = 8, tol: float = ROUND_TOL, progress=None,
           rows=None, probe_rows=None, plastic_starts=(), note=None, albedo=None, per_part=None,
           lobe=None, ratio=None) -> Reflectance:
    """`auto`: the Lambertian model unless a specular one lowers the held-out error by `min_gain`.

    1. Light under Lambert (kd = kd_reference).
    2. A probe: LM with that light fixed, from `start` (on `probe_rows` when given, or
       `probe_rows(light)`: it only has to tell whether a specular term helps). If ks is not
       significant (< 3 sigma), stay Lambertian (no further light solve). If it is but the probe
       lowers the held-out error of the same light by less than `min_gain` (its held-out rows are a
       spread sample that a small highlight can miss), the probe's material gets its own light (the
       first solve of step 3) and stays Lambertian unless that lowers the held-out error by `min_gain`.
    3. Otherwise the lobe: the probe's material gets its own light (one solve); each of
       `plastic_starts` (the microfacet dielectric, e.g. GGX and Beckmann) is fitted on the same
       rows with that light fixed and gets its own light in turn. The best of each family (by
       held-out error under its first light: the probe's Phong lobe, the best plastic) is
       alternated with the light; the lowest held-out error of those is kept if it beats the
       Lambertian light's by `min_gain`.
    `per_part(data, probe)`: with several parts, which of them the lobe belongs on, once the probe
    found one (None: nothing to decide; else ((P,) bool pixels of the glossy parts, what it found)):
    the fits after it use those pixels alone.
    """
    t0 = time.perf_counter()
    kd_ref = start.kd if kd_reference is None else kd_reference
    lambert = Material(kd=tuple(kd_ref))
    ts = time.perf_counter()
    sol0, ctx0 = solve_light(lambert)
    r0 = Round(0, lambert, sol0.fit_rmse, sol0.held_out_rmse, time.perf_counter() - ts)
    if progress:
        progress(r0)
    base = sol0.held_out_rmse if sol0.held_out_rmse is not None else sol0.fit_rmse
    candidates = {"lambert": {"held_out_rmse": sol0.held_out_rmse, "fit_rmse": sol0.fit_rmse}}

    def stay(reason, rounds):
        return Reflectance(lambert, sol0, ctx0, rounds, 0, "auto", reason, candidates, time.perf_counter() - t0)

    try:
        chosen = probe_rows(sol0.light) if callable(probe_rows) else probe_rows
        if chosen is None:
            chosen = rows(sol0.light, start.kd) if callable(rows) else rows
        data = lm_data(vis, photo, sol0.light, start, use, held_out, **_rows(chosen), albedo=_now(albedo),
                       lobe=_now(lobe))
    except FitError as exc:
        return stay(f"lambert: {exc}", [r0])
    probe = lm_fit(data, start, screen=PROBE_SCREEN)

    def fitted_under(material, light):
        """`material`'s LM fit with `light` fixed, on the probe's rows (None if its rows cannot fit it)."""
        try:
            d = lm_data(vis, photo, light, material, use, held_out, **_rows(chosen), albedo=_now(albedo),
                        lobe=_now(lobe))
        except FitError:
            return None
        return lm_fit(d, material)

    which = "held_out" if (~data.fit).any() else "fit"
    plain = data.rmse(lambert.kd, 0.0, 1.0, which) if hasattr(data, "rmse") else _lambert_rmse(data, lambert.kd, which)
    probe_err = probe.held_out_rmse if which == "held_out" else probe.fit_rmse
    gain = 1.0 - probe_err / plain if plain else 0.0
    compared = which.replace("_", "-") + " rows of the probe"
    candidates["probe"] = {**probe.summary(), "gain": gain, "compared_on": compared, "lambert_rmse_same_rows": plain}
    probe_round = Round(1, probe.material, probe.fit_rmse, probe.held_out_rmse, 0.0, probe, "probe", plain)
    passed = probe.ks_significant and gain >= min_gain
    by_plastic = False
    plastic_probes = []  # (name, fit) of the significant plastic probes with the Lambertian light fixed
    if not passed and probe.ks_significant and start.model != PLASTIC and plastic_starts:
        # a Fresnel-weighted lobe can explain a highlight the probe's lobe cannot (it brightens towards
        # grazing views): when the probe finds a significant ks but too small a gain, probe each
        # plastic start with the same light fixed on the same rows before staying Lambertian; one
        # that passes sends the scene on to the lobe's choice below. (No significant ks at all: a
        # diffuse scene, which is spared the plastic probes: ~7 s on bunny_sun.)
        for ps in plastic_starts:
            ps = replace(ps, kd=start.kd)
            name = f"lambert_probe_{ps.model}-{ps.distribution}"
            pp = fitted_under(ps, sol0.light)
            if pp is None:
                continue
            p_err = pp.held_out_rmse if which == "held_out" else pp.fit_rmse
            p_gain = 1.0 - p_err / plain if plain else 0.0
            candidates[name] = {**pp.summary(), "gain": p_gain, "compared_on": compared,
                                "note": f"fitted with the Lambertian light fixed (the {start.model} probe did not pass)"}
            if pp.ks_significant:
                plastic_probes.append((f"{ps.model}-{ps.distribution}", pp))
            if pp.ks_significant and p_gain >= min_gain:
                passed = by_plastic = True
                candidates["probe"]["passed_by"] = name
                if note:
                    note(f"reflectance: the {start.model} probe lowers the error by {100 * gain:.2f} %, a {ps.model} "
                         f"({ps.distribution}) probe by {100 * p_gain:.2f} %: choosing the lobe")
                break
    if not passed and not probe.ks_significant:
        ks, sd = float(np.mean(probe.material.ks)), probe.sigma["ks"]
        nor = " (nor does a plastic one)" if any(k.startswith("lambert_probe_") for k in candidates) else ""
        return stay(f"lambert: a {start.model} term fitted with the Lambertian light fixed is not significant "
                    f"(ks {ks:.3g} +- {sd:.2g}){nor}", [r0, probe_round])
    if per_part is not None:
        decided = per_part(data, probe)
        if decided is not None:
            keep, info = decided
            candidates["parts"] = info
            if not keep.any():
                return stay("lambert: the probe's lobe is significant on no part of its own", [r0, probe_round])
            if chosen is not None:
                chosen = (chosen[0][keep[chosen[0]]], chosen[1][keep[chosen[0]]])
            use = keep if use is None else (np.asarray(use, bool) & keep)
    data = None  # (the probe's inputs are not needed any more: memory)
    # a specular term: which lobe. The probe's material gets its own light (one solve); the microfacet
    # candidates are then fitted with that light fixed (it holds a highlight-free sun, unlike
    # Lambert's, which bends towards the highlights), from the alpha that matches the probe's
    # lobe width (Beckmann ~ Phong: alpha^2 = 2 / (n + 2)), and get their own light in turn; the
    # lowest held-out error of these first lights is alternated
    tried = []

    def first_light(name, material):
        nonlocal ctx0
        ctx0 = None  # (the Lambertian system's transport goes before the lobe's is built: memory; built again if chosen)
        ts = time.perf_counter()
        sol, ctx = solve_light(material)
        e1 = sol.held_out_rmse if sol.held_out_rmse is not None else sol.fit_rmse
        candidates.setdefault(name, {})["first_light_held_out_rmse"] = e1
        tried.append((e1, name, material, (sol, ctx), time.perf_counter() - ts))
        # only each family's best first light may be alternated: the others' systems go now (memory)
        fam = _family(name)
        best = min((t for t in tried if _family(t[1]) == fam), key=lambda t: t[0])
        for i, t in enumerate(tried):
            if _family(t[1]) == fam and t is not best and t[3] is not None:
                tried[i] = t[:3] + (None,) + t[4:]
        return sol

    material, _, _ = normalise(probe.material, sol0.light, kd_ref)
    sol1 = first_light(start.model, material)
    own_plastic = False  # a plastic probe's own light passed: the plastic candidates have their first lights
    if gain < min_gain and not by_plastic:
        # a significant ks that the probe's held-out rows do not reward: those are a spread sample,
        # which a small highlight can all but miss; its own light's held-out error (over all of the
        # light's held-out pixels, as Lambert's) decides
        gain1 = 1.0 - tried[-1][0] / base if base else 0.0
        candidates["probe"]["gain_under_its_own_light"] = gain1
        if gain1 < min_gain:
            # the same for each significant plastic probe: a Lambertian light bent towards a highlight
            # (its fit error far above its held-out one) makes every probe fitted under it look worse
            # than it is, and a needle lobe's own light can lose where a Fresnel-weighted one wins
            # (DiLiGenT 092: probe gains -73 to -81 %, the Phong probe's own light -49 %, a plastic one's
            # own light well ahead of Lambert's)
            # Then each plastic start as it is (not fitted under a bent light: a needle lobe fitted there
            # stays a needle, while the start's own light can place the highlight's source itself)
            own = [(name, f"lambert_probe_{name}", normalise(pp.material, sol0.light, kd_ref)[0])
                   for name, pp in plastic_probes]
            if plastic_probes:  # (a significant plastic probe: some lobe is there to be found)
                own += [(f"{ps.model}-{ps.distribution}", f"start_{ps.model}-{ps.distribution}", replace(ps, kd=start.kd))
                        for ps in plastic_starts]
            for name, label, m in own:
                first_light(name, m)
                g = 1.0 - tried[-1][0] / base if base else 0.0
                candidates.setdefault(label, {"material": m.to_json()})["gain_under_its_own_light"] = g
                if g >= min_gain:
                    by_plastic = own_plastic = True
                    candidates["probe"]["passed_by"] = f"{label} under its own light"
                    if note:
                        note(f"reflectance: the {start.model} probe's own light lowers the held-out error by "
                             f"{100 * gain1:.2f} %, {label.replace('_', ' ')}'s own light by {100 * g:.2f} %: "
                             "choosing the lobe")
                    break
        if gain1 < min_gain and not by_plastic:
            return stay(f"lambert: a {start.model} term fitted with the Lambertian light fixed lowers the "
                        f"{which.replace('_', '-')} error by only {100 * gain:.2f} %, and under its own light the "
                        f"{'held-out' if sol1.held_out_rmse is not None else 'fit'} error by {100 * gain1:.2f} % "
                        f"(< {100 * min_gain:g} %)"
                        + (" (nor does a plastic one)" if any(k.startswith("lambert_probe_") for k in candidates)
                           else ""), [r0, probe_round])
    if start.model != PLASTIC and plastic_starts and not own_plastic:
        alpha0 = float(np.sqrt(2.0 / (max(probe.material.shininess, 0.0) + 2.0)))
        for ps in plastic_starts:
            ps = replace(ps, kd=material.kd, ks=material.ks, roughness=float(np.clip(alpha0, 0.01, 0.7)))
            name = f"{ps.model}-{ps.distribution}"
            pp = fitted_under(ps, sol1.light)
            if pp is None:
                continue
            candidates[f"probe_{name}"] = {**pp.summary(), "compared_on": compared,
                                           "note": f"fitted with the {start.model} probe's light fixed"}
            first_light(name, normalise(pp.material, sol1.light, kd_ref)[0])
    tried.sort(key=lambda t: t[0])
    # the best of each family (the Phong lobes; plastic's distributions) is alternated: one light solve
    # cannot tell them apart (each candidate was fitted to another model's light); plastic's other
    # distribution too when its first light is within DISTRIBUTION_TIE (its system was let go: its
    # alternation solves that light again)
    runs, leaders = [], {}
    for t in tried:
        family = _family(t[1])
        if family not in leaders:
            leaders[family] = t[0]
            runs.append(t)
        elif (family == PLASTIC and t[0] <= leaders[family] * (1.0 + DISTRIBUTION_TIE)
              and all(r[1] != t[1] for r in runs)):
            runs.append(t)
    if note and len(tried) > 1:
        note("reflectance candidates (held-out error under each one's first light): " + ", ".join(
            f"{name} {100 * e1:.3f} %" for e1, name, *_ in tried) + f"; alternating {', '.join(r[1] for r in runs)}")
    tried.clear()  # (the candidates not alternated: their systems are not needed any more: memory)
    t = None
    rounds = [r0]  # then the alternations' rounds (the probes are in candidates)
    results = []
    while runs:
        e1, name, material, first, seconds = runs.pop(0)  # (popped: an alternated run's first system goes)
        offset = len(rounds)
        shifted = (lambda r, o=offset: progress(replace(r, index=r.index + o))) if progress else None
        # a trailing candidate stops once it heads above the best so far (it cannot be chosen)
        beat = min(r[0] for r in results) if results else None
        spec = alternate(vis, photo, material, solve_light, use, held_out, kd_ref, max_rounds, tol, progress=shifted,
                         rows=rows, first=first, albedo=albedo, beat=beat, lobe=lobe, ratio=ratio)
        first = None
        spec.rounds[0].light_seconds = seconds
        best = spec.rounds[spec.chosen_round]
        e = best.held_out_rmse if best.held_out_rmse is not None else best.fit_rmse
        candidates[name].update({"held_out_rmse": best.held_out_rmse, "fit_rmse": best.fit_rmse,
                                 "material": best.material.to_json(), "alternation": spec.decision})
        results.append((e, name, spec, offset))
        rounds += [replace(r, index=r.index + offset) for r in spec.rounds]
        for other in sorted(results, key=lambda t: t[0])[1:]:
            other[2].context = None  # a losing alternation's system (its transport rows: memory)
    e, name, spec, offset = min(results, key=lambda t: t[0])
    gain = 1.0 - e / base if base else 0.0
    others = "; ".join(f"{n} {100 * x:.3f} %" for x, n, *_ in results if n != name)
    versus = f" and beats {others} (held-out {100 * e:.3f} %, each alternated with its light)" if others else ""
    if gain >= min_gain:
        return Reflectance(spec.material, spec.solution, spec.context, rounds, offset + spec.chosen_round, "auto",
                           f"{name}: lowers the held-out error by {100 * gain:.1f} % (>= {100 * min_gain:g} %) over "
                           f"Lambertian{versus}", candidates, time.perf_counter() - t0)
    return stay(f"lambert: a {name} term lowers the held-out error by only {100 * gain:.2f} % "
                f"(< {100 * min_gain:g} %)", rounds)


def _family(name: str) -> str:
    """A candidate's family: the Phong lobes, or plastic's distributions (`select` alternates the
    best first light of each)."""
    return PLASTIC if name.startswith(PLASTIC) else "phong"


def _lambert_rmse(data, kd, which: str) -> float | None:
    """Lambert (no lobe) on a plastic probe's rows: its base without the coating is kd D L."""
    sel = data.fit if which == "fit" else ~data.fit
    if not sel.any():
        return None
    pred = data.lambert[sel] * np.asarray(kd)[None, :]
    r = pred - data.photo[sel]
    return float(np.sqrt((r**2).sum() / max((data.photo[sel] ** 2).sum(), 1e-300)))
