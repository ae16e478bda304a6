"""`points`: directional lights at texel centres, added one at a time where the fit's gradient is
largest (the paper's first family of methods); the count is chosen on held-out pixels."""

from __future__ import annotations

import time

import numpy as np

from ..cubemap import CubeMap, direction_to_spherical
from ..solution import Level, LightSolution, _rmse, _Stopper, observability, solve_nonnegative
from ..system import LightSystem


def solve_points(ne: LightSystem, cube: CubeMap, max_points: int | str = "auto", limit: int = 64,
                 min_gain: float = 0.01, patience: int = 3) -> LightSolution:
    """Directional lights at texel centres, added one at a time where the fit's gradient is largest.

    max_points : "auto" (stop when the held-out error stops falling) or a fixed count.
    """
    t_all = time.perf_counter()
    fit, held = ne.fit, ne.held_out
    _, unobservable = observability(ne)
    N = cube.n_texels
    diag = fit.diag("mean")
    inv = np.where(~unobservable & (diag > 0), 1.0 / np.sqrt(np.maximum(diag, 1e-300)), 0.0)
    cap = limit if max_points == "auto" else int(max_points)
    support: list[int] = []
    x = np.zeros((N, 3))
    stopper = _Stopper(min_gain, patience)
    records: list[Level] = []
    for index in range(min(cap, N)):
        t0 = time.perf_counter()
        grad = fit.gradient(x, support)
        score = grad.sum(axis=1) * inv
        score[support] = -np.inf
        best = int(np.argmax(score))
        if not score[best] > 0:
            break
        support.append(best)
        sub = np.array(support)
        part = fit.select(sub)
        xs, info = solve_nonnegative(part)
        x[:] = 0.0
        x[sub] = xs
        rec = Level(index, len(support), part.relative_rmse(xs), _rmse(held, x), time.perf_counter() - t0,
                    info, x.copy(), xs.copy())
        records.append(rec)
        score_now = rec.held_out_rmse if rec.held_out_rmse is not None else rec.fit_rmse
        if max_points == "auto" and stopper.update(index, score_now):
            break
        if max_points != "auto":
            stopper.update(index, score_now)
    if not records:  # nothing to explain (black photo)
        zero = np.zeros((N, 3))
        rec = Level(0, 0, 1.0, None, 0.0, {}, zero, np.zeros((0, 3)))
        return LightSolution("points", zero, np.zeros((0, 3)), [rec], 0, 1.0, {}, time.perf_counter() - t_all,
                             details={"points": []})
    chosen = stopper.best_index if max_points == "auto" else len(records) - 1
    sub = np.array(support[:chosen + 1])
    both = fit.combine(held)
    part = both.select(sub)
    xs, info = solve_nonnegative(part)
    # the re-solve on all pixels may switch a light off, or leave it a million times dimmer than
    # the brightest (rounding of a fit that is already exact without it)
    keep = xs.max(axis=1) > 1e-6 * max(float(xs.max(initial=0.0)), 1e-300)
    sub, xs = sub[keep], xs[keep]
    light = np.zeros((N, 3))
    light[sub] = xs
    theta, phi = direction_to_spherical(cube.directions[sub])
    omega = cube.solid_angles[sub]
    points = [{"texel": int(i), "direction": cube.directions[i].tolist(),
               "theta_deg": float(np.degrees(t)), "phi_deg": float(np.degrees(p) % 360.0),
               "irradiance_rgb": (xs[k] * omega[k]).tolist()}
              for k, (i, t, p) in enumerate(zip(sub, theta, phi))]
    return LightSolution("points", light, xs * omega[:, None], records, chosen, both.relative_rmse(light), info,
                         time.perf_counter() - t_all, None,
                         {"points": points, "unobservable_texels": int(unobservable.sum())})


def solve(ne: LightSystem, cube: CubeMap, options, progress=None) -> LightSolution:
    return solve_points(ne, cube, options.levels_value, min_gain=options.min_gain)
