"""One pass over the used pixels -> the normal equations of the light solve.

For the transport T (pixels x texels, `render.transport`) and the photo b (pixels x RGB), the
solve needs only G = T'T (texels x texels) and h = T'b: every basis P then costs P'GP and P'h,
and the residual of any light L is  |TL - b|^2 = L'GL - 2h'L + b'b,  with no second pass.
Pixels are split into a fit set and a held-out set (for choosing the model size), each with its
own (G, h, b'b). T never exists whole: blocks of pixel rows are built and folded in.

Channels share G when the material's RGB kd and ks are proportional (the default white
material): T_c = a_c T_0, so G_c = a_c^2 G_0 and h_c = a_c T_0'b_c. Otherwise each channel gets
its own G.
"""

from __future__ import annotations

import os
import time
from collections import deque
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.linalg import blas

from ..geometry.visibility import VisibilityData
from ..model.materials import Material
from ..model.microfacet import samples_footprint
from ..model.render import transport
from ..threads import blas_threads


@dataclass
class SystemPart:
    """Normal equations of one pixel set: for channel c, |T_c L - b_c|^2 = L'G_c L - 2 h_c'L + bb_c.

    G: (N, N) shared by all channels up to a factor (G_c = channel_scale_c^2 G), or (C, N, N);
    h: (N, C); bb: (C,).
    """

    G: np.ndarray
    h: np.ndarray
    bb: np.ndarray
    n_pixels: int
    channel_scale: np.ndarray | None = None

    def gram(self, channel: int) -> np.ndarray:
        if self.G.ndim == 3:
            return self.G[channel]
        a = 1.0 if self.channel_scale is None else float(self.channel_scale[channel])
        return self.G if a == 1.0 else (a * a) * self.G

    def residual(self, light: np.ndarray) -> np.ndarray:
        """(C,) sum of squared residuals |T L_c - b_c|^2 of a light (N, C), from G alone."""
        L = np.asarray(light, dtype=np.float64)
        out = np.empty(L.shape[1])
        for c in range(L.shape[1]):
            out[c] = L[:, c] @ self.gram(c) @ L[:, c] - 2.0 * self.h[:, c] @ L[:, c] + self.bb[c]
        return np.maximum(out, 0.0)

    def relative_rmse(self, light: np.ndarray) -> float:
        """sqrt(residual / b'b) over all channels (0 = perfect)."""
        return float(np.sqrt(self.residual(light).sum() / max(self.bb.sum(), 1e-300)))

    # -- the interface every part offers the bases (`rows.RowsPart` is the other kind) ---------------
    def project(self, P) -> SystemPart:
        """The system in coefficients c of light = P c: (P'GP, P'h). P dense or sparse (N, k)."""
        def proj(G):
            if sp.issparse(P):
                A = np.asarray((P.T @ G))  # (k, N)
                return np.asarray((P.T @ A.T).T)
            return P.T @ G @ P

        G = np.stack([proj(g) for g in self.G]) if self.G.ndim == 3 else proj(self.G)
        G = 0.5 * (G + np.swapaxes(G, -1, -2))
        return SystemPart(G, np.asarray(P.T @ self.h), self.bb, self.n_pixels, self.channel_scale)

    def project_tree(self, tree) -> SystemPart:
        """The system in the leaf values of a Haar tree (`haar.leaf_matrix`)."""
        from .haar import leaf_matrix

        return self.project(leaf_matrix(tree))

    def select(self, texels: np.ndarray) -> SystemPart:
        """The system of the light restricted to some texels (the others held at zero)."""
        G = self.G[np.ix_(texels, texels)] if self.G.ndim == 2 else self.G[:, texels][:, :, texels]
        return SystemPart(G, self.h[texels], self.bb, self.n_pixels, self.channel_scale)

    def gradient(self, light: np.ndarray, support=None) -> np.ndarray:
        """(N, C) minus half the gradient of the residual at a texel light: T'(b - T L) = h - G L.
        `support`: the texels where the light may be non-zero (the others are zero)."""
        L = np.asarray(light, dtype=np.float64)
        sub = np.arange(len(L)) if support is None else np.asarray(support, np.int64)
        if len(sub) == 0:
            return self.h.copy()
        return np.column_stack([self.h[:, c] - self.gram(c)[:, sub] @ L[sub, c] for c in range(self.h.shape[1])])

    def diag(self, channels: str = "max") -> np.ndarray:
        """(N,) the squared transport each texel gets from these pixels; per-channel G: the channels'
        `max` or `mean`."""
        if self.G.ndim == 2:
            return np.diag(self.G).copy()
        d = np.einsum("cii->ci", self.G)
        return d.max(axis=0) if channels == "max" else d.mean(axis=0)

    def combine(self, other: SystemPart) -> SystemPart:
        """The normal equations of the union of two pixel sets."""
        if other.n_pixels == 0:
            return self
        return SystemPart(self.G + other.G, self.h + other.h, self.bb + other.bb, self.n_pixels + other.n_pixels,
                          self.channel_scale)


@dataclass
class LightSystem:
    """What the bases solve: the fit pixels' part and the held-out pixels' part (each a dense
    `SystemPart` over all pixels, or a `rows.RowsPart` over a sample of them)."""

    fit: SystemPart
    held_out: SystemPart
    seconds: float
    explore: object = None  # a smaller part of the fit pixels that refinement levels are chosen on (None: fit)


def holdout_mask(pixels: np.ndarray, fraction: float, seed: int = 0) -> np.ndarray:
    """Deterministic, spatially scattered held-out pixels: a hash of (row, col) below `fraction`."""
    if not 0.0 <= fraction < 1.0:
        raise ValueError(f"held-out fraction must be in [0, 1), got {fraction}")
    key = (pixels[:, 0].astype(np.uint64) * np.uint64(73856093)) ^ (pixels[:, 1].astype(np.uint64) * np.uint64(19349663))
    key = (key + np.uint64(seed) * np.uint64(83492791)) * np.uint64(2654435761)
    return ((key >> np.uint64(8)) % np.uint64(1 << 20)).astype(np.float64) / float(1 << 20) < fraction


def _channel_scale(material: Material) -> np.ndarray | None:
    kd, ks = np.asarray(material.kd), np.asarray(material.ks)
    ref = int(np.argmax(kd + ks))
    if kd[ref] + ks[ref] == 0:
        return np.zeros(3)
    a = (kd + ks) / (kd[ref] + ks[ref])
    shared = np.allclose(kd, a * kd[ref], rtol=1e-9, atol=0) and (not material.specular or np.allclose(
        ks, a * ks[ref], rtol=1e-9, atol=0))
    return a if shared else None


def _syrk(T: np.ndarray) -> np.ndarray:
    """Lower triangle of T'T in float64, as a C-ordered array (the upper part is not filled).

    float64 throughout, not float32 products: G's rounding would otherwise be ~1e-6 of its size,
    which is both the floor of a noise-free fit and gradient noise that stalls the NNLS near its
    optimum; and the residual from G (L'GL - 2h'L + b'b) cancels, so G must be accurate for it.
    """
    # T' of a C-ordered T is a Fortran-ordered view: BLAS reads it without a copy. dsyrk returns the
    # upper triangle in Fortran order; its transpose is the lower triangle in C order, which the
    # C-ordered accumulators add at memory speed (adding the Fortran array itself strides across
    # rows: 60x slower, and it dominated the pass)
    return blas.dsyrk(1.0, np.ascontiguousarray(T, dtype=np.float64).T, trans=0, lower=0).T


def _symmetrise(G: np.ndarray) -> np.ndarray:
    """The full symmetric matrix from its lower triangle."""
    return np.tril(G) + np.tril(G, -1).T


def build_normal_equations(vis: VisibilityData, photo: np.ndarray, material: Material,
                           use: np.ndarray | None = None, held_out: np.ndarray | None = None,
                           rows: int = 2048, progress=None, threads: int | None = None,
                           albedo: np.ndarray | None = None, specular: np.ndarray | None = None) -> LightSystem:
    """Accumulate G, h, b'b for the fit and held-out pixel sets.

    Parameters
    ----------
    vis : visibility data of the used pixels.
    photo : (P, 3) linear radiance of the used pixels (same order as vis.samples).
    material : reflectance used to build the transport.
    use : (P,) bool, pixels that may be fitted at all (e.g. not saturated); default all.
    held_out : (P,) bool, pixels kept out of the fit for model selection; default none.
    threads : worker threads (default: the machine's cores, at most 4).
    albedo : (P, 3) per-pixel relative albedo multiplying kd (several parts, textures); None: uniform.
    specular : (P,) 0 for pixels of matte parts (no lobe: `model.render.transport`), else the factor on
        ks (the part's specular weight); None: all have it at 1.
    """
    t0 = time.perf_counter()
    b = np.asarray(photo, dtype=np.float64)
    P = vis.n_pixels
    if b.shape != (P, 3):
        raise ValueError(f"photo values must have shape ({P}, 3), got {b.shape}")
    use = np.ones(P, bool) if use is None else np.asarray(use, bool)
    held_out = np.zeros(P, bool) if held_out is None else np.asarray(held_out, bool)
    N = vis.cube.n_texels
    scale = _channel_scale(material) if albedo is None else None
    kd, ks = np.asarray(material.kd, np.float32), np.asarray(material.ks, np.float32)
    nG = 1 if scale is not None else 3
    parts = {}
    for name in ("fit", "held_out"):
        parts[name] = {"G": np.zeros((nG, N, N)), "h": np.zeros((N, 3)), "bb": np.zeros(3), "n": 0}
    s = vis.samples
    ref = None if scale is None else int(np.argmax(kd + ks))

    def block(sl: slice) -> dict:
        """Everything one block of pixel rows adds to the two parts (runs in a worker thread)."""
        V = vis.block(sl)
        D, S = transport(V, s.normal[sl], s.view[sl], vis.cube, material, None if specular is None else specular[sl],
                         samples_footprint(s, sl, material))
        bb = b[sl]
        add = {}
        for name, sel in (("fit", use[sl] & ~held_out[sl]), ("held_out", use[sl] & held_out[sl])):
            if not sel.any():
                continue
            if scale is not None:
                T = kd[ref] * D[sel] + (ks[ref] * S[sel] if S is not None else 0)
                grams = [_syrk(T)]
                h = (T.T.astype(np.float64) @ bb[sel]) * scale[None, :]  # T_c = a_c T_ref
            else:
                grams, h = [], np.zeros((N, 3))
                for c in range(3):
                    k = kd[c] if albedo is None else (kd[c] * albedo[sl][sel, c]).astype(np.float32)[:, None]
                    T = k * D[sel] + (ks[c] * S[sel] if S is not None else 0)
                    grams.append(_syrk(T))
                    h[:, c] = T.T.astype(np.float64) @ bb[sel, c]
            add[name] = (int(sel.sum()), (bb[sel] ** 2).sum(axis=0), grams, h)
        return add

    # Blocks run on a few threads, each with single-threaded BLAS (threads.py: no spin-waiting when
    # the machine is busy; transport's numpy work runs in parallel too); the main thread folds the
    # results in, in order, into float64 sums, with at most `workers + 1` blocks in flight.
    slices = [slice(a, min(P, a + rows)) for a in range(0, P, rows)]
    workers = max(1, min(threads or os.cpu_count() or 1, 4, len(slices)))
    with blas_threads(1), ThreadPoolExecutor(workers) as pool:
        pending = deque()
        for i in range(len(slices) + workers + 1):
            if i < len(slices):
                pending.append((slices[i], pool.submit(block, slices[i])))
            if pending and (len(pending) > workers or i >= len(slices)):
                sl, fut = pending.popleft()
                for name, (n, bb2, grams, h) in fut.result().items():
                    part = parts[name]
                    part["n"] += n
                    part["bb"] += bb2
                    for g, add in zip(part["G"], grams):
                        g += add
                    part["h"] += h
                if progress:
                    progress(sl.stop, P)
    out = {}
    for name, part in parts.items():
        G = np.stack([_symmetrise(g) for g in part["G"]])
        out[name] = SystemPart(G[0] if scale is not None else G, part["h"], part["bb"], part["n"], scale)
    return LightSystem(out["fit"], out["held_out"], time.perf_counter() - t0)
