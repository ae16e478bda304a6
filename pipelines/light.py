"""The light solve: recover texel radiances from the normal equations, in one of five bases.

Every basis is a matrix P (texels x coefficients) and is solved through the same normal equations
(`normal_equations.SystemPart`): the projected system is P'GP, P'h, so no basis ever goes back to
the pixels. The five bases (DESIGN §3):

- ``wavelet`` (the paper, Fig. 6): per tile a Haar quadtree, grown coarse to fine. On a given tree
  the Haar span equals the piecewise constants on its leaves, and light >= 0 at every texel equals
  light >= 0 on every leaf, so each level is an NNLS in leaf values; the result is stored as the
  tree's wavelet coefficients. After each level: nodes whose three wavelets vanish are pruned
  (children equal: no detail there; such a node is not subdivided again unless its value is zero),
  then leaves with non-zero light are subdivided.
- ``quadtree`` (the paper's §7.2 rival): the same refinement with one constant per leaf; a node is
  pruned only when its whole block is zero.
- ``discrete``: one value per texel at a chosen face resolution (the paper's failing case).
- ``sh``: real spherical harmonics to order l, plain least squares (may go negative: reported) or
  constrained non-negative at every texel.
- ``points``: directional lights at texel centres, added greedily (largest gradient of the fit).

Model size: a deterministic part of the pixels is held out (`normal_equations.holdout_mask`);
with ``levels="auto"`` refinement (or adding points) stops when the held-out error stops falling,
the level with the lowest held-out error is kept and re-solved on all pixels.

Unobservable texels (no used pixel's transport reaches them: G_ii = 0) are never given light:
they stay zero in every output and are reported.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
from scipy import optimize, special

from . import haar
from .cubemap import CubeMap, direction_to_spherical
from .haar import HaarTree
from .nnls import NNLSResult, nnls_gram
from .fileio import h5_file
from .normal_equations import NormalEquations, SystemPart
from .threads import blas_threads

BASES = ("wavelet", "quadtree", "discrete", "sh", "points")
ZERO_TOL = 1e-9  # light below this fraction of the brightest leaf counts as zero (refine / prune)
EXACT_FIT = 1e-6  # a relative RMSE this small is an exact fit (rounding): refining stops there
UNOBSERVABLE_TOL = 1e-12  # G_ii below this fraction of max G_ii: no pixel constrains the texel


# -- systems ------------------------------------------------------------------------------------
def combine(a: SystemPart, b: SystemPart) -> SystemPart:
    """The normal equations of the union of two pixel sets."""
    if b.n_pixels == 0:
        return a
    return SystemPart(a.G + b.G, a.h + b.h, a.bb + b.bb, a.n_pixels + b.n_pixels, a.channel_scale)


def project(part: SystemPart, P) -> SystemPart:
    """The system in coefficients c of light = P c: (P'GP, P'h). P dense or sparse (N, k)."""
    def proj(G):
        if sp.issparse(P):
            A = np.asarray((P.T @ G))  # (k, N)
            return np.asarray((P.T @ A.T).T)
        return P.T @ G @ P

    G = np.stack([proj(g) for g in part.G]) if part.G.ndim == 3 else proj(part.G)
    G = 0.5 * (G + np.swapaxes(G, -1, -2))
    h = np.asarray(P.T @ part.h)
    return SystemPart(G, h, part.bb, part.n_pixels, part.channel_scale)


def observability(ne: NormalEquations) -> tuple[np.ndarray, np.ndarray]:
    """Per texel: relative observability sqrt(G_ii) / max (0..1) over all used pixels, and the
    unobservable mask (G_ii <= UNOBSERVABLE_TOL max G_ii: no pixel's transport reaches it)."""
    G = combine(ne.fit, ne.held_out).G
    d = np.diag(G) if G.ndim == 2 else np.einsum("cii->ci", G).max(axis=0)
    d = np.maximum(d, 0.0)
    dmax = float(d.max(initial=0.0))
    if dmax <= 0:
        return np.zeros_like(d), np.ones(len(d), bool)
    return np.sqrt(d / dmax), d <= UNOBSERVABLE_TOL * dmax


LOW_FREQUENCY_SHARE = 0.98  # a clamped cosine keeps ~99 % of its energy in SH l <= 2 (Ramamoorthi & Hanrahan)
POOR_FIT = 0.3  # relative RMSE against the photo above which the fit explains little of it


def low_frequency_share(ne: NormalEquations, cube: CubeMap) -> tuple[float, int]:
    """How much of what the pixels see of the light lies in its 9 lowest spherical harmonics.

    Each pixel's transport row t (per unit texel radiance) is a function t_i / w_i of direction
    (w the texel solid angles); its energy is sum t_i^2 / w_i, so over all pixels tr(W^-1 G).
    Its part in the span of SH l <= 2 (orthonormalised on the cube's directions with weights w) is
    tr(Q'GQ). Returns (that share, 0..1; the rank of Q'GQ, how many of the 9 components the pixels
    determine). A diffuse, shadow-free scene has a share near 1: only those 9 numbers of the light
    are observable (the paper's point: cast shadows carry the rest).
    """
    G = combine(ne.fit, ne.held_out).G
    G = G if G.ndim == 2 else G.mean(axis=0)
    w = cube.solid_angles.astype(np.float64)
    Y = real_sh(2, cube.directions)
    M = Y.T @ (w[:, None] * Y)
    evals, evecs = np.linalg.eigh(M)
    keep = evals > 1e-9 * evals.max()
    Q = Y @ (evecs[:, keep] / np.sqrt(evals[keep]))  # Q' W Q = I
    total = float(np.sum(np.diag(G) / w))
    if total <= 0:
        return 0.0, 0
    low = Q.T @ G @ Q
    lev = np.linalg.eigvalsh((low + low.T) / 2)
    rank = int(np.sum(lev > 1e-8 * max(float(lev.max(initial=0.0)), 1e-300)))
    return float(np.trace(low)) / total, rank


def diagnose(ne: NormalEquations, solution: LightSolution, cube: CubeMap, relit_error: float | None) -> list[str]:
    """Warnings about what the photo can and cannot tell of this light (empty when all is well)."""
    notes = []
    pixels = ne.fit.n_pixels + ne.held_out.n_pixels
    if pixels < solution.n_coefficients:
        notes.append(f"{pixels} pixels for {solution.n_coefficients} light coefficients: the light is "
                     "underdetermined; it is one of many that fit these pixels equally well")
    share, rank = low_frequency_share(ne, cube)
    if rank < 9:
        notes.append(f"the pixels determine only {rank} of the 9 lowest-frequency components of the light "
                     "(too few distinct surface normals, e.g. a single plane): only relighting of surfaces "
                     "like these is reliable")
    elif share >= LOW_FREQUENCY_SHARE:
        notes.append(f"{100 * share:.1f} % of what the pixels see of the light is its 9 lowest-frequency "
                     "components (few cast shadows): only a blurred light is observable, and detail finer than "
                     "that in the result is not supported by the photo")
    if not np.any(solution.light > 0):
        notes.append("the recovered light is zero: the used pixels are dark, or lit only from directions they "
                     "cannot see")
    elif relit_error is not None and relit_error > POOR_FIT:
        notes.append(f"the fit explains little of the photo (relative error {100 * relit_error:.0f} %): the photo "
                     "may be mostly noise, or the mesh, pose, camera or material may not match it (see residual.png)")
    return notes


# -- records ------------------------------------------------------------------------------------
@dataclass
class Level:
    """One solve of a sequence (a refinement level, a point count, or the single solve)."""

    index: int
    n_coefficients: int
    fit_rmse: float  # relative RMSE over the fit pixels
    held_out_rmse: float | None  # relative RMSE over the held-out pixels (None: none held out)
    seconds: float
    solver: dict
    light: np.ndarray  # (N, 3) texel radiance
    coefficients: np.ndarray  # (k, 3)
    tree: HaarTree | None = None

    def summary(self) -> dict:
        out = {"level": self.index, "coefficients": self.n_coefficients, "fit_rmse": self.fit_rmse,
               "held_out_rmse": self.held_out_rmse, "seconds": self.seconds, "solver": self.solver}
        if self.tree is not None:
            out["leaves"] = self.tree.n_leaves
            out["max_depth"] = int(haar.tree_depth_image(self.tree).max())
        return out


@dataclass
class LightSolution:
    basis: str
    light: np.ndarray  # (N, 3) final texel radiance (unobservable texels zero)
    coefficients: np.ndarray  # (k, 3) in the basis' own terms (wavelet coefficients, leaf values, ...)
    levels: list[Level]
    chosen: int  # index of the level kept
    fit_rmse: float  # relative RMSE of the final light over all used pixels (fit + held out)
    solver: dict  # diagnostics of the final solve
    seconds: float
    tree: HaarTree | None = None
    details: dict = field(default_factory=dict)

    @property
    def n_coefficients(self) -> int:
        return int(self.coefficients.shape[0])

    @property
    def held_out_rmse(self) -> float | None:
        return self.levels[self.chosen].held_out_rmse

    def summary(self) -> dict:
        return {"basis": self.basis, "coefficients": self.n_coefficients, "chosen_level": self.chosen,
                "fit_rmse_all_pixels": self.fit_rmse, "held_out_rmse": self.held_out_rmse,
                "seconds": self.seconds, "solver": self.solver, "levels": [lv.summary() for lv in self.levels],
                **self.details}


def _solver_summary(results: list[NNLSResult]) -> dict:
    return {"kkt_residual": max(r.kkt_residual for r in results),
            "n_free": [r.n_free for r in results], "n_bound": [r.n_bound for r in results],
            "n_unconstrained": results[0].n_unconstrained,
            "ridge": max(r.ridge for r in results),
            "pivot_ratio": min((r.pivot_ratio for r in results if np.isfinite(r.pivot_ratio)), default=float("nan")),
            "iterations": sum(r.iterations for r in results),
            "fallback": any(r.fallback for r in results),
            "seconds": sum(r.seconds for r in results)}


def solve_nonnegative(part: SystemPart, initial_free: np.ndarray | None = None) -> tuple[np.ndarray, dict]:
    """NNLS per colour channel on a projected system -> ((k, C) coefficients, solver summary)."""
    C = part.h.shape[1]
    x = np.zeros((part.h.shape[0], C))
    results = []
    # without a per-channel guess, each channel after the brightest starts from the positive set of
    # the one before (the colour channels of one light share most of their support)
    order = np.argsort(-np.abs(part.h).sum(axis=0))
    previous = None
    with blas_threads(1):  # many small factorisations: threads cost more than they give (threads.py)
        for c in order:
            if initial_free is not None and initial_free.ndim == 2:
                guess = initial_free[:, c]
            elif previous is not None:
                guess = previous
            else:
                guess = initial_free
            r = nnls_gram(part.gram(c), part.h[:, c], initial_free=guess)
            x[:, c] = r.x
            previous = r.x > 0
            results.append(r)
    return x, _solver_summary(results)


def _rmse(part: SystemPart, light: np.ndarray) -> float | None:
    return part.relative_rmse(light) if part.n_pixels > 0 else None


class _Stopper:
    """Keeps the last step that improved the score by at least `min_gain` (relative); says stop
    after `patience` further steps that did not."""

    def __init__(self, min_gain: float, patience: int):
        self.min_gain, self.patience = min_gain, patience
        self.best, self.best_index, self.stall = np.inf, -1, 0

    def update(self, index: int, score: float) -> bool:
        if self.best <= EXACT_FIT:  # nothing left to explain: further steps only fit rounding
            self.stall += 1
        elif score < self.best * (1.0 - self.min_gain) or self.best_index < 0:
            self.best, self.best_index, self.stall = score, index, 0
            if score <= EXACT_FIT:
                self.stall = self.patience  # stop here
        else:  # a step that gains less than min_gain does not earn its extra coefficients
            self.stall += 1
        return self.stall >= self.patience


# -- trees --------------------------------------------------------------------------------------
def uniform_tree(cube: CubeMap, face_resolution: int) -> HaarTree:
    """Tree whose leaves are the texels of a cube map of face resolution `face_resolution` (<= R)."""
    R = cube.resolution
    if face_resolution < 1 or face_resolution > R or face_resolution & (face_resolution - 1):
        raise ValueError(f"face resolution must be a power of two from 1 to {R}, got {face_resolution}")
    shrink = int(np.log2(R // face_resolution))
    nodes = []
    for size in cube.tile_sizes:
        depth = max(int(np.log2(size)) - shrink, 0)
        nodes.append([(lv, i, j) for lv in range(depth) for i in range(1 << lv) for j in range(1 << lv)])
    return HaarTree(cube.tile_sizes, tuple(frozenset(n) for n in nodes))


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


def solve_tree(ne: NormalEquations, cube: CubeMap, basis: str = "wavelet", levels: int | str = "auto",
               min_gain: float = 0.01, patience: int = 1, progress=None) -> LightSolution:
    """The paper's coarse-to-fine solve (`wavelet`) or its quadtree twin.

    levels : "auto" (refine until the held-out error stops falling by `min_gain` for `patience`
        levels; keep the best) or a number of levels (1 = the 9 tile roots only).
    """
    if basis not in ("wavelet", "quadtree"):
        raise ValueError(f"solve_tree needs basis wavelet or quadtree, got {basis!r}")
    t_all = time.perf_counter()
    fit, held = ne.fit, ne.held_out
    _, unobservable = observability(ne)
    tree = HaarTree.roots(cube.tile_sizes)
    frozen: list[set] = [set() for _ in cube.tile_sizes]
    stopper = _Stopper(min_gain, patience)
    records: list[Level] = []
    guess = None
    for index in range(64):
        t0 = time.perf_counter()
        P = haar.leaf_matrix(tree)
        part = project(fit, P)
        x, info = solve_nonnegative(part, guess)
        light = np.asarray(P @ x)
        light[unobservable] = 0.0
        coeffs = haar.leaf_values_to_coefficients(x, tree) if basis == "wavelet" else x
        rec = Level(index, tree.n_coefficients, part.relative_rmse(x), _rmse(held, light),
                    0.0, info, light, coeffs, tree)
        records.append(rec)
        if progress:
            progress(rec)
        score = rec.held_out_rmse if rec.held_out_rmse is not None else rec.fit_rmse
        stop = stopper.update(index, score) if levels == "auto" else index + 1 >= int(levels)
        new_tree = None if stop else _refine(tree, light, coeffs, basis, frozen)
        rec.seconds = time.perf_counter() - t0
        if stop or new_tree.subdivided == tree.subdivided:
            break
        # warm start: a new leaf is expected positive where its old leaf was
        Pn = haar.leaf_matrix(new_tree)
        guess = (np.asarray(Pn.T @ (P @ x)) > 0)
        tree = new_tree
    chosen = stopper.best_index if levels == "auto" else len(records) - 1
    best = records[chosen]
    light, coeffs, info = best.light, best.coefficients, best.solver
    both = combine(fit, held)
    if held.n_pixels > 0:  # re-solve the chosen tree on all pixels
        P = haar.leaf_matrix(best.tree)
        x, info = solve_nonnegative(project(both, P), _leaf_guess(best, P))
        light = np.asarray(P @ x)
        light[unobservable] = 0.0
        coeffs = haar.leaf_values_to_coefficients(x, best.tree) if basis == "wavelet" else x
    all_rmse = both.relative_rmse(light)
    return LightSolution(basis, light, coeffs, records, chosen, all_rmse, info, time.perf_counter() - t_all,
                         best.tree, {"unobservable_texels": int(unobservable.sum())})


def _leaf_guess(level: Level, P) -> np.ndarray:
    """Leaves of the tree behind P where the level's light is positive (a warm start)."""
    counts = np.asarray(P.sum(axis=0)).ravel()
    return (np.asarray(P.T @ level.light) / np.maximum(counts, 1)[:, None]) > 0


# -- discrete ----------------------------------------------------------------------------------
def solve_discrete(ne: NormalEquations, cube: CubeMap, face_resolution: int | None = None) -> LightSolution:
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
        Pc = haar.leaf_matrix(uniform_tree(cube, coarse))
        xc, _ = solve_nonnegative(project(ne.fit, Pc), None if guess is None else guess(Pc))
        light_c = np.asarray(Pc @ xc)
        guess = (lambda lc: lambda Pn: np.asarray(Pn.T @ lc) > 0)(light_c)
        coarse *= 2
    part = project(ne.fit, P)
    x, info = solve_nonnegative(part, None if guess is None else guess(P))
    light = np.asarray(P @ x)
    light[unobservable] = 0.0
    rec = Level(0, tree.n_leaves, part.relative_rmse(x), _rmse(ne.held_out, light), 0.0, info, light, x, tree)
    rec.seconds = time.perf_counter() - t_all
    final_light, final_x, final_info = light, x, info
    if ne.held_out.n_pixels > 0:
        final_x, final_info = solve_nonnegative(project(combine(ne.fit, ne.held_out), P), x > 0)
        final_light = np.asarray(P @ final_x)
        final_light[unobservable] = 0.0
    all_rmse = combine(ne.fit, ne.held_out).relative_rmse(final_light)
    return LightSolution("discrete", final_light, final_x, [rec], 0, all_rmse, final_info,
                         time.perf_counter() - t_all, tree,
                         {"face_resolution": r, "unobservable_texels": int(unobservable.sum())})


# -- spherical harmonics -----------------------------------------------------------------------
def real_sh(order: int, directions: np.ndarray) -> np.ndarray:
    """Orthonormal real spherical harmonics Y_lm, l <= order, at unit directions -> (N, (order+1)^2).

    Columns in the order (l, m) = (0,0), (1,-1), (1,0), (1,1), (2,-2), ...; for m > 0
    sqrt(2) (-1)^m Re Y_l^m, for m < 0 sqrt(2) (-1)^m Im Y_l^|m|.
    """
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


def solve_sh(ne: NormalEquations, cube: CubeMap, order: int = 2, nonnegative: bool = False) -> LightSolution:
    """Spherical-harmonic light: plain least squares (the paper) or non-negative at every texel."""
    t_all = time.perf_counter()
    _, unobservable = observability(ne)
    Y = real_sh(order, cube.directions)
    K = Y.shape[1]

    def fit_part(part: SystemPart):
        proj = project(part, Y)
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
        c, notes = fit_part(combine(ne.fit, ne.held_out))
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
    both = combine(ne.fit, ne.held_out)
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


# -- points ------------------------------------------------------------------------------------
def solve_points(ne: NormalEquations, cube: CubeMap, max_points: int | str = "auto", limit: int = 64,
                 min_gain: float = 0.01, patience: int = 3) -> LightSolution:
    """Directional lights at texel centres, added one at a time where the fit's gradient is largest.

    max_points : "auto" (stop when the held-out error stops falling) or a fixed count.
    """
    t_all = time.perf_counter()
    fit, held = ne.fit, ne.held_out
    _, unobservable = observability(ne)
    N = cube.n_texels
    Gs = [fit.gram(c) for c in range(3)] if fit.G.ndim == 3 else None
    G0 = fit.gram(0) if Gs is None else None
    diag = np.diag(fit.G if fit.G.ndim == 2 else fit.G.mean(axis=0))
    inv = np.where(~unobservable & (diag > 0), 1.0 / np.sqrt(np.maximum(diag, 1e-300)), 0.0)
    cap = limit if max_points == "auto" else int(max_points)
    support: list[int] = []
    x = np.zeros((N, 3))
    stopper = _Stopper(min_gain, patience)
    records: list[Level] = []
    for index in range(min(cap, N)):
        t0 = time.perf_counter()
        grad = np.empty((N, 3))
        for c in range(3):
            Gc = Gs[c] if Gs is not None else fit.gram(c) if fit.channel_scale is not None else G0
            grad[:, c] = fit.h[:, c] - Gc[:, support] @ x[support, c] if support else fit.h[:, c]
        score = grad.sum(axis=1) * inv
        score[support] = -np.inf
        best = int(np.argmax(score))
        if not score[best] > 0:
            break
        support.append(best)
        sub = np.array(support)
        part = SystemPart(fit.G[np.ix_(sub, sub)] if fit.G.ndim == 2 else fit.G[:, sub][:, :, sub],
                          fit.h[sub], fit.bb, fit.n_pixels, fit.channel_scale)
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
    both = combine(fit, held)
    part = SystemPart(both.G[np.ix_(sub, sub)] if both.G.ndim == 2 else both.G[:, sub][:, :, sub],
                      both.h[sub], both.bb, both.n_pixels, both.channel_scale)
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


# -- dispatch ----------------------------------------------------------------------------------
def solve(ne: NormalEquations, cube: CubeMap, basis: str = "wavelet", levels: int | str = "auto",
          face_resolution: int | None = None, sh_order: int = 2, sh_nonnegative: bool = False,
          min_gain: float = 0.01, progress=None) -> LightSolution:
    """Solve the light in one basis (see the module docstring)."""
    if basis in ("wavelet", "quadtree"):
        return solve_tree(ne, cube, basis, levels, min_gain=min_gain, progress=progress)
    if basis == "discrete":
        return solve_discrete(ne, cube, face_resolution)
    if basis == "sh":
        return solve_sh(ne, cube, sh_order, sh_nonnegative)
    if basis == "points":
        return solve_points(ne, cube, levels, min_gain=min_gain)
    raise ValueError(f"unknown basis {basis!r}; use one of {', '.join(BASES)}")


# -- storage -----------------------------------------------------------------------------------
SOLUTION_FORMAT = "wavelight-light-1"
_KIND_CODES = {"scaling": 0, "h": 1, "v": 2, "d": 3}


def _tree_nodes(tree: HaarTree) -> np.ndarray:
    rows = [(t, *n) for t, nodes in enumerate(tree.subdivided) for n in sorted(nodes)]
    return np.array(rows, dtype=np.int32).reshape(-1, 4)


def _write_tree(group, tree: HaarTree) -> None:
    group.create_dataset("tile_sizes", data=np.array(tree.tile_sizes, dtype=np.int32))
    group.create_dataset("subdivided", data=_tree_nodes(tree))
    index = tree.coefficient_index()
    group.create_dataset("coefficient_index", data=np.array(
        [(t, _KIND_CODES[k], lv, i, j) for t, k, lv, i, j in index], dtype=np.int32).reshape(-1, 5))
    group.create_dataset("leaves", data=np.array(tree.leaves(), dtype=np.int32).reshape(-1, 4))


def read_tree(group) -> HaarTree:
    sizes = [int(s) for s in group["tile_sizes"][:]]
    nodes: list[set] = [set() for _ in sizes]
    for t, lv, i, j in group["subdivided"][:]:
        nodes[int(t)].add((int(lv), int(i), int(j)))
    return HaarTree(tuple(sizes), tuple(frozenset(n) for n in nodes))


def write_solution(path, solution: LightSolution, cube: CubeMap, unobservable: np.ndarray,
                   attrs: dict | None = None) -> None:
    """The solved light as HDF5: texels, coefficients (with the tree), every level, the mask.

    Layout: attrs format/basis/resolution/hemisphere; `light` (N, 3) texel radiance (the output
    light, unobservable texels zero); `coefficients` (k, 3) in the basis' terms (wavelet: Haar
    coefficients of `tree`, orthonormal in the texel inner product, rows in `tree/coefficient_index`
    order (tile, kind 0=scaling 1=h 2=v 3=d, level, i, j); quadtree/discrete: leaf values in
    `tree/leaves` order; sh: real SH coefficients; points: irradiance per light; they describe the
    light before unobservable texels are zeroed, `light` after); `unobservable`
    (N,) bool; `levels/NN/` the same per refinement level, with its errors as attributes.
    """
    with h5_file(path) as f:
        f.attrs.update({"format": SOLUTION_FORMAT, "basis": solution.basis, "resolution": cube.resolution,
                        "hemisphere": cube.hemisphere, "chosen_level": solution.chosen,
                        "units": "linear radiance per texel (light x albedo when kd = 1)"})
        for k, v in (attrs or {}).items():
            f.attrs[k] = v
        f.create_dataset("light", data=solution.light.astype(np.float32))
        f.create_dataset("coefficients", data=solution.coefficients)
        f.create_dataset("unobservable", data=np.asarray(unobservable, bool))
        f.create_dataset("texel_directions", data=cube.directions.astype(np.float32))
        f.create_dataset("texel_solid_angles", data=cube.solid_angles)
        if solution.tree is not None:
            _write_tree(f.create_group("tree"), solution.tree)
        if "points" in solution.details:
            pts = solution.details["points"]
            f.create_dataset("points/direction", data=np.array([p["direction"] for p in pts]).reshape(-1, 3))
            f.create_dataset("points/irradiance", data=np.array([p["irradiance_rgb"] for p in pts]).reshape(-1, 3))
        for lv in solution.levels:
            g = f.create_group(f"levels/{lv.index:02d}")
            g.attrs["fit_rmse"] = lv.fit_rmse
            g.attrs["held_out_rmse"] = np.nan if lv.held_out_rmse is None else lv.held_out_rmse
            g.attrs["seconds"] = lv.seconds
            g.create_dataset("coefficients", data=lv.coefficients)
            if lv.tree is not None:
                _write_tree(g.create_group("tree"), lv.tree)


def read_solution_light(path) -> tuple[np.ndarray, CubeMap, dict]:
    """(N, 3) texel light, its cube map and the file's attributes, from `write_solution`'s file."""
    import h5py

    with h5py.File(path, "r") as f:
        if f.attrs.get("format") != SOLUTION_FORMAT:
            raise ValueError(f"not a {SOLUTION_FORMAT} file")
        cube = CubeMap(int(f.attrs["resolution"]), bool(f.attrs["hemisphere"]))
        return f["light"][:].astype(np.float64), cube, dict(f.attrs)
