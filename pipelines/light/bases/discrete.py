"""`discrete`: one non-negative value per texel at a chosen face resolution (the paper's failing case;
this one solves 64 x 64 faces, 12 288 unknowns, coarse to fine as a warm start)."""

from __future__ import annotations

import time

import numpy as np

from .. import haar
from ..cubemap import CubeMap
from ..haar import uniform_tree
from ..solution import Level, LightSolution, _rmse, observability, solve_nonnegative
from ..system import LightSystem


def solve_discrete(ne: LightSystem, cube: CubeMap, face_resolution: int | None = None) -> LightSolution:
    """One non-negative value per texel of a cube map of face resolution `face_resolution` (<= R)."""
    t_all = time.perf_counter()
    r = face_resolution or cube.resolution
    tree = uniform_tree(cube, r)
    _, unobservable = observability(ne)
    P = haar.leaf_matrix(tree)  # at r = R a permutation of the texels (leaves are in (level, i, j) order)
    # warm start coarse to fine (face resolution 1, 2, 4, ... r): each level's positive texels seed
    # the next level's free set, so the large, ill-conditioned final NNLS starts near its solution
    guess, coarse = None, 1
    while coarse < r:
        coarse_tree = uniform_tree(cube, coarse)
        Pc = haar.leaf_matrix(coarse_tree)
        xc, _ = solve_nonnegative(ne.fit.project_tree(coarse_tree), None if guess is None else guess(Pc))
        light_c = np.asarray(Pc @ xc)
        guess = (lambda lc: lambda Pn: np.asarray(Pn.T @ lc) > 0)(light_c)
        coarse *= 2
    part = ne.fit.project_tree(tree)
    x, info = solve_nonnegative(part, None if guess is None else guess(P))
    light = np.asarray(P @ x)
    light[unobservable] = 0.0
    rec = Level(0, tree.n_leaves, part.relative_rmse(x), _rmse(ne.held_out, light), 0.0, info, light, x, tree)
    rec.seconds = time.perf_counter() - t_all
    final_light, final_x, final_info = light, x, info
    if ne.held_out.n_pixels > 0:
        # the fit part is projected already: only the held-out rows are added
        final_x, final_info = solve_nonnegative(part.combine(ne.held_out.project_tree(tree)), x > 0)
        final_light = np.asarray(P @ final_x)
        final_light[unobservable] = 0.0
    all_rmse = ne.fit.combine(ne.held_out).relative_rmse(final_light)
    return LightSolution("discrete", final_light, final_x, [rec], 0, all_rmse, final_info,
                         time.perf_counter() - t_all, tree,
                         {"face_resolution": r, "unobservable_texels": int(unobservable.sum())})


def solve(ne: LightSystem, cube: CubeMap, options, progress=None) -> LightSolution:
    return solve_discrete(ne, cube, options.face_resolution)
