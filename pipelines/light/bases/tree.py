"""`wavelet` (the paper, Fig. 6) and its `quadtree` twin (the paper's §7.2 rival): coarse to fine
on a Haar quadtree per tile.

On a given tree the Haar span equals the piecewise constants on its leaves, and light >= 0 at every
texel equals light >= 0 on every leaf, so each level is an NNLS in leaf values; the wavelet result is
stored as the tree's wavelet coefficients. After each level: nodes whose three wavelets vanish are
pruned (children equal: no detail there; such a node is not subdivided again unless its value is
zero), then leaves with non-zero light are subdivided. The quadtree prunes a node only when its
whole block is zero; on the same tree it reaches exactly the wavelet's objective.
"""

from __future__ import annotations

import time

import numpy as np

from .. import haar
from ..cubemap import CubeMap
from ..haar import HaarTree
from ..rows import all_rows
from ..solution import ZERO_TOL, Level, LightSolution, _rmse, _Stopper, observability, solve_nonnegative
from ..system import LightSystem


def _tile_images(tree: HaarTree, texels: np.ndarray) -> list[np.ndarray]:
    out, a = [], 0
    for s in tree.tile_sizes:
        out.append(texels[a:a + s * s].reshape(s, s))
        a += s * s
    return out


def _block_max(img: np.ndarray, level: int, i: int, j: int) -> float:
    side = img.shape[0] >> level
    return float(img[i * side:(i + 1) * side, j * side:(j + 1) * side].max())


def _refine(tree: HaarTree, light: np.ndarray, coefficients: np.ndarray, basis: str,
            frozen: list[set]) -> HaarTree:
    """Prune (wavelet: vanishing wavelets; quadtree: all-zero blocks), then subdivide lit leaves."""
    level_light = light.max(axis=1)
    tol = ZERO_TOL * max(float(level_light.max(initial=0.0)), 1e-300)
    images = _tile_images(tree, level_light)
    if basis == "wavelet":
        pruned, _ = haar.prune(tree, coefficients, tol)
    else:
        kept = [frozenset(n for n in nodes if _block_max(img, *n) > tol)
                for nodes, img in zip(tree.subdivided, images)]
        pruned = HaarTree(tree.tile_sizes, tuple(kept))
    for t, (before, after) in enumerate(zip(tree.subdivided, pruned.subdivided)):
        for node in before - after:
            if _block_max(images[t], *node) > tol:  # merged for equal, non-zero children: keep merged
                frozen[t].add(node)
    grow = np.zeros(pruned.n_leaves, dtype=bool)
    for k, (t, lv, i, j) in enumerate(pruned.leaves()):
        grow[k] = (pruned.tile_sizes[t] >> lv) > 1 and (lv, i, j) not in frozen[t] and \
            _block_max(images[t], lv, i, j) > tol
    return haar.subdivide(pruned, grow)


def solve_tree(ne: LightSystem, cube: CubeMap, basis: str = "wavelet", levels: int | str = "auto",
               min_gain: float = 0.01, patience: int = 1, progress=None, trees=None,
               all_pixels: bool = True) -> LightSolution:
    """The paper's coarse-to-fine solve (`wavelet`) or its quadtree twin.

    levels : "auto" (refine until the held-out error stops falling by `min_gain` for `patience`
        levels; keep the best) or a number of levels (1 = the 9 tile roots only).
    trees : the levels' trees of an earlier solve, followed instead of refining while they last
        (`replay`); the level is chosen afresh and refinement goes on past the last one if the
        errors ask for it.
    all_pixels : the chosen level re-solved on all pixels (the fit and the held-out ones, the whole
        sample: the final light); without it the light is the chosen level's own, fitted on the
        exploration's rows (an intermediate light: a first light a reflectance round re-solves, a
        Lambertian light a bright-direction cast solves again), and `finish` re-solves it later.
    """
    if basis not in ("wavelet", "quadtree"):
        raise ValueError(f"solve_tree needs basis wavelet or quadtree, got {basis!r}")
    t_all = time.perf_counter()
    fit, held = ne.fit, ne.held_out
    explore = fit if ne.explore is None else ne.explore
    _, unobservable = observability(ne)
    tree = HaarTree.roots(cube.tile_sizes) if not trees else trees[0]
    frozen: list[set] = [set() for _ in cube.tile_sizes]
    stopper = _Stopper(min_gain, patience)
    records: list[Level] = []
    guess = None
    for index in range(64):
        t0 = time.perf_counter()
        P = haar.leaf_matrix(tree)
        part = explore.project_tree(tree)
        x, info = solve_nonnegative(part, guess)
        light = np.asarray(P @ x)
        light[unobservable] = 0.0
        coeffs = haar.leaf_values_to_coefficients(x, tree) if basis == "wavelet" else x
        # the fit error from the rows themselves (the explore system may be accumulated in float32,
        # where L'GL - 2h'L + b'b cancels below ~0.3 %)
        rec = Level(index, tree.n_coefficients, explore.relative_rmse(light), _rmse(held, light),
                    0.0, info, light, coeffs, tree)
        records.append(rec)
        if progress:
            progress(rec)
        score = rec.held_out_rmse if rec.held_out_rmse is not None else rec.fit_rmse
        stop = stopper.update(index, score) if levels == "auto" else index + 1 >= int(levels)
        if stop:
            new_tree = None
        elif trees is not None and index + 1 < len(trees):
            new_tree = trees[index + 1]
        else:
            new_tree = _refine(tree, light, coeffs, basis, frozen)
        rec.seconds = time.perf_counter() - t0
        if stop or new_tree.subdivided == tree.subdivided:
            break
        # warm start: a new leaf is expected positive where its old leaf was
        Pn = haar.leaf_matrix(new_tree)
        guess = (np.asarray(Pn.T @ (P @ x)) > 0)
        tree = new_tree
    chosen = stopper.best_index if levels == "auto" else len(records) - 1
    best = records[chosen]
    both = fit.combine(held)
    sol = LightSolution(basis, best.light, best.coefficients, records, chosen, both.relative_rmse(best.light),
                        best.solver, time.perf_counter() - t_all, best.tree,
                        {"unobservable_texels": int(unobservable.sum()),
                         "all_pixels": held.n_pixels == 0 and ne.explore is None}, unobservable)
    return finish(ne, cube, sol) if all_pixels else sol


def finish(ne: LightSystem, cube: CubeMap, solution: LightSolution) -> LightSolution:
    """The chosen level re-solved on all pixels of `ne` (the fit and held-out ones, the whole
    sample), unless it already is (`solve_tree(all_pixels=...)`): the final light. The levels'
    records and held-out errors stay (they were measured on lights fitted without the held-out
    pixels)."""
    if solution.details.get("all_pixels", True) or solution.tree is None:
        return solution
    t0 = time.perf_counter()
    best = solution.levels[solution.chosen]
    # (sampled rows: projected in float32, half the time of float64, the rows explained as well, the
    # exploration's head taken from its memo; the exact route's dense parts stay as they are)
    both = all_rows(ne.fit, ne.held_out, ne.explore)
    P = haar.leaf_matrix(best.tree)
    x, info = solve_nonnegative(both.project_tree(best.tree), _leaf_guess(best, P))
    light = np.asarray(P @ x)
    if solution.unobservable is not None:
        light[solution.unobservable] = 0.0
    coeffs = haar.leaf_values_to_coefficients(x, best.tree) if solution.basis == "wavelet" else x
    return LightSolution(solution.basis, light, coeffs, solution.levels, solution.chosen, both.relative_rmse(light),
                         info, solution.seconds + time.perf_counter() - t0, best.tree,
                         {**solution.details, "all_pixels": True}, solution.unobservable)


def replay(ne: LightSystem, cube: CubeMap, solution: LightSolution, levels: int | str = "auto",
           min_gain: float = 0.01, progress=None) -> LightSolution:
    """`solution`'s levels solved again on `ne` (the same pixels, a few rows' transport corrected in
    place: `rows.RowsPart.correct`), following its trees: every level's system is then one the
    corrected memo already holds (no pass over the rows), the level is chosen afresh on the new errors
    and refinement continues past the last tree if they ask for it. What `solve_tree` would explore
    from scratch differs only where the few corrected rows would have steered a refinement."""
    return solve_tree(ne, cube, solution.basis, levels, min_gain, progress=progress,
                      trees=[lv.tree for lv in solution.levels])


def _leaf_guess(level: Level, P) -> np.ndarray:
    """Leaves of the tree behind P where the level's light is positive (a warm start)."""
    counts = np.asarray(P.sum(axis=0)).ravel()
    return (np.asarray(P.T @ level.light) / np.maximum(counts, 1)[:, None]) > 0


def solve(ne: LightSystem, cube: CubeMap, options, progress=None, all_pixels: bool = True) -> LightSolution:
    return solve_tree(ne, cube, options.basis, options.levels_value, min_gain=options.min_gain, progress=progress,
                      all_pixels=all_pixels)


def refit(ne: LightSystem, cube: CubeMap, solution: LightSolution, all_pixels: bool = True) -> LightSolution:
    """The solution's tree re-solved on another system (the same pixels with corrected transport,
    or another material), warm-started from its light. As in `solve_tree`, the tree is solved on the
    fit pixels first, so that its held-out error is this system's (what `--reflectance auto` and the
    rounds compare), then on all pixels (`all_pixels`; without it the light stays the fit pixels'
    one: an intermediate light, a reflectance round's, which the next LM fit and the final solve
    replace); the refit level replaces the chosen one in the record."""
    t0 = time.perf_counter()
    # which texels no pixel sees is geometry (the same pixels): the refinement's, when it kept it
    unobservable = solution.unobservable if solution.unobservable is not None else observability(ne)[1]
    tree = solution.tree
    P = haar.leaf_matrix(tree)
    counts = np.asarray(P.sum(axis=0)).ravel()
    guess = (np.asarray(P.T @ solution.light) / np.maximum(counts, 1)[:, None]) > 0
    fit_part = ne.fit.project_tree(tree)
    x, info = solve_nonnegative(fit_part, guess)
    light = np.asarray(P @ x)
    light[unobservable] = 0.0
    coeffs = haar.leaf_values_to_coefficients(x, tree) if solution.basis == "wavelet" else x
    old = solution.levels[solution.chosen]
    rec = Level(old.index, tree.n_coefficients, fit_part.relative_rmse(x), _rmse(ne.held_out, light),
                0.0, info, light, coeffs, tree)
    both = ne.fit.combine(ne.held_out)
    if ne.held_out.n_pixels > 0 and all_pixels:
        x, info = solve_nonnegative(fit_part.combine(ne.held_out.project_tree(tree)), x > 0)
        light = np.asarray(P @ x)
        light[unobservable] = 0.0
        coeffs = haar.leaf_values_to_coefficients(x, tree) if solution.basis == "wavelet" else x
    rec.seconds = time.perf_counter() - t0
    levels = list(solution.levels)
    levels[solution.chosen] = rec
    return LightSolution(solution.basis, light, coeffs, levels, solution.chosen, both.relative_rmse(light),
                         info, solution.seconds + time.perf_counter() - t0, tree,
                         {**solution.details, "unobservable_texels": int(unobservable.sum()), "refit": True,
                          "all_pixels": bool(all_pixels or ne.held_out.n_pixels == 0)},
                         unobservable)
