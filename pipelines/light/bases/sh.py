"""`sh`: real spherical harmonics to order l, plain least squares as in the paper (the light may go
negative: reported) or constrained non-negative at every texel."""

from __future__ import annotations

import time

import numpy as np

from ..cubemap import CubeMap, direction_to_spherical
from ..solution import Level, LightSolution, _rmse, observability
from ..system import LightSystem, SystemPart


def real_sh(order: int, directions: np.ndarray) -> np.ndarray:
    """Orthonormal real spherical harmonics Y_lm, l <= order, at unit directions -> (N, (order+1)^2).

    Columns in the order (l, m) = (0,0), (1,-1), (1,0), (1,1), (2,-2), ...; for m > 0
    sqrt(2) (-1)^m Re Y_l^m, for m < 0 sqrt(2) (-1)^m Im Y_l^|m|.
    """
    from scipy import special

    theta, phi = direction_to_spherical(np.asarray(directions, dtype=np.float64))
    cols = []
    for l in range(order + 1):
        for m in range(-l, l + 1):
            y = special.sph_harm_y(l, abs(m), theta, phi)
            if m == 0:
                cols.append(y.real)
            elif m > 0:
                cols.append(np.sqrt(2.0) * (-1) ** m * y.real)
            else:
                cols.append(np.sqrt(2.0) * (-1) ** m * y.imag)
    return np.column_stack(cols)


def solve_sh(ne: LightSystem, cube: CubeMap, order: int = 2, nonnegative: bool = False) -> LightSolution:
    """Spherical-harmonic light: plain least squares (the paper) or non-negative at every texel."""
    t_all = time.perf_counter()
    _, unobservable = observability(ne)
    Y = real_sh(order, cube.directions)
    K = Y.shape[1]

    def fit_part(part: SystemPart):
        proj = part.project(Y)
        c = np.zeros((K, 3))
        notes = {}
        for ch in range(3):
            G, h = proj.gram(ch), proj.h[:, ch]
            scale = max(float(np.abs(np.diag(G)).max(initial=0.0)), 1e-300)
            c[:, ch], _, rank, sv = np.linalg.lstsq(G / scale, h / scale, rcond=1e-12)
            notes["rank"] = int(rank)
            notes["condition"] = float(sv[0] / sv[-1]) if sv[-1] > 0 else float("inf")
            if nonnegative:
                c[:, ch] = _sh_nonnegative(G / scale, h / scale, Y[~unobservable], c[:, ch])
        return c, notes

    t0 = time.perf_counter()
    c, notes = fit_part(ne.fit)
    light = Y @ c
    rec = Level(0, K, ne.fit.relative_rmse(light), _rmse(ne.held_out, light), time.perf_counter() - t0,
                notes, light, c)
    if ne.held_out.n_pixels > 0:
        c, notes = fit_part(ne.fit.combine(ne.held_out))
    raw = Y @ c
    seen = raw[~unobservable]
    peak = max(float(seen.max(initial=0.0)), 1e-300)
    details = {"sh_order": order, "nonnegative": nonnegative,
               "min_radiance": float(seen.min()) if len(seen) else 0.0,
               "min_radiance_relative": float(seen.min() / peak) if len(seen) else 0.0,
               "negative_fraction": float((seen < -1e-9 * peak).mean()) if len(seen) else 0.0,
               "unobservable_texels": int(unobservable.sum())}
    # the light is kept as solved, negative lobes included (the paper's comparison); what clipping
    # it to a physical light would cost is reported (it is usually far worse: the lobes cancel)
    both = ne.fit.combine(ne.held_out)
    all_rmse = both.relative_rmse(raw)
    light = raw.copy()
    light[unobservable] = 0.0
    details["clipped_light_rmse"] = both.relative_rmse(np.maximum(light, 0.0))
    return LightSolution("sh+" if nonnegative else "sh", light, c, [rec], 0, all_rmse, notes,
                         time.perf_counter() - t_all, None, details)


def _sh_nonnegative(G: np.ndarray, h: np.ndarray, Y: np.ndarray, start: np.ndarray) -> np.ndarray:
    """min 1/2 c'Gc - h'c subject to Y c >= 0 (SLSQP from the projected least-squares start)."""
    c0 = start.copy()
    low = float((Y @ c0).min(initial=0.0))
    if low < 0:  # shift the DC term until the start is feasible
        c0[0] -= low / Y[0, 0] * 1.0001
    # SLSQP's ftol is absolute: scale the objective to O(1) (it scales with the photo's brightness^2)
    scale = max(abs(float(h @ start)), float(np.abs(h).max(initial=0.0)) * 1e-12, 1e-300)
    Gs, hs = G / scale, h / scale
    from scipy import optimize

    res = optimize.minimize(lambda c: 0.5 * c @ Gs @ c - hs @ c, c0, jac=lambda c: Gs @ c - hs, method="SLSQP",
                            constraints=[{"type": "ineq", "fun": lambda c: Y @ c, "jac": lambda c: Y}],
                            options={"maxiter": 500, "ftol": 1e-12})
    dc = np.zeros_like(c0)  # the best constant light (feasible, so never beaten by a worse answer)
    dc[0] = max(float(h[0]) / float(G[0, 0]), 0.0) if G[0, 0] > 0 else 0.0
    candidates = [c0, dc, np.zeros_like(c0)]  # all feasible: the shifted start, a constant, no light
    if res.success:  # (SLSQP can fail, e.g. "inequality constraints incompatible", with a wild point)
        c = res.x.copy()
        low = float((Y @ c).min(initial=0.0))
        if low < 0:  # clean up the constraint tolerance
            c[0] -= low / Y[0, 0]
        candidates.insert(0, c)
    return min(candidates, key=lambda c: 0.5 * c @ Gs @ c - hs @ c)


def solve(ne: LightSystem, cube: CubeMap, options, progress=None) -> LightSolution:
    return solve_sh(ne, cube, options.sh_order, options.sh_nonnegative)
