"""Non-negative least squares on the normal equations: min_x 1/2 x'Gx - h'x  subject to  x >= 0.

The light solve never builds the tall transport matrix T; it works on G = T'T and h = T'b.
`nnls_gram` is a block principal pivoting active-set method (Kim & Park, SIAM J. Sci. Comput. 33,
2011): each iteration exchanges every variable that violates the KKT conditions between the free
and the bound set, with the classic backup rule (exchange only the worst one) when the number of
violations stops falling, which guarantees termination. Each iteration solves the free block by a
Cholesky factorisation.

It must never fail: columns no pixel constrains are fixed at zero up front; a free block that is
not numerically positive definite is solved with a small ridge (reported); if the pivoting does
not converge within its budget, projected gradient iterations finish the job. Every solve returns
diagnostics: KKT residual, free/bound counts, ridge, the Cholesky pivot ratio of the free block
(a cheap stand-in for its reciprocal condition number), iterations and time.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
from scipy import linalg


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


def _solve_free(G: np.ndarray, h: np.ndarray, F: np.ndarray, ridge0: float):
    """x_F = (G_FF + ridge I)^-1 h_F, trying ridge = 0 first; returns (x_F, ridge used, pivot ratio)."""
    GFF = G[np.ix_(F, F)]
    scale = float(np.mean(np.diag(GFF))) if len(F) else 1.0
    for ridge in (0.0, ridge0, 1e3 * ridge0, 1e6 * ridge0):
        try:
            c = linalg.cho_factor(GFF + ridge * scale * np.eye(len(F)), lower=True, check_finite=False)
        except linalg.LinAlgError:
            continue
        # Cholesky can "succeed" on a matrix that is singular to working precision; the pivots tell.
        piv = np.abs(np.diag(c[0]))
        if ridge == 0.0 and piv.min() <= 1e-7 * piv.max():
            continue
        return linalg.cho_solve(c, h[F], check_finite=False), ridge * scale, float((piv.min() / piv.max()) ** 2)
    # pathological: fall back to a least-squares solve of the block
    return np.linalg.lstsq(GFF, h[F], rcond=None)[0], float("inf"), 0.0


def _projected_gradient(G, h, x, iterations=500):
    """Projected gradient with exact line search along the projected direction (a safe finish)."""
    for _ in range(iterations):
        g = G @ x - h
        d = -g
        d[(x <= 0) & (d < 0)] = 0.0
        gd = float(d @ G @ d)
        if gd <= 0 or not np.any(d):
            break
        step = float(-(g @ d) / gd)
        x = np.maximum(x + step * d, 0.0)
    return x


def nnls_gram(G: np.ndarray, h: np.ndarray, max_iterations: int | None = None, ridge: float = 1e-10,
              unconstrained_tol: float = 1e-12) -> NNLSResult:
    """Solve min 1/2 x'Gx - h'x s.t. x >= 0 for one right-hand side.

    Parameters
    ----------
    G : (n, n) symmetric positive semi-definite (float64).
    h : (n,) right-hand side.
    max_iterations : pivoting budget (default 5 n + 50) before projected gradient takes over.
    ridge : relative ridge (x mean diagonal) tried when a free block is singular.
    unconstrained_tol : columns with G_ii <= tol * max G_ii are unconstrained by the data and fixed at 0.

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
    if not (np.all(np.isfinite(G)) and np.all(np.isfinite(h))):
        raise ValueError("G and h must be finite")
    diag = np.diag(G).copy()
    live = diag > unconstrained_tol * max(float(diag.max(initial=0.0)), 1e-300)
    x = np.zeros(n)
    hscale = max(float(np.abs(h[live]).max(initial=0.0)), 1e-300)
    if not live.any() or hscale <= 1e-300:
        return NNLSResult(x, 0.0, 0, n - int((~live).sum()), int((~live).sum()), 0.0, float("nan"), 0,
                          time.perf_counter() - t0, objective=0.0)
    idx = np.flatnonzero(live)
    Gl, hl = G[np.ix_(idx, idx)], h[idx]
    m = len(idx)
    tol = 1e-12 * hscale
    free = np.zeros(m, dtype=bool)
    xl = np.zeros(m)
    y = -hl.copy()
    budget = max_iterations if max_iterations is not None else 5 * m + 50
    best_violations, backup = m + 1, 3
    ridge_used, iterations, fallback, pivot_ratio = 0.0, 0, False, float("nan")
    while True:
        bad = (free & (xl < -tol)) | (~free & (y < -tol))
        nbad = int(bad.sum())
        if nbad == 0:
            break
        if iterations >= budget:
            fallback = True
            break
        iterations += 1
        if nbad < best_violations:
            best_violations, backup = nbad, 3
            free ^= bad
        elif backup > 0:
            backup -= 1
            free ^= bad
        else:  # backup rule: exchange only the largest-index violator (finite termination)
            j = np.flatnonzero(bad)[-1]
            free[j] = ~free[j]
        F = np.flatnonzero(free)
        xl = np.zeros(m)
        if len(F):
            xl[F], r, pivot_ratio = _solve_free(Gl, hl, F, ridge)
            ridge_used = max(ridge_used, r)
        y = Gl @ xl - hl
        y[F] = 0.0
    xl = np.maximum(xl, 0.0)
    if fallback:
        xl = _projected_gradient(Gl, hl, xl)
    x[idx] = xl
    grad = Gl @ xl - hl
    kkt = float(np.abs(np.minimum(xl, grad)).max() / hscale) if m else 0.0
    F = np.flatnonzero(xl > 0)
    objective = float(0.5 * xl @ Gl @ xl - hl @ xl)
    return NNLSResult(x, kkt, len(F), n - len(F), int((~live).sum()), float(ridge_used), pivot_ratio, iterations,
                      time.perf_counter() - t0, fallback, objective)


def nnls_gram_multi(G: np.ndarray, H: np.ndarray, **kwargs) -> tuple[np.ndarray, list[NNLSResult]]:
    """`nnls_gram` for each column of H ((n, C), e.g. RGB sharing one G) -> ((n, C), results)."""
    H = np.asarray(H, dtype=np.float64)
    if H.ndim == 1:
        H = H[:, None]
    results = [nnls_gram(G, H[:, c], **kwargs) for c in range(H.shape[1])]
    return np.column_stack([r.x for r in results]), results
