"""Non-negative least squares on the normal equations: min_x 1/2 x'Gx - h'x  subject to  x >= 0.

The light solve never builds the tall transport matrix T; it works on G = T'T and h = T'b.
`nnls_gram` is a feasible active-set method in the spirit of Lawson & Hanson, with block steps:
each outer iteration lets the most violating variables (up to half the free set's size) join the
free set, then the inner loop walks from the current feasible point towards the optimum on the
free set, dropping variables as they reach zero, until that optimum is feasible. The objective
never increases; when an iteration makes no progress only one variable enters at a time, which is
classic Lawson-Hanson and terminates. A warm start (the positive set of a coarser level) makes
most solves take a few iterations. Each free block is factored by pivoted Cholesky, and columns
numerically dependent on the others are held at zero (a basic solution): near-duplicate texels
never make a block singular.

It must never fail: columns no pixel constrains are fixed at zero up front; a ridge is used only
if LAPACK cannot factor a block (reported); if the iterations exceed their budget, projected
gradient iterations finish the job. Every solve returns
diagnostics: KKT residual, free/bound counts, ridge, the Cholesky pivot ratio of the free block
(a cheap stand-in for its reciprocal condition number), iterations and time.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
from scipy import linalg
from scipy.linalg import lapack


@dataclass
class NNLSResult:
    """Solution and diagnostics of one `nnls_gram` solve (per right-hand side for `x`)."""

    x: np.ndarray
    kkt_residual: float  # max_i |min(x_i, grad_i)| / max|h|: 0 at an exact KKT point
    n_free: int  # variables strictly positive
    n_bound: int  # variables held at zero
    n_unconstrained: int  # variables fixed at zero because no data constrains them
    ridge: float  # ridge added to the free block (0 if none was needed)
    pivot_ratio: float  # (min / max Cholesky pivot)^2 of the final free block: ~ its reciprocal condition number
    iterations: int
    seconds: float
    fallback: bool = False  # projected gradient had to finish the job
    objective: float = float("nan")  # 1/2 x'Gx - h'x
    notes: list = field(default_factory=list)

    def as_dict(self) -> dict:
        return {k: (v.tolist() if isinstance(v, np.ndarray) else v) for k, v in self.__dict__.items() if k != "x"}


def _block(G: np.ndarray, F: np.ndarray) -> np.ndarray:
    """G[F][:, F] (rows, then columns: 2-4x faster than np.ix_'s one fancy index, the same values)."""
    return G.take(F, axis=0).take(F, axis=1)


def _solve_free(G: np.ndarray, h: np.ndarray, F: np.ndarray, ridge0: float, rank_tol: float = 1e-11):
    """x_F = G_FF^-1 h_F on a linearly independent subset of F.

    A pivoted Cholesky factorisation (LAPACK ?pstrf) finds the columns of the free block that are
    numerically dependent on the others (pivot < rank_tol x the largest diagonal): they are held at
    zero, which loses nothing (the others span them) and keeps every solve well posed, as
    Lawson-Hanson's basic solutions are. Returns (x_F, dropped (bool over F), ridge, pivot ratio).
    A ridge is only used if LAPACK itself fails.
    """
    GFF = _block(G, F)
    n = len(F)
    dropped = np.zeros(n, dtype=bool)
    dmax = float(np.max(np.diag(GFF), initial=0.0))
    if n == 0 or dmax <= 0:
        return np.zeros(n), ~dropped, 0.0, float("nan")
    U, piv, rank, info = lapack.dpstrf(GFF, tol=rank_tol * dmax, lower=0)
    if info >= 0 and rank > 0:
        order = piv[:rank] - 1  # LAPACK pivots are 1-based
        Ur = U[:rank, :rank]  # ?trtrs reads only the upper triangle
        # U'U z = h: two triangular solves (LAPACK's own: scipy's solve_triangular costs ~10 us a call
        # in its checks, and the active set calls this thousands of times on small blocks)
        z, info1 = lapack.dtrtrs(Ur, h[F][order], lower=0, trans=1)
        z, info2 = lapack.dtrtrs(Ur, z, lower=0, trans=0)
        if info1 == 0 and info2 == 0:  # (a zero pivot cannot pass pstrf's tolerance: else the ridge below)
            x = np.zeros(n)
            x[order] = z
            dropped[:] = True
            dropped[order] = False
            d = np.abs(np.diag(Ur))
            return x, dropped, 0.0, float((d.min() / d.max()) ** 2)
    scale = float(np.mean(np.diag(GFF)))
    for ridge in (ridge0, 1e3 * ridge0, 1e6 * ridge0):
        try:
            c = linalg.cho_factor(GFF + ridge * scale * np.eye(n), lower=True, check_finite=False)
        except linalg.LinAlgError:
            continue
        d = np.abs(np.diag(c[0]))
        return linalg.cho_solve(c, h[F], check_finite=False), dropped, ridge * scale, float((d.min() / d.max()) ** 2)
    # pathological: fall back to a least-squares solve of the block
    return np.linalg.lstsq(GFF, h[F], rcond=None)[0], dropped, float("inf"), 0.0


def _objective(G: np.ndarray, h: np.ndarray, x: np.ndarray) -> float:
    """1/2 x'Gx - h'x, touching only the support of x."""
    S = np.flatnonzero(x)
    if len(S) == 0:
        return 0.0
    xs = x[S]
    return float(0.5 * xs @ (_block(G, S) @ xs) - h[S] @ xs)


def _projected_gradient(G, h, x, tol=0.0, iterations=500, window=10):
    """Projected gradient with exact line search along the projected direction (a safe finish).

    Stops at a KKT point to within `tol` (max |min(x_i, grad_i)|, the active-set loop's own
    tolerance), or when `window` iterations together lower the objective by less than 1e-12 of its
    size: what the active-set iterations hand over is usually optimal but for a few variables of a
    nearly singular block, which gradient steps cannot move (the objective stays put to ~11 digits
    over hundreds of iterations: measured on the sample scene's finest levels)."""
    previous = None
    for k in range(iterations):
        g = G @ x - h
        if float(np.abs(np.minimum(x, g)).max(initial=0.0)) <= tol:
            break
        if k % window == 0:
            objective = 0.5 * float(x @ (g - h))  # 1/2 x'Gx - h'x = 1/2 x'(g - h)
            if previous is not None and previous - objective <= 1e-12 * abs(objective):
                break
            previous = objective
        d = -g
        d[(x <= 0) & (d < 0)] = 0.0
        gd = float(d @ G @ d)
        if gd <= 0 or not np.any(d):
            break
        step = float(-(g @ d) / gd)
        x = np.maximum(x + step * d, 0.0)
    return x


def nnls_gram(G: np.ndarray, h: np.ndarray, max_iterations: int | None = None, ridge: float = 1e-10,
              unconstrained_tol: float = 1e-12, initial_free: np.ndarray | None = None,
              max_enter: int | None = None, trace=None) -> NNLSResult:
    """Solve min 1/2 x'Gx - h'x s.t. x >= 0 for one right-hand side.

    Parameters
    ----------
    G : (n, n) symmetric positive semi-definite (float64).
    h : (n,) right-hand side.
    max_iterations : budget of outer iterations (default 5 n + 50) before projected gradient takes over.
    ridge : relative ridge (x mean diagonal), only if LAPACK cannot factor a free block.
    unconstrained_tol : columns with G_ii <= tol * max G_ii are unconstrained by the data and fixed at 0.
    initial_free : (n,) bool, a guess of the positive variables (warm start, e.g. from a coarser level).
    max_enter : at most this many variables join the free set per outer iteration (the most
        violating, by gradient / sqrt(G_ii)); default max(16, half the free count).
    trace : optional callable(iteration, n_free, n_violators, objective), called every outer iteration.

    Returns
    -------
    NNLSResult
    """
    t0 = time.perf_counter()
    G = np.asarray(G, dtype=np.float64)
    h = np.asarray(h, dtype=np.float64).ravel()
    n = len(h)
    if G.shape != (n, n):
        raise ValueError(f"G must have shape ({n}, {n}), got {G.shape}")
    if not (np.all(np.isfinite(h)) and np.isfinite(G).all()):
        raise ValueError("G and h must be finite")
    diag = np.diag(G).copy()
    live = diag > unconstrained_tol * max(float(diag.max(initial=0.0)), 1e-300)
    x = np.zeros(n)
    hscale = max(float(np.abs(h[live]).max(initial=0.0)), 1e-300)
    if not live.any() or hscale <= 1e-300:
        return NNLSResult(x, 0.0, 0, n, int((~live).sum()), 0.0, float("nan"), 0,
                          time.perf_counter() - t0, objective=0.0)
    idx = np.flatnonzero(live)
    Gl = G if len(idx) == n else _block(G, idx)  # no copy of a large G when every column is live
    hl = h[idx]
    m = len(idx)
    tol = 1e-9 * hscale  # a gradient this small is rounding, not a reason to move
    inv_norm = 1.0 / np.sqrt(diag[idx])
    free = np.zeros(m, dtype=bool) if initial_free is None else np.asarray(initial_free, bool)[idx].copy()
    xl = np.zeros(m)
    budget = max_iterations if max_iterations is not None else 5 * m + 50
    ridge_used, iterations, fallback, pivot_ratio = 0.0, 0, False, float("nan")
    # a warm start is pruned first, all negatives at once, until the optimum on it is positive:
    # from there the monotone iterations below start at a feasible point near the solution
    for _ in range(50):
        F = np.flatnonzero(free)
        if len(F) == 0:
            break
        z, dropped, r, pivot_ratio = _solve_free(Gl, hl, F, ridge)
        ridge_used = max(ridge_used, r)
        free[F[dropped | (z <= 0)]] = False
        if not (z[~dropped] <= 0).any():
            xl[F[~dropped]] = z[~dropped]
            break
    else:
        free[:] = False
    stuck = np.zeros(m, dtype=bool)  # entered, but dependent on the free set: skipped until progress
    best = 0.0
    single = False
    while True:
        # inner loop: move from the feasible xl towards the optimum on the free set, dropping
        # variables that hit zero, until that optimum is feasible (Lawson-Hanson's inner loop)
        while True:
            F = np.flatnonzero(free)
            if len(F) == 0:
                xl[:] = 0.0
                break
            z, dropped, r, pivot_ratio = _solve_free(Gl, hl, F, ridge)
            ridge_used = max(ridge_used, r)
            if dropped.any():
                free[F[dropped]] = False
                z, F = z[~dropped], F[~dropped]
            if np.all(z > 0):
                xl[:] = 0.0
                xl[F] = z
                break
            # shortcut: drop every variable the free optimum wants negative at once; accepted only
            # if the optimum on what is left is positive and lowers the objective (monotone still),
            # which saves the one-at-a-time walk of the classic inner loop most of the time
            K = F[z > 0]
            for _ in range(8):  # drop negatives until the optimum on K is positive (usually 2-4 rounds)
                if len(K) == 0:
                    break
                zk, dk, r, piv_k = _solve_free(Gl, hl, K, ridge)
                K, zk = K[~dk], zk[~dk]
                if np.all(zk > 0):
                    break
                K = K[zk > 0]
            if len(K) and np.all(zk > 0) and -0.5 * float(hl[K] @ zk) < _objective(Gl, hl, xl):
                free[:] = False
                free[K] = True
                xl[:] = 0.0
                xl[K] = zk
                pivot_ratio = piv_k
                break
            neg = z <= 0
            step = xl[F][neg] / (xl[F][neg] - z[neg])
            alpha = float(np.min(step))
            xl[F] += alpha * (z - xl[F])
            leaving = F[neg][step <= alpha * (1 + 1e-12)]
            xl[leaving] = 0.0
            free[leaving] = False
            xl[~free] = 0.0
        F = np.flatnonzero(free)
        y = (xl[F] @ Gl[F] if len(F) else np.zeros(m)) - hl
        objective = 0.5 * float(xl[F] @ (y[F] + hl[F])) - float(hl[F] @ xl[F]) if len(F) else 0.0
        if objective < best - 1e-15 * abs(best):
            best, single = objective, False
            stuck[:] = False
        elif iterations > 0:
            single = True  # no progress: enter one variable at a time (Lawson-Hanson, finite)
        violators = ~free & ~stuck & (y < -tol)
        if trace is not None:
            trace(iterations, len(F), int(violators.sum()), objective)
        if not violators.any():
            # ended with variables that want in but were called dependent on the free set (a nearly
            # singular block): not an optimum, so projected gradient finishes from here
            fallback = bool((~free & stuck & (y < -tol)).any())
            break
        if iterations >= budget:
            fallback = True
            break
        iterations += 1
        cand = np.flatnonzero(violators)
        limit = 1 if single else (max_enter if max_enter is not None else max(16, len(F) // 2))
        if len(cand) > limit:
            cand = cand[np.argsort(y[cand] * inv_norm[cand])[:limit]]
        if single:
            stuck[cand] = True  # if it comes back dependent, do not try it again before progress
        free[cand] = True
    xl = np.maximum(xl, 0.0)
    if fallback:
        xl = _projected_gradient(Gl, hl, xl, tol)
    x[idx] = xl
    F = np.flatnonzero(xl > 0)
    grad = (xl[F] @ Gl[F] if len(F) else np.zeros(m)) - hl
    kkt = float(np.abs(np.minimum(xl, grad)).max() / hscale) if m else 0.0
    objective = float(0.5 * xl[F] @ (grad[F] + hl[F]) - hl[F] @ xl[F]) if len(F) else 0.0
    return NNLSResult(x, kkt, len(F), n - len(F), int((~live).sum()), float(ridge_used), pivot_ratio, iterations,
                      time.perf_counter() - t0, fallback, objective)


def nnls_gram_multi(G: np.ndarray, H: np.ndarray, **kwargs) -> tuple[np.ndarray, list[NNLSResult]]:
    """`nnls_gram` for each column of H ((n, C), e.g. RGB sharing one G) -> ((n, C), results)."""
    H = np.asarray(H, dtype=np.float64)
    if H.ndim == 1:
        H = H[:, None]
    results = [nnls_gram(G, H[:, c], **kwargs) for c in range(H.shape[1])]
    return np.column_stack([r.x for r in results]), results
