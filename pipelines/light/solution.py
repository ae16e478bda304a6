"""The light solve's shared parts: the projected systems, solution records, the NNLS per colour
channel, the stopping rule of refinement, observability and what the photo cannot tell.

Every basis (`pipelines.light.bases`) is a matrix P (texels x coefficients) solved through the same
normal equations (`pipelines.light.system.SystemPart`): the projected system is P'GP, P'h, so no
basis ever goes back to the pixels.

Model size: a deterministic part of the pixels is held out (`system.holdout_mask`); with
``levels="auto"`` refinement (or adding points) stops when the held-out error stops falling, the
level with the lowest held-out error is kept and re-solved on all pixels.

Unobservable texels (no used pixel's transport reaches them: G_ii = 0) are never given light:
they stay zero in every output and are reported.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..threads import blas_threads
from . import haar
from .cubemap import CubeMap
from .haar import HaarTree
from .nnls import NNLSResult, nnls_gram
from .system import LightSystem, SystemPart

ZERO_TOL = 1e-9  # light below this fraction of the brightest leaf counts as zero (refine / prune)
EXACT_FIT = 1e-6  # a relative RMSE this small is an exact fit (rounding): refining stops there
UNOBSERVABLE_TOL = 1e-12  # G_ii below this fraction of max G_ii: no pixel constrains the texel


# -- systems ------------------------------------------------------------------------------------
def observability(ne: LightSystem) -> tuple[np.ndarray, np.ndarray]:
    """Per texel: relative observability sqrt(G_ii) / max (0..1) over all used pixels, and the
    unobservable mask (G_ii <= UNOBSERVABLE_TOL max G_ii: no pixel's transport reaches it)."""
    d = np.maximum(ne.fit.combine(ne.held_out).diag(), 0.0)
    dmax = float(d.max(initial=0.0))
    if dmax <= 0:
        return np.zeros_like(d), np.ones(len(d), bool)
    return np.sqrt(d / dmax), d <= UNOBSERVABLE_TOL * dmax


LOW_FREQUENCY_SHARE = 0.98  # a clamped cosine keeps ~99 % of its energy in SH l <= 2 (Ramamoorthi & Hanrahan)
POOR_FIT = 0.3  # relative RMSE against the photo above which the fit explains little of it


def low_frequency_share(ne: LightSystem, cube: CubeMap) -> tuple[float, int]:
    """How much of what the pixels see of the light lies in its 9 lowest spherical harmonics.

    Each pixel's transport row t (per unit texel radiance) is a function t_i / w_i of direction
    (w the texel solid angles); its energy is sum t_i^2 / w_i, so over all pixels tr(W^-1 G).
    Its part in the span of SH l <= 2 (orthonormalised on the cube's directions with weights w) is
    tr(Q'GQ). Returns (that share, 0..1; the rank of Q'GQ, how many of the 9 components the pixels
    determine). A diffuse, shadow-free scene has a share near 1: only those 9 numbers of the light
    are observable (the paper's point: cast shadows carry the rest).
    """
    from .bases.sh import real_sh

    both = ne.fit.combine(ne.held_out)
    w = cube.solid_angles.astype(np.float64)
    Y = real_sh(2, cube.directions)
    M = Y.T @ (w[:, None] * Y)
    evals, evecs = np.linalg.eigh(M)
    keep = evals > 1e-9 * evals.max()
    Q = Y @ (evecs[:, keep] / np.sqrt(evals[keep]))  # Q' W Q = I
    total = float(np.sum(both.diag("mean") / w))
    if total <= 0:
        return 0.0, 0
    low = both.project(Q).G
    low = low if low.ndim == 2 else low.mean(axis=0)
    lev = np.linalg.eigvalsh((low + low.T) / 2)
    rank = int(np.sum(lev > 1e-8 * max(float(lev.max(initial=0.0)), 1e-300)))
    return float(np.trace(low)) / total, rank


def diagnose(ne: LightSystem, solution: LightSolution, cube: CubeMap, relit_error: float | None) -> list[str]:
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
    unobservable: np.ndarray | None = None  # (N,) bool: texels no used pixel sees (`observability`)

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
