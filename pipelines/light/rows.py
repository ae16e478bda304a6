"""The light solve on transport rows: a weighted sample of the pixels instead of dense normal equations.

The dense route (`system.build_normal_equations`) folds every pixel into G = T'T over all texels:
50,000 pixels x 3,072^2 entries for a light that ends with a few hundred coefficients. Here the
transport rows of a sample of pixels are kept, each row weighted by the number of pixels it
stands for (`sampling`), and each basis' system is built in its own coefficients: for a Haar
tree, the transport of a leaf is the sum of its texels' transport, which the rows keep for every
level of every tile (a pyramid of 2 x 2 sums: O(texels) per row, once), so a level's system
A'WA costs a gather and (rows x leaves^2), never (pixels x texels^2).

`RowsPart` offers the bases the same interface as `system.SystemPart` (project, project_tree,
select, gradient, diag, relative_rmse, combine); residuals are computed from the rows directly,
so they do not cancel the way L'GL - 2h'L + b'b does.

Channel c's transport is kd_c D + ks_c S, with D the diffuse transport (kd = 1) and S the
specular one (ks = 1); both are kept, so a new kd colour needs no new rows and a new shininess
only a new S.
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass, field
from functools import cached_property, lru_cache
import weakref

import numpy as np
from scipy.linalg import blas

from ..threads import parallel_blocks
from .haar import HaarTree
from .system import SystemPart


MEMO_TREES = 6  # tree systems a RowsPart keeps (the largest of the latest exploration's levels)
_CURRENT = object()  # (`TransportRows._matte`: the rows' current specular weights)
PYRAMID_BLOCK = 1024  # rows whose block sums a thread forms at a time
SYSTEM_BLOCK_VALUES = 2**21  # a tree system is projected in blocks of rows of at most this many leaf sums
# (memory: a block's leaf sums and weighted copies; fewer, larger blocks keep BLAS efficient)
# `RowsPart._grown`: a tree's system extends a memoised one when at most this share of its leaves is new
# and it has at least as many rows as leaves (with fewer, putting the L x L matrix together costs more
# than the rows' products). Measured, not the flop count's (A'A_new is 2 n L k flops against the whole
# A'A's n L^2: 1.2x at 60 % new, but the whole one is also mirrored and reordered into tree order):
# spot_sun's explore rows, 8192 x 1100-1650 leaves, 1.7-3x faster at 27-50 % new, slower at 87 %
GROWN_SHARE = 0.6
# `RowsPart.adopt`: memoised systems are corrected for other weights when at most this share of the rows
# changed (the correction projects the changed rows twice, new and old, for every memoised tree)
ADOPT_SHARE = 0.25


class Pyramid:
    """Texel sums of transport rows at every level of every tile.

    rows : (n, N) float32 transport (texel order: tile by tile, row-major inside a tile).
    levels[t][l] : (n, 2^l, 2^l) sums over the tile's blocks at level l (l = log2(size): the texels
    themselves, views into `rows`).
    """

    def __init__(self, rows: np.ndarray, tile_sizes: tuple[int, ...]):
        self.rows = rows
        self.tile_sizes = tuple(int(s) for s in tile_sizes)
        self.version = [0]  # shared with the heads: bumped when rows change in place (`set_rows`)
        n = len(rows)
        self.levels = []  # levels[t][l]: (n, 4^l) the sums of the tile's 2^l x 2^l blocks, row-major
        self.offsets = []
        offset = 0
        for s in self.tile_sizes:
            top = int(np.log2(s))
            # {level: array}; the texels themselves (top) are columns of `rows`
            self.levels.append({top: None, **{lv: np.empty((n, 4**lv), np.float32) for lv in range(top)}})
            self.offsets.append(offset)
            offset += s * s

        def run(starts):  # (the sums of blocks of rows, on both cores: the same sums as all rows at once)
            for a in starts:
                sl = slice(a, min(n, a + PYRAMID_BLOCK))
                for s, off, tile in zip(self.tile_sizes, self.offsets, self.levels):
                    cur = rows[sl, off:off + s * s].reshape(-1, s, s)
                    for level in range(int(np.log2(s)) - 1, -1, -1):
                        cur = cur[:, :, 0::2] + cur[:, :, 1::2]
                        cur = cur[:, 0::2, :] + cur[:, 1::2, :]
                        tile[level][sl] = cur.reshape(len(cur), -1)

        parallel_blocks(run, list(range(0, n, PYRAMID_BLOCK)))

    def head(self, n: int) -> "Pyramid":
        """The first n rows (views, no copy)."""
        out = object.__new__(Pyramid)
        out.rows, out.tile_sizes, out.offsets, out.version = self.rows[:n], self.tile_sizes, self.offsets, self.version
        out.whole = getattr(self, "whole", self)  # (the whole lives while a head does: `TransportRows.pyramids`)
        out.levels = [{lv: (None if a is None else a[:n]) for lv, a in tile.items()} for tile in self.levels]
        return out

    def tail(self, n: int) -> "Pyramid":
        """The rows from n on (views, no copy), as `head`."""
        out = self.head(len(self.rows))
        out.rows = self.rows[n:]
        out.levels = [{lv: (None if a is None else a[n:]) for lv, a in tile.items()} for tile in self.levels]
        return out

    def set_rows(self, index: np.ndarray, rows: np.ndarray) -> None:
        """Replace some rows in place (their block sums too): every head sees them, and the systems
        projected before are marked stale (`version`) unless corrected (`RowsPart.correct`)."""
        index = np.asarray(index, np.int64)
        if not len(index):
            return
        new = Pyramid(np.ascontiguousarray(rows, np.float32), self.tile_sizes)
        self.rows[index] = new.rows
        for tile, fresh in zip(self.levels, new.levels):
            for level, a in tile.items():
                if a is not None:
                    a[index] = fresh[level]
        self.version[0] += 1

    def leaf_sums(self, tree: HaarTree, rows: slice = slice(None), grouped: bool = False) -> np.ndarray:
        """(n, leaves) float32: each row's transport (of `rows`: all by default) summed over each leaf,
        in `tree.leaves()` order, or with `grouped` in `leaf_order(tree)` (the leaves of one level of
        one tile side by side: each is one gather into a block of columns, ~2x faster than placing
        them in tree order)."""
        if tuple(tree.tile_sizes) != self.tile_sizes:
            raise ValueError("the tree does not cover this cube map's tiles")
        n = len(range(*rows.indices(len(self.rows))))
        out = np.empty((n, tree.n_leaves), np.float32)
        a = 0
        for cols, t, level, idx in _leaf_plan(tree):
            pool = self.levels[t][level]
            if pool is None:  # single texels
                src, idx = self.rows, self.offsets[t] + idx
            else:
                src = pool
            # (np.take gathers columns ~1.5x faster than fancy indexing)
            if grouped:
                out[:, a:a + len(idx)] = np.take(src[rows], idx, axis=1)
            else:
                out[:, cols] = np.take(src[rows], idx, axis=1)
            a += len(idx)
        return out


def _n_leaves(entry) -> int:
    """Leaves of a memoised tree system (a SystemPart, or the pieces of `RowsPart._group_pieces`)."""
    return len(entry.h) if isinstance(entry, SystemPart) else len(next(iter(entry.values()))["hD"])


def _assembled(old: np.ndarray, cross: np.ndarray, kept, was, fresh, inv, rows: np.ndarray | None = None):
    """A grown tree's square matrix ((L, L) or (C, L, L), float64, tree order; `RowsPart._grown`):
    the old tree's entries `was` at the new positions `kept`, the new leaves' columns `cross`
    ((..., L, k), rows in grouped leaf order: `inv` maps tree order to it) and rows: `rows`
    ((..., k, L), grouped columns) for a matrix that is not symmetric, else cross's transpose (the
    new leaves' own block from one triangle, mirrored: symmetric exactly)."""
    one = old.ndim == 2
    old, cross = (old[None], cross[None]) if one else (old, cross)
    rows = None if rows is None else (rows[None] if one else rows)
    L = len(inv)
    out = np.empty((len(old), L, L))
    for i, g in enumerate(out):
        x = np.asarray(cross[i], np.float64)[inv]
        g[np.ix_(kept, kept)] = np.take(np.take(old[i], was, axis=0), was, axis=1)
        g[:, fresh] = x
        block = x[fresh]
        if rows is None:
            g[fresh, :] = x.T
            block = np.triu(block) + np.triu(block, 1).T
        else:
            g[fresh, :] = np.asarray(rows[i], np.float64)[:, inv]
        g[np.ix_(fresh, fresh)] = block
    return out[0] if one else out


@lru_cache(maxsize=64)
def _leaves(tile_sizes: tuple, subdivided: tuple) -> tuple:
    """`HaarTree.leaves()` of the tree of a memo key (kept for the latest trees: `RowsPart._grown`)."""
    return tuple(HaarTree(tile_sizes, subdivided).leaves())


@lru_cache(maxsize=16)
def _leaf_plan(tree: HaarTree) -> list:
    """The tree's leaves grouped by (level, tile): [(their columns in `leaves()` order, tile, level,
    their block index in the tile's level, row-major (at the top level: the texel's in the tile))]
    (kept for the latest trees: a projection asks for it once per block of rows; read only)."""
    plan = []
    for level, (cols, tile, i, j) in _leaf_groups(tree).items():
        for t in np.unique(tile):
            sel = tile == t
            plan.append((cols[sel], int(t), level, (i[sel] << level) + j[sel]))
    return plan


def _in_tree_order(entry, order: np.ndarray):
    """A tree system (a SystemPart, or per part the pieces of `RowsPart._group_pieces`) projected
    from leaf sums whose column k is leaf order[k], put in `leaves()` order."""
    inv = np.empty_like(order)
    inv[order] = np.arange(len(order))
    if np.array_equal(inv, np.arange(len(inv))):
        return entry

    def square(M):  # (..., L, L) (np.take: faster than fancy indexing)
        return None if M is None else np.take(np.take(M, inv, axis=-2), inv, axis=-1)

    if isinstance(entry, SystemPart):
        return SystemPart(square(entry.G), entry.h[inv], entry.bb, entry.n_pixels, entry.channel_scale)
    return {q: {k: (v if v is None or k == "bb" else square(v) if k in ("DD", "X", "SS") else v[inv])
                for k, v in e.items()} for q, e in entry.items()}


def leaf_order(tree: HaarTree) -> np.ndarray:
    """The `leaves()` index of each column of `Pyramid.leaf_sums(tree, grouped=True)`."""
    return np.concatenate([cols for cols, *_ in _leaf_plan(tree)])


def _leaf_groups(tree: HaarTree) -> dict:
    """The tree's leaves grouped by level: {level: (column, tile, i, j) arrays}."""
    leaves = np.array(tree.leaves(), dtype=np.int64).reshape(-1, 4)
    groups = {}
    for level in np.unique(leaves[:, 1]):
        cols = np.flatnonzero(leaves[:, 1] == level)
        groups[int(level)] = (cols, leaves[cols, 0], leaves[cols, 2], leaves[cols, 3])
    return groups


def _rhs(A: np.ndarray, r: np.ndarray) -> np.ndarray:
    """h = A'r in float64 for weighted rows A (float64, or float32 for a single-precision system:
    then in float32 like its Gram matrix, with no float64 copy of A: a transposed cast strides
    through memory, numpy's mixed float32/float64 product can take a non-BLAS loop, and a fresh
    copy's page faults alone were measured at up to 1 s per level on the test machines)."""
    if A.dtype == np.float64:
        return A.T @ r
    return (A.T @ r.astype(np.float32)).astype(np.float64)


def _gram(A: np.ndarray) -> np.ndarray:
    """A'A (A float64: dsyrk; float32: ssyrk, accumulated in float32), symmetrised, in float64."""
    return _symmetric(_upper_gram(A))


def _upper_gram(A: np.ndarray, C: np.ndarray | None = None) -> np.ndarray:
    """The upper triangle of A'A (in A's precision), added to C's (an earlier block's) when given."""
    syrk = blas.dsyrk if A.dtype == np.float64 else blas.ssyrk
    # without a `c` scipy's wrapper starts from zeros, so the strict lower triangle stays 0
    if C is None:
        return syrk(1.0, np.ascontiguousarray(A).T, trans=0, lower=0)
    return syrk(1.0, np.ascontiguousarray(A).T, beta=1.0, c=C, trans=0, lower=0, overwrite_c=1)


SYMMETRIC_BLOCK = 256  # `_symmetric` mirrors the upper triangle in square blocks of this size


def _symmetric(C: np.ndarray) -> np.ndarray:
    """The symmetric float64 matrix of an upper triangle (C's strict lower triangle is ignored: 0
    from `_upper_gram`): the upper triangle mirrored block by block, each block's transpose read
    while it is in cache (`G += G.T` strides through the whole matrix: 4x slower at 1,400 leaves)."""
    G = C.astype(np.float64)
    n, b = len(G), SYMMETRIC_BLOCK
    for i in range(0, n, b):
        for j in range(i + b, n, b):
            G[j:j + b, i:i + b] = G[i:i + b, j:j + b].T
        block = G[i:i + b, i:i + b]
        block[...] = np.triu(block) + np.triu(block, 1).T
    return G


def _tree_size(key: tuple) -> int:
    """A memo key's tree size: its subdivided nodes (leaves = tiles + 3 x nodes)."""
    return sum(len(nodes) for nodes in key[1])


def _of_rows(v, rows: slice):
    """A per-row (n, 1) factor's rows, or a scalar one as it is."""
    return v[rows] if np.ndim(v) == 2 else v


def _channel(v: np.ndarray, c: int) -> np.ndarray:
    """Channel c of a per-channel value (C,) (a scalar) or per-row one (n, C) (an (n, 1) column)."""
    return v[..., c][:, None] if v.ndim == 2 else np.asarray(v[c])


@dataclass
class RowsPart:
    """A weighted sample of transport rows: for channel c, sum_j w_j (T_c L - b_c)_j^2 with
    T_c = kd_c D + ks_c S.

    D, S : `Pyramid`s of the diffuse (kd = 1) and specular (ks = 1) transport (S None: Lambertian).
    kd, ks : (C,) the material per channel; kd may be (n, C), per row (several parts, textures: the
        material's kd times each row's relative albedo).
    b : (n, C) photo values; w : (n,) weights (pixels each row stands for).
    n_pixels : the pixels these rows stand for (what the diagnostics count).
    precision : "double" accumulates the projected systems in float64; "single" in float32 (half the
        time: the exploration's head, and the final light's `finish`, whose residuals come from the
        rows; the reflectance rounds' systems stay in float64, their fit errors taken from G).
    """

    D: Pyramid
    S: Pyramid | None
    kd: np.ndarray
    ks: np.ndarray
    b: np.ndarray
    w: np.ndarray
    n_pixels: int
    precision: str = "double"
    # the systems of the trees projected so far, by tree: a level explored again (after a few rows
    # changed, `correct`; with other part scales, `with_scales`) costs no second pass over the rows
    memo: OrderedDict = field(default_factory=OrderedDict, repr=False, compare=False)
    # several parts: row j's kd is kd[j] x group_scales[group[j]] (kd (n, C) then holds the material's
    # kd x the known relative albedo, the part's fitted factor 1). A Lambertian tree system is then
    # kept per part, so that it serves any factors: G_c = sum_q s_qc^2 G_qc, h_c = sum_q s_qc h_qc
    group: np.ndarray | None = None
    group_scales: np.ndarray | None = None
    # and each part's specular weight (parts,): row j's ks is ks x group_ks[group[j]] (None: 1 for all)
    group_ks: np.ndarray | None = None
    # with a specular term the pieces cost ~3x one projection (diffuse, cross and specular products):
    # worth it for a system re-solved under many factors (a specular round's), not for one explored once
    split_specular: bool = True

    @property
    def n_rows(self) -> int:
        return len(self.b)

    @cached_property
    def kd_eff(self) -> np.ndarray:
        """The kd the rows render with: (C,), or (n, C) per row (the part factors applied)."""
        kd = np.asarray(self.kd, np.float64)
        if self.group is None:
            return kd
        return kd * np.asarray(self.group_scales, np.float64)[self.group]

    @cached_property
    def ks_eff(self) -> np.ndarray:
        """The ks the rows render with: (C,), or (n, C) per row (the parts' specular weights applied)."""
        ks = np.asarray(self.ks, np.float64)
        if self.group is None or self.group_ks is None:
            return ks
        return ks[None, :] * np.asarray(self.group_ks, np.float64)[self.group][:, None]

    def _ks(self, c: int) -> np.ndarray:
        """Channel c's ks: a scalar, or (n, 1) per row."""
        return _channel(self.ks_eff, c)

    def with_scales(self, scales: np.ndarray, ks_scales: np.ndarray | None = None) -> "RowsPart":
        """The same rows with other part factors (`group_scales`, and `group_ks` when given): the tree
        systems kept per part serve it without a pass over the rows (the memo is shared)."""
        from dataclasses import replace

        if self.group is None:
            raise ValueError("with_scales needs rows grouped by part")
        ks = self.group_ks if ks_scales is None else np.array(ks_scales, np.float64)
        return replace(self, group_scales=np.array(scales, np.float64), group_ks=ks, memo=self.memo)

    @cached_property
    def bb(self) -> np.ndarray:
        return (self.w[:, None] * self.b**2).sum(axis=0)

    @cached_property
    def channel_scale(self) -> np.ndarray | None:
        """a_c with T_c = a_c T_ref when kd and ks are proportional across channels (else None)."""
        kd, ks = self.kd_eff, np.asarray(self.ks, float)
        if kd.ndim == 2:  # per-row albedo: one Gram matrix per channel
            return None
        ref = int(np.argmax(kd + ks))
        if kd[ref] + ks[ref] == 0:
            return np.zeros(len(kd))
        a = (kd + ks) / (kd[ref] + ks[ref])
        shared = np.allclose(kd, a * kd[ref], rtol=1e-9, atol=0) and (self.S is None or np.allclose(
            ks, a * ks[ref], rtol=1e-9, atol=0))
        return a if shared else None

    def _weighted(self, A_D: np.ndarray, A_S: np.ndarray | None, c: int, dtype,
                  rows: slice = slice(None)) -> np.ndarray:
        """sqrt(w) (kd_c A_D + ks_c A_S) in `dtype`: channel c's weighted coefficient-space rows (A_D,
        A_S those of `rows`)."""
        sw = np.sqrt(self.w[rows]).astype(dtype)[:, None]
        A = A_D.astype(dtype)  # a copy (A_D float32): scaled in place, no second temporary
        A *= sw * _of_rows(self._kd(c), rows).astype(dtype)
        if A_S is not None and self.ks[c] != 0:
            A += A_S.astype(dtype) * (sw * _of_rows(self._ks(c), rows).astype(dtype))
        return A

    def _system(self, A_D: np.ndarray | None, A_S: np.ndarray | None, blocks=None) -> SystemPart:
        """The weighted normal equations of coefficient-space rows (in `precision`): of A_D, A_S
        (n, k), or summed over `blocks`, (row slice, its A_D, its A_S) for every row in turn (memory:
        a block's arrays at a time)."""
        dtype = np.float64 if self.precision == "double" else np.float32
        scale = self.channel_scale
        ref = int(np.argmax(self.kd_eff + np.asarray(self.ks))) if scale is not None else None
        channels = [ref] if scale is not None else range(np.shape(self.kd)[-1])
        upper, h = [None] * len(channels), 0.0  # (each channel's Gram accumulated over the blocks in A's precision)
        for rows, a_d, a_s in ([(slice(None), A_D, A_S)] if blocks is None else blocks):
            sw = np.sqrt(self.w[rows])
            b = self.b[rows]
            r = []
            for i, c in enumerate(channels):
                A = self._weighted(a_d, a_s, c, dtype, rows)
                upper[i] = _upper_gram(A, upper[i])
                # (T_c = a_c T_ref, a_ref = 1: one Gram matrix, every channel's h from it)
                r.append(_rhs(A, b * sw[:, None]) * scale[None, :] if scale is not None else _rhs(A, b[:, c] * sw))
            A = None
            h = h + (r[0] if scale is not None else np.column_stack(r))
        if scale is not None:
            return SystemPart(_symmetric(upper[0]), h, self.bb, self.n_pixels, scale)
        return SystemPart(np.stack([_symmetric(u) for u in upper]), h, self.bb, self.n_pixels, None)

    def _kd(self, c: int) -> np.ndarray:
        """Channel c's kd: a scalar, or (n, 1) per row."""
        return _channel(self.kd_eff, c)

    # -- the part interface (as system.SystemPart) --------------------------------------------------
    def _versions(self) -> tuple:
        return (self.D.version[0], None if self.S is None else self.S.version[0])

    @property
    def _per_group(self) -> bool:
        """Tree systems kept per part (rows grouped by part), else for the rows' kd as it is."""
        return self.group is not None and (self.S is None or self.split_specular)

    def _tree_key(self, tree: HaarTree) -> tuple:
        key = (tree.tile_sizes, tree.subdivided)
        if self.group is not None and not self._per_group:  # (kept for these factors only)
            key += (np.asarray(self.group_scales, np.float64).tobytes(),
                    None if self.group_ks is None else np.asarray(self.group_ks, np.float64).tobytes())
        return key

    def _tree_entry(self, tree: HaarTree):
        """The memo's value for a tree: its SystemPart, or per part q the pieces of its rows' system at
        factor 1 (`_group_pieces`)."""
        key = self._tree_key(tree)
        hit = self.memo.get(key)
        if hit is not None and hit[0] == self._versions():
            self.memo.move_to_end(key)
            return hit[1]
        # (projected from the leaf sums in `leaf_order`, the faster gather, and put in tree order after;
        # fewer rows than leaves, the few rows a correction projects (`correct`, `adopt`): gathered in
        # tree order, as reordering the L x L products would cost more than forming them)
        grown = self._grown(tree, key)
        grouped = self.n_rows >= tree.n_leaves
        if grown is not None:
            out = grown
        elif self._per_group:
            A_D = self.D.leaf_sums(tree, grouped=grouped)
            A_S = None if self.S is None else self.S.leaf_sums(tree, grouped=grouped)
            out = {int(q): self._group_pieces(A_D, A_S, np.flatnonzero(self.group == q)) for q in np.unique(self.group)}
        else:  # (block by block: the leaf sums of all rows, weighted per channel, would be held at once)
            out = self._system(None, None, self._row_blocks(tree, grouped))
        if grown is None and grouped:
            out = _in_tree_order(out, leaf_order(tree))
        self.memo[key] = (self._versions(), out)
        while len(self.memo) > MEMO_TREES:  # (memory: leaves^2 per tree, part, channel)
            # the smallest tree goes (this one too, if it is): the cheapest to project again. Levels
            # are solved coarse to fine, so a least-recently-used memo would lose every large tree of
            # an exploration solved again (`bases.replay`, other part factors) to its small first levels
            del self.memo[min(self.memo, key=_tree_size)]
        return out

    def _row_blocks(self, tree: HaarTree, grouped: bool = True):
        """(row slice, its A_D, its A_S): the rows' leaf sums in `leaf_order` (or, not `grouped`, in
        tree order), block by block (memory: at most SYSTEM_BLOCK_VALUES leaf sums a block)."""
        n = self.n_rows
        step = -(-n // max(1, -(-n * tree.n_leaves // SYSTEM_BLOCK_VALUES))) if n else 1
        return ((sl, self.D.leaf_sums(tree, sl, grouped), None if self.S is None else self.S.leaf_sums(tree, sl, grouped))
                for sl in (slice(a, min(n, a + step)) for a in range(0, max(n, 1), step)))

    def _grown(self, tree: HaarTree, key: tuple):
        """The memo's value for `tree` (as `_tree_entry`) from a memoised one of a tree that shares most
        of its leaves (the level before, in a coarse-to-fine solve: a refined leaf gives way to its four
        children, and every other leaf's Gram entries stay what they were): only the new leaves'
        columns are projected, A'A_new (n L k multiply-adds for k new leaves, against n L^2 / 2 for
        the whole A'A). The same sums as projecting the tree afresh, added in another order (float
        rounding). None when no memoised tree of these rows shares enough leaves (more than
        GROWN_SHARE of them new), or the rows are fewer than the leaves."""
        L, versions = tree.n_leaves, self._versions()
        if self.n_rows < L:
            return None
        kind = dict if self._per_group else SystemPart
        position = None
        best = None
        for k, (version, entry) in self.memo.items():
            if version != versions or not isinstance(entry, kind) or k[0] != key[0] or k[2:] != key[2:] \
                    or L - _n_leaves(entry) > GROWN_SHARE * L:  # (fewer leaves than that cannot share enough)
                continue
            if position is None:
                position = {leaf: j for j, leaf in enumerate(_leaves(tree.tile_sizes, tree.subdivided))}
            common = [(position[leaf], i) for i, leaf in enumerate(_leaves(*k[:2])) if leaf in position]
            if best is None or len(common) > len(best[1]):
                best = (entry, common)
        if best is None or L - len(best[1]) > GROWN_SHARE * L or not best[1]:
            return None
        entry, common = best
        kept, was = (np.array(c, np.int64) for c in zip(*common))
        new = np.ones(L, bool)
        new[kept] = False
        order = leaf_order(tree)  # (column g of the grouped leaf sums is leaf order[g])
        inv = np.empty_like(order)
        inv[order] = np.arange(L)
        fresh = np.flatnonzero(new)
        cols = inv[fresh]  # the new leaves' columns among the grouped leaf sums

        def assembled(old, cross, rows=None):
            return _assembled(old, cross, kept, was, fresh, inv, rows)

        if self._per_group:
            A_D = self.D.leaf_sums(tree, grouped=True)
            A_S = None if self.S is None else self.S.leaf_sums(tree, grouped=True)
            out = {}
            for q, e in entry.items():
                c = self._group_cross(A_D, A_S, np.flatnonzero(self.group == q), cols)
                out[q] = {"bb": c["bb"], "hD": c["hD"][inv], "hS": None if c["hS"] is None else c["hS"][inv],
                          "DD": assembled(e["DD"], c["DD"]),
                          "X": None if c["X"] is None else assembled(e["X"], c["X"], c["X_rows"]),
                          "SS": None if c["SS"] is None else assembled(e["SS"], c["SS"])}
            return out
        dtype = np.float64 if self.precision == "double" else np.float32
        scale = self.channel_scale
        ref = int(np.argmax(self.kd_eff + np.asarray(self.ks))) if scale is not None else None
        channels = [ref] if scale is not None else range(np.shape(self.kd)[-1])
        cross, h = [0.0] * len(channels), 0.0  # (A'A_new per channel, accumulated over the blocks in A's precision)
        for rows, a_d, a_s in self._row_blocks(tree):
            sw = np.sqrt(self.w[rows])
            b = self.b[rows]
            r = []
            for i, c in enumerate(channels):
                A = self._weighted(a_d, a_s, c, dtype, rows)
                cross[i] = cross[i] + A.T @ np.take(A, cols, axis=1)
                r.append(_rhs(A, b * sw[:, None]) * scale[None, :] if scale is not None else _rhs(A, b[:, c] * sw))
            A = None
            h = h + (r[0] if scale is not None else np.column_stack(r))
        G = assembled(entry.G, np.stack(cross) if entry.G.ndim == 3 else cross[0])
        return SystemPart(G, np.asarray(h)[inv], self.bb, self.n_pixels, scale)

    def _part_rows(self, A_D: np.ndarray, A_S: np.ndarray | None, sel: np.ndarray) -> tuple:
        """Rows `sel`'s weighted arrays for `_group_pieces` and `_group_cross`: (the system's dtype,
        b sqrt(w) (n, C), kd per row (n, C), t = sqrt(w) A_S or None, base = sqrt(w) A_D)."""
        dtype = np.float64 if self.precision == "double" else np.float32
        sw = np.sqrt(self.w[sel])
        C = np.shape(self.kd)[-1]
        kd = np.asarray(self.kd, np.float64)
        kd = kd[sel] if kd.ndim == 2 else np.broadcast_to(kd, (len(sel), C))
        t = None if A_S is None else A_S[sel].astype(dtype) * sw.astype(dtype)[:, None]
        return dtype, self.b[sel] * sw[:, None], kd, t, A_D[sel].astype(dtype) * sw.astype(dtype)[:, None]

    def _group_cross(self, A_D: np.ndarray, A_S: np.ndarray | None, sel: np.ndarray, cols: np.ndarray) -> dict:
        """`_group_pieces` of rows `sel` for the new leaves `cols` (columns of A_D, A_S): DD, SS their
        columns ((C,) L x k, L x k), X its columns and "X_rows" its rows (X = a_c't is not symmetric);
        bb, hD and hS whole."""
        dtype, b, kd, t, base = self._part_rows(A_D, A_S, sel)
        C = kd.shape[1]
        out = {"bb": (b**2).sum(axis=0)}
        tc = None if t is None else np.take(t, cols, axis=1)
        if len(sel) and np.all(kd == kd[0]):  # a uniform part: one Gram matrix, kd_c^2 times
            k = kd[0]
            bc = np.take(base, cols, axis=1)
            out["DD"] = k[:, None, None] ** 2 * (base.T @ bc).astype(np.float64)[None]
            out["hD"] = np.column_stack([k[c] * _rhs(base, b[:, c]) for c in range(C)])
            out["X"] = None if t is None else k[:, None, None] * (base.T @ tc).astype(np.float64)[None]
            out["X_rows"] = None if t is None else k[:, None, None] * (bc.T @ t).astype(np.float64)[None]
        else:
            DD, hD, X, Xr = [], [], [], []
            for c in range(C):
                a = base * kd[:, c].astype(dtype)[:, None]
                ac = np.take(a, cols, axis=1)
                DD.append((a.T @ ac).astype(np.float64))
                hD.append(_rhs(a, b[:, c]))
                if t is not None:
                    X.append((a.T @ tc).astype(np.float64))
                    Xr.append((ac.T @ t).astype(np.float64))
            out["DD"], out["hD"] = np.stack(DD), np.column_stack(hD)
            out["X"], out["X_rows"] = (np.stack(X), np.stack(Xr)) if t is not None else (None, None)
        out["SS"] = None if t is None else (t.T @ tc).astype(np.float64)
        out["hS"] = None if t is None else np.column_stack([_rhs(t, b[:, c]) for c in range(C)])
        return out

    def _group_pieces(self, A_D: np.ndarray, A_S: np.ndarray | None, sel: np.ndarray) -> dict:
        """The system of rows `sel` (one part) split so that any factor s of the part and the material's
        ks give it: per channel c, G_c = s_c^2 DD_c + s_c ks_c (X_c + X_c') + ks_c^2 SS and
        h_c = s_c hD_c + ks_c hS_c, with a_c = sqrt(w) kd_c A_D (kd: the part's known albedo x the
        material's kd, factor 1) and t = sqrt(w) A_S: DD_c = a_c'a_c, X_c = a_c't, SS = t't,
        hD_c = a_c'b_c sqrt(w), hS_c = t'b_c sqrt(w)."""
        dtype, b, kd, t, base = self._part_rows(A_D, A_S, sel)
        C = kd.shape[1]
        out = {"bb": (b**2).sum(axis=0)}
        if len(sel) and np.all(kd == kd[0]):  # a uniform part (no texture): a_c = kd_c sqrt(w) A_D, one Gram
            k = kd[0]
            out["DD"] = k[:, None, None] ** 2 * _gram(base)[None]
            out["hD"] = np.column_stack([k[c] * _rhs(base, b[:, c]) for c in range(C)])
            out["X"] = None if t is None else k[:, None, None] * (base.T @ t).astype(np.float64)[None]
        else:  # a textured part: kd differs from row to row in each channel, a Gram matrix per channel
            DD, hD, X = [], [], []
            for c in range(C):
                a = base * kd[:, c].astype(dtype)[:, None]
                DD.append(_gram(a))
                hD.append(_rhs(a, b[:, c]))
                if t is not None:
                    X.append((a.T @ t).astype(np.float64))
            out["DD"], out["hD"] = np.stack(DD), np.column_stack(hD)
            out["X"] = np.stack(X) if t is not None else None
        out["SS"] = None if t is None else _gram(t)
        out["hS"] = None if t is None else np.column_stack([_rhs(t, b[:, c]) for c in range(C)])
        return out

    def _combined(self, entry) -> SystemPart:
        if not isinstance(entry, dict):
            return entry
        s = np.asarray(self.group_scales, np.float64)
        C = s.shape[1]
        G, h = 0.0, 0.0
        for q, e in entry.items():
            ks = np.asarray(self.ks, np.float64) * (1.0 if self.group_ks is None else float(self.group_ks[q]))
            Gq = s[q][:, None, None] ** 2 * e["DD"]
            hq = e["hD"] * s[q][None, :]
            if e["X"] is not None:
                for c in range(C):
                    if ks[c] != 0:
                        Gq[c] += s[q, c] * ks[c] * (e["X"][c] + e["X"][c].T) + ks[c] ** 2 * e["SS"]
                hq = hq + e["hS"] * ks[None, :]
            G, h = G + Gq, h + hq
        return SystemPart(G, h, self.bb, self.n_pixels, None)

    def project_tree(self, tree: HaarTree) -> SystemPart:
        return self._combined(self._tree_entry(tree))

    def group_systems(self, tree: HaarTree) -> dict:
        """Per part q, the Lambertian system of its rows at factor 1 ({q: SystemPart})."""
        if not self._per_group:
            raise ValueError("group_systems needs rows grouped by part")
        return {q: SystemPart(e["DD"], e["hD"], e["bb"], 0, None) for q, e in self._tree_entry(tree).items()}

    def correct(self, index: np.ndarray, old_D: np.ndarray, old_S: np.ndarray | None, stale: tuple) -> None:
        """Rows `index` of D (and S) were replaced in place (`Pyramid.set_rows`): their previous
        values were old_D, old_S, and `stale` the versions before. Each memoised tree system is
        corrected by the rows' change (the new rows' system minus the old rows'), exactly as if it
        were projected again, at the cost of those rows alone."""
        index = np.asarray(index, np.int64)
        # (a memo shared with copies of other factors, `with_scales`: theirs go, stale)
        keep = OrderedDict((k, v) for k, v in self.memo.items()
                           if v[0] == stale and k == self._tree_key(HaarTree(*k[:2])))
        self.memo = OrderedDict()
        if not len(keep):
            return
        if not len(index):
            self.memo = OrderedDict((k, (self._versions(), v[1])) for k, v in keep.items())
            return
        kd = self.kd[index] if np.ndim(self.kd) == 2 else self.kd
        w, b = self.w[index], self.b[index]
        group = None if self.group is None else self.group[index]

        def rows_part(D, S):
            return RowsPart(Pyramid(np.ascontiguousarray(D), self.D.tile_sizes),
                            None if S is None else Pyramid(np.ascontiguousarray(S), self.D.tile_sizes),
                            kd, self.ks, b, w, 0, self.precision, group=group, group_scales=self.group_scales,
                            split_specular=self.split_specular, group_ks=self.group_ks)

        def fix(system, a, c):
            return SystemPart(system.G + a.G - c.G, system.h + a.h - c.h, system.bb, system.n_pixels,
                              system.channel_scale)

        def fix_pieces(e, a, c):
            return {k: (v if v is None or k == "bb" else v + a[k] - c[k]) for k, v in e.items()}

        old = rows_part(old_D, old_S)
        new = rows_part(self.D.rows[index], None if self.S is None else self.S.rows[index])
        for key, (_, entry) in keep.items():
            tree = HaarTree(*key[:2])
            a, c = new._tree_entry(tree), old._tree_entry(tree)
            new.memo.clear(), old.memo.clear()  # (the changed rows' systems of one tree at a time: memory)
            if isinstance(entry, dict):  # per part: only the parts of the changed rows change
                entry = {q: fix_pieces(e, a[q], c[q]) if q in a else e for q, e in entry.items()}
            else:
                entry = fix(entry, a, c)
            self.memo[key] = (self._versions(), entry)

    def adopt(self, other: "RowsPart") -> int | None:
        """Take over `other`'s memoised tree systems: the same transport rows under other weights
        and targets (the robust pass's: a few pixels down-weighted, a clipped pixel's bound moved).
        Every weight of `other` times one common factor s (a head's, whose weights are scaled to
        stand for all pixels, changes with theirs) is this part's but at the changed rows, so each
        system is s times the old one plus the changed rows' new system minus their old one: exactly
        the system projected afresh, at the cost of those rows alone. `other`'s memo is emptied.
        Returns how many rows changed, or None when nothing is taken over (other transport, other
        material, or more than ADOPT_SHARE of the rows changed: projecting afresh is then cheaper).
        (A copy of `other` with other part factors, `with_scales`, shares its memo dict and keeps
        it: its systems are neither taken nor changed.)"""
        if not isinstance(other, RowsPart) or other is self or not other.memo:
            return None
        same_rows = (other.n_rows == self.n_rows and other.precision == self.precision
                     and other.D.version is self.D.version and len(other.D.rows) == len(self.D.rows)
                     and (other.S is None) == (self.S is None)
                     and (self.S is None or other.S.version is self.S.version)
                     and other.split_specular == self.split_specular
                     and np.array_equal(other.kd, self.kd) and np.array_equal(other.ks, self.ks)
                     and (other.group is None) == (self.group is None)
                     and (self.group is None or np.array_equal(other.group, self.group)))
        if same_rows and self.group is not None and not self._per_group:  # (systems at the factors)
            same_rows = (np.array_equal(other.group_scales, self.group_scales)
                         and (other.group_ks is None) == (self.group_ks is None)
                         and (self.group_ks is None or np.array_equal(other.group_ks, self.group_ks)))
        # (a memo shared with copies of other factors, `with_scales`, holds their systems too: only those
        # kept for this part's own key are taken)
        keep = [(k, v[1]) for k, v in other.memo.items()
                if v[0] == self._versions() and k == self._tree_key(HaarTree(*k[:2]))]
        if not same_rows or not keep:
            return None
        same_b = np.all(other.b == self.b, axis=1)
        both = same_b & (other.w > 0) & (self.w > 0)
        if not both.any():
            return None
        s = float(np.median(self.w[both] / other.w[both]))
        index = np.flatnonzero(~same_b | (np.abs(self.w - s * other.w) > 1e-12 * np.abs(self.w)))
        if len(index) > ADOPT_SHARE * self.n_rows:
            return None
        other.memo = OrderedDict()
        kd = self.kd[index] if np.ndim(self.kd) == 2 else self.kd
        group = None if self.group is None else self.group[index]

        def rows_part(w, b):
            return RowsPart(Pyramid(np.ascontiguousarray(self.D.rows[index]), self.D.tile_sizes),
                            None if self.S is None else Pyramid(np.ascontiguousarray(self.S.rows[index]),
                                                                self.D.tile_sizes),
                            kd, self.ks, b, w, 0, self.precision, group=group, group_scales=self.group_scales,
                            split_specular=self.split_specular, group_ks=self.group_ks)

        new, old = rows_part(self.w[index], self.b[index]), rows_part(s * other.w[index], other.b[index])

        def moved(v, a, c):  # s v + (the changed rows' new sums - their old ones)
            out = v * v.dtype.type(s)
            if a is not None:
                out += a - c
            return out

        memo = OrderedDict()
        keep.reverse()
        while keep:  # (tree by tree, each old system and the changed rows' ones let go once used: memory)
            key, entry = keep.pop()
            tree = HaarTree(*key[:2])
            a, c = (new._tree_entry(tree), old._tree_entry(tree)) if len(index) else (None, None)
            new.memo.clear(), old.memo.clear()
            if isinstance(entry, dict):  # per part: pieces linear in the weights, bb included
                entry = {q: {k: None if v is None else moved(v, None if a is None or q not in a else a[q][k],
                                                            None if c is None or q not in c else c[q][k])
                             for k, v in e.items()} for q, e in entry.items()}
            else:
                entry = SystemPart(moved(entry.G, None if a is None else a.G, None if c is None else c.G),
                                   moved(entry.h, None if a is None else a.h, None if c is None else c.h),
                                   self.bb, self.n_pixels, entry.channel_scale)
            memo[key] = (self._versions(), entry)
        self.memo = memo
        return int(len(index))

    def in_single(self) -> "RowsPart":
        """These rows with their systems accumulated in float32 (`precision`; a memo of their own): what
        the final light of a chosen tree is solved on (`bases.tree.finish`: half the time of float64,
        a light that explains the rows as float64's does). Its errors are measured on the rows, not from the float32 Gram matrix, whose
        L'GL - 2h'L + b'b cancels."""
        from dataclasses import replace

        return self if self.precision == "single" else replace(self, precision="single", memo=OrderedDict())

    def head(self, n: int, precision: str | None = None) -> "RowsPart":
        """The first n rows, standing for the same pixels (weights scaled up): a smaller sample when
        the rows are ordered so that every prefix is spread like the whole (`sampling.fit_sample`)."""
        n = min(int(n), self.n_rows)
        factor = self.w.sum() / max(self.w[:n].sum(), 1e-300)
        kd = self.kd[:n] if np.ndim(self.kd) == 2 else self.kd
        return RowsPart(self.D.head(n), None if self.S is None else self.S.head(n), kd, self.ks, self.b[:n],
                        self.w[:n] * factor, self.n_pixels, precision or self.precision,
                        group=None if self.group is None else self.group[:n], group_scales=self.group_scales,
                        split_specular=self.split_specular, group_ks=self.group_ks)

    def tail(self, n: int, precision: str | None = None) -> "RowsPart":
        """The rows from n on, each standing for what it stood for here (the weights as they are)."""
        n = min(int(n), self.n_rows)
        kd = self.kd[n:] if np.ndim(self.kd) == 2 else self.kd
        return RowsPart(self.D.tail(n), None if self.S is None else self.S.tail(n), kd, self.ks, self.b[n:],
                        self.w[n:], self.n_rows - n, precision or self.precision,
                        group=None if self.group is None else self.group[n:], group_scales=self.group_scales,
                        split_specular=self.split_specular, group_ks=self.group_ks)

    def head_factor(self, head: "RowsPart") -> float | None:
        """f when `head` is this part's `head(n)` (its first n rows, each weight f times this one's,
        the same material and targets), else None."""
        n = head.n_rows if isinstance(head, RowsPart) else 0
        if not n or n > self.n_rows or self.group is not None or head.group is not None \
                or (self.S is None) != (head.S is None) or head._versions() != self._versions():
            return None
        for mine, theirs in ((self.D, head.D), (self.S, head.S)):
            if mine is not None and (theirs.rows.__array_interface__["data"][0] != mine.rows.__array_interface__["data"][0]
                                     or theirs.rows.strides != mine.rows.strides):
                return None
        w = self.w[:n]
        f = float(head.w.sum() / max(w.sum(), 1e-300))
        if not (np.array_equal(head.b, self.b[:n]) and np.array_equal(head.kd_eff, self.kd_eff if np.ndim(self.kd) < 2
                                                                    else self.kd_eff[:n])
                and np.array_equal(head.ks, self.ks) and np.allclose(head.w, w * f, rtol=1e-12, atol=0)):
            return None
        return f

    def project(self, P) -> SystemPart:
        """The system in coefficients c of light = P c (P dense or sparse, (N, k))."""
        if not hasattr(P, "toarray"):
            P = np.asarray(P, dtype=np.float32)  # a float64 P would make numpy copy the rows to float64

        def apply(rows):
            out = rows @ P
            return np.asarray(out.toarray() if hasattr(out, "toarray") else out, dtype=np.float64)

        return self._system(apply(self.D.rows), None if self.S is None else apply(self.S.rows))

    def select(self, texels: np.ndarray) -> SystemPart:
        sub = np.asarray(texels, np.int64)
        return self._system(self.D.rows[:, sub].astype(np.float64),
                            None if self.S is None else self.S.rows[:, sub].astype(np.float64))

    def predict(self, light: np.ndarray, support=None) -> np.ndarray:
        """(n, C) the rows' radiance under a texel light (N, C); `support`: its non-zero texels."""
        L = np.asarray(light, dtype=np.float64)
        sub = slice(None) if support is None else np.asarray(support, np.int64)
        D = self.D.rows[:, sub]
        out = np.atleast_2d(self.kd_eff) * (D @ L[sub].astype(np.float32)).astype(np.float64)
        if self.S is not None:
            out += np.atleast_2d(self.ks_eff) * (self.S.rows[:, sub] @ L[sub].astype(np.float32)).astype(np.float64)
        return out

    def residual(self, light: np.ndarray) -> np.ndarray:
        """(C,) weighted sum of squared residuals of a texel light."""
        r = self.predict(light) - self.b
        return (self.w[:, None] * r**2).sum(axis=0)

    def relative_rmse(self, light: np.ndarray) -> float:
        return float(np.sqrt(self.residual(light).sum() / max(self.bb.sum(), 1e-300)))

    def gradient(self, light: np.ndarray, support=None) -> np.ndarray:
        """(N, C) T'W(b - T L) at a texel light (`support`: its non-zero texels)."""
        r = (self.w[:, None] * (self.b - self.predict(light, support)))
        kd = self.kd_eff
        if kd.ndim == 2:  # per row: T_c' r_c = D' (kd_c r_c)
            out = (self.D.rows.T @ (kd * r).astype(np.float32)).astype(np.float64)
        else:
            out = kd[None, :] * (self.D.rows.T @ r.astype(np.float32)).astype(np.float64)
        if self.S is not None:
            ks = self.ks_eff
            if ks.ndim == 2:
                out += (self.S.rows.T @ (ks * r).astype(np.float32)).astype(np.float64)
            else:
                out += ks[None, :] * (self.S.rows.T @ r.astype(np.float32)).astype(np.float64)
        return out

    def channel_diag(self) -> np.ndarray:
        """(C, N) sum_j w_j T_c,ij^2: the squared transport each texel gets, per channel."""
        N = self.D.rows.shape[1]
        C = np.shape(self.kd)[-1]
        scale = self.channel_scale
        ref = int(np.argmax(self.kd_eff + np.asarray(self.ks))) if scale is not None else 0
        channels = [ref] if scale is not None else range(C)
        w = self.w.astype(np.float32)
        b = 256
        starts = list(range(0, self.n_rows, b))
        partial = {}

        def run(mine):  # per thread: its blocks' sums, on its own scratch
            acc = np.zeros((C, N))
            T = np.empty((b, N), np.float32)
            for a in mine:
                sl = slice(a, min(self.n_rows, a + b))
                t = T[: sl.stop - sl.start]
                for c in channels:
                    kd_c = self._kd(c)
                    np.multiply(self.D.rows[sl], (kd_c[sl] if kd_c.ndim else kd_c).astype(np.float32), out=t)
                    if self.S is not None and self.ks[c] != 0:
                        ks_c = self._ks(c)
                        t += self.S.rows[sl] * (ks_c[sl] if ks_c.ndim else ks_c).astype(np.float32)
                    t *= t
                    acc[c] += w[sl] @ t
            partial[mine[0] if mine else -1] = acc

        parallel_blocks(run, starts)
        out = sum(partial.values()) if partial else np.zeros((C, N))
        if scale is not None:
            out = scale[:, None] ** 2 * out[ref][None, :]
        return out

    def diag(self, channels: str = "max") -> np.ndarray:
        """(N,) the squared transport each texel gets: the channels' max or mean."""
        per = self.channel_diag()
        return per.max(axis=0) if channels == "max" else per.mean(axis=0)

    def combine(self, other) -> "UnionPart":
        return UnionPart((self, other))


@dataclass
class UnionPart:
    """The union of parts (e.g. the fit sample and the held-out pixels): every quantity is the sum."""

    parts: tuple

    @property
    def n_pixels(self) -> int:
        return sum(p.n_pixels for p in self.parts)

    @property
    def bb(self) -> np.ndarray:
        return sum(p.bb for p in self.parts)

    def _sum(self, systems) -> SystemPart:
        out = None
        for s in systems:
            out = s if out is None else out.combine(s)
        return out

    def project_tree(self, tree):
        return self._sum(p.project_tree(tree) for p in self.parts)

    def project(self, P):
        return self._sum(p.project(P) for p in self.parts)

    def select(self, texels):
        return self._sum(p.select(texels) for p in self.parts)

    def residual(self, light):
        return sum(p.residual(light) for p in self.parts)

    def relative_rmse(self, light) -> float:
        return float(np.sqrt(self.residual(light).sum() / max(self.bb.sum(), 1e-300)))

    def gradient(self, light, support=None):
        return sum(p.gradient(light, support) for p in self.parts)

    def channel_diag(self) -> np.ndarray:
        return sum(p.channel_diag() for p in self.parts)

    def diag(self, channels: str = "max"):
        per = self.channel_diag()
        return per.max(axis=0) if channels == "max" else per.mean(axis=0)

    def combine(self, other):
        return UnionPart(self.parts + (other,))

    def in_single(self) -> "UnionPart":
        return UnionPart(tuple(p.in_single() if hasattr(p, "in_single") else p for p in self.parts))

    def with_scales(self, scales, ks_scales=None):
        return UnionPart(tuple(p.with_scales(scales, ks_scales) for p in self.parts))


@dataclass
class ScaledPart:
    """`part` with every weight divided by `divisor`: an exploration's head (`RowsPart.head`, its
    weights scaled up to stand for all of the fit rows) standing for its own rows again, so that its
    memoised tree systems serve the final solve (`all_rows`)."""

    part: RowsPart
    divisor: float
    n_pixels: int

    @property
    def bb(self) -> np.ndarray:
        return self.part.bb / self.divisor

    def project_tree(self, tree) -> SystemPart:
        s = self.part.project_tree(tree)
        return SystemPart(s.G / self.divisor, s.h / self.divisor, s.bb / self.divisor, self.n_pixels, s.channel_scale)

    def residual(self, light) -> np.ndarray:
        return self.part.residual(light) / self.divisor

    def relative_rmse(self, light) -> float:
        return float(np.sqrt(self.residual(light).sum() / max(self.bb.sum(), 1e-300)))


def all_rows(fit, held_out, explore=None):
    """Every row of a sampled system (the fit and the held-out ones) in single precision: what the
    final light of a chosen tree is solved on (`bases.tree.finish`). When `explore` is the fit rows'
    single-precision head (`LightSystem.explore`), its rows come from it: the tree systems it
    memoised while the levels were explored (corrected in place after a recast) are reused, and only
    the other rows are projected (at the defaults 13,000 of 21,000 rows). The same sums as projecting
    all rows afresh, added in another order (float32 rounding)."""
    both = fit.combine(held_out)
    both = both.in_single() if hasattr(both, "in_single") else both
    if not (isinstance(fit, RowsPart) and isinstance(explore, RowsPart) and explore.precision == "single"):
        return both
    f = fit.head_factor(explore)
    if f is None:
        return both
    parts = [ScaledPart(explore, f, fit.n_pixels)]
    if explore.n_rows < fit.n_rows:
        parts.append(fit.tail(explore.n_rows, "single"))
    held = held_out.in_single() if hasattr(held_out, "in_single") else held_out
    return UnionPart(tuple(parts) + ((held,) if held.n_pixels > 0 else ()))


def lobe_pieces(part, tree: HaarTree) -> dict | None:
    """The leaf-space pieces of a uniform glossy material's rows on `tree`, for the ratio t_c =
    ks / kd_c of each channel c: with the light absorbing kd_c (it is only known as kd_c L_c),
    channel c renders kd_c (D + t_c S) L_c, and its normal equations are G(t) = DD + t (X + X') +
    t^2 SS, h_c(t) = hD_c + t hS_c (weights sqrt(w) applied), with bb_c the targets' squared sum.
    `part`: a `RowsPart` or a `UnionPart` of them (summed). None when a part has no specular
    transport or is not uniform (a per-row kd: textures; rows grouped by part; a specular weight
    per row): those have their own factors (`model.parts`)."""
    parts = part.parts if isinstance(part, UnionPart) else (part,)
    out = None
    for p in parts:
        if not isinstance(p, RowsPart) or p.S is None or np.ndim(p.kd) == 2 or p.group is not None:
            return None
        dtype = np.float64 if p.precision == "double" else np.float32
        sw = np.sqrt(p.w)
        base = p.D.leaf_sums(tree).astype(dtype)
        base *= sw.astype(dtype)[:, None]
        lobe = p.S.leaf_sums(tree).astype(dtype)
        lobe *= sw.astype(dtype)[:, None]
        b = p.b * sw[:, None]
        C = b.shape[1]
        piece = {"DD": _gram(base), "X": (base.T @ lobe).astype(np.float64), "SS": _gram(lobe),
                 "hD": np.column_stack([_rhs(base, b[:, c]) for c in range(C)]),
                 "hS": np.column_stack([_rhs(lobe, b[:, c]) for c in range(C)]), "bb": np.asarray(p.bb, np.float64)}
        out = piece if out is None else {k: out[k] + piece[k] for k in out}
    return out


def with_scales(system, scales: np.ndarray, ks_scales: np.ndarray | None = None):
    """A sampled `LightSystem` of rows grouped by part with other part factors (and specular weights,
    `RowsPart.group_ks`) (its tree systems kept)."""
    from .system import LightSystem

    return LightSystem(system.fit.with_scales(scales, ks_scales), system.held_out.with_scales(scales, ks_scales),
                       system.seconds,
                       None if system.explore is None else system.explore.with_scales(scales, ks_scales))


class TransportRows:
    """The transport of some used pixels (rows of a visibility), built once per material.

    The diffuse transport D is built once (a `plastic` base's once per coating); the specular one S
    once per lobe (model, shininess or roughness, IOR, distribution). Only the
    stored visibility rows (bit-packed) and the rows' geometry are kept to rebuild S.

    Memory: the transports of one material are kept at a time (`part` drops the others' first:
    `keep_only`), so that auto's candidates (a Lambertian D, a Phong S, a plastic's coated D and S)
    are not all held at once; a system built before still holds its own, and `update` (a recast's
    new visibility) rebuilds the rows of every transport still held anywhere.
    """

    def __init__(self, vis, rows: np.ndarray):
        from ..geometry.visibility import VisibilityData

        rows = np.asarray(rows, np.int64)
        sub = vis.samples.take(rows)
        self.vis = VisibilityData(sub, vis.cube, vis.supersample, np.asarray(vis.stored)[rows],
                                  castable_only=vis.castable_only)
        self.rows = rows
        self._diffuse: Pyramid | None = None
        self._coated: tuple | None = None  # (plastic key, D seen through the coating, the material)
        self._specular: dict = {}  # lobe key -> (S, the unit material)
        self._built: list = []  # (weak reference, material, kind, specular weight) per transport built: `pyramids`
        self.specular_weight: np.ndarray | None = None  # (rows,) 0 where the pixel's part is matte

    def set_specular(self, weight: np.ndarray | None) -> None:
        """Which rows have the specular term ((rows,) 1 or 0; None: all): the rows of matte parts get
        no lobe and, under `plastic`, no coating (`render.matte_rows`; another weight multiplies the
        row's lobe). The kept specular and coated transports are dropped (built again under the new
        weights)."""
        w = None if weight is None else np.asarray(weight, np.float32)
        if w is not None and np.all(w == 1):
            w = None
        if w is None and self.specular_weight is None:
            return
        self.specular_weight = w
        self._coated = None
        self._specular = {}

    def _matte(self, D, S, V, index, material, weight=_CURRENT) -> None:
        """`render.matte_rows` for rows `index` (into these rows) whose new transports are D and S,
        under the rows' specular weights (`weight`: those a transport was built with; default the
        rows' current ones)."""
        from ..model.render import matte_rows

        weight = self.specular_weight if weight is _CURRENT else weight
        if weight is not None:
            matte_rows(D, S, V, self.vis.samples.normal[index], self.vis.cube, material, weight[index])

    def _built_one(self, pyramid: Pyramid, material, kind: str) -> Pyramid:
        self._built = [b for b in self._built if b[0]() is not None] + [
            (weakref.ref(pyramid), material, kind, self.specular_weight)]
        return pyramid

    def pyramids(self) -> list:
        """(pyramid, the material it was built with: None for the Lambertian D, kind, the rows'
        specular weights then) of every transport still held (here, or by a system built on it):
        what `update` rebuilds rows of."""
        out = []
        for ref, material, kind, weight in self._built:
            pyramid = ref()
            if pyramid is not None:
                out.append((pyramid, material, kind, weight))
        return out

    def keep_only(self, material) -> None:
        """Drop the kept transports that `material` does not use (the Lambertian D under `plastic`,
        another coating's D, another lobe's S): once the model is chosen they only hold memory (and
        are built again if asked for)."""
        from ..model.materials import PLASTIC

        if material.model == PLASTIC:
            self._diffuse = None
        key = (material.roughness, material.ior, material.distribution)
        if self._coated is not None and (material.model != PLASTIC or self._coated[0] != key):
            self._coated = None
        lobe = (material.model, material.shininess, material.roughness, material.ior, material.distribution)
        self._specular = {k: v for k, v in self._specular.items() if material.specular and tuple(k[:-1]) == lobe}

    def release_lobe(self) -> None:
        """Drop the kept specular and coated transports (a reflectance fit follows: the next light's
        lobe is another one, built again; the Lambertian D stays, every round's base)."""
        self._coated = None
        self._specular = {}

    def diffuse_shading(self, light: np.ndarray) -> np.ndarray:
        """(rows, 3) float64 the Lambertian D (kd = 1) times `light` ((N,) or (N, 3)): from the kept D
        if there is one, else in blocks, not kept (under another material it would only hold memory)."""
        from ..model.materials import Material
        from ..model.render import render

        L = np.asarray(light, np.float32)
        if L.ndim == 1:
            L = np.repeat(L[:, None], 3, axis=1)
        if self._diffuse is not None:
            return (self._diffuse.rows @ L).astype(np.float64)
        return render(self.vis, L, Material(kd=(1.0, 1.0, 1.0)))

    def update(self, stored: np.ndarray, index: np.ndarray) -> None:
        """New visibility for some of these rows (`index` into them; `stored` their new stored
        rows): the kept transports are rebuilt for those rows alone, in place."""
        from ..geometry.visibility import decode
        from ..model.microfacet import samples_footprint
        from ..model.render import diffuse_transport, specular_transport

        index = np.asarray(index, np.int64)
        if not len(index):
            return
        v = self.vis
        v.stored[index] = stored
        V = decode(np.asarray(stored), v.cube.n_texels, v.encoding, True)
        normal, view = v.samples.normal[index], v.samples.view[index]
        for pyramid, material, kind, weight in self.pyramids():
            sel = np.flatnonzero(index < len(pyramid.rows))  # a specular S may cover a head only
            if not len(sel):
                continue
            if kind == "diffuse":
                new = diffuse_transport(V[sel], normal[sel], v.cube, material, view[sel])
                if material is not None:  # (a coated D: the matte rows' plain)
                    self._matte(new, None, V[sel], index[sel], material, weight)
            else:
                new = specular_transport(V[sel], normal[sel], view[sel], v.cube, material,
                                         footprint=samples_footprint(v.samples, index[sel], material))
                self._matte(None, new, V[sel], index[sel], material, weight)
            pyramid.set_rows(index[sel], new)

    def diffuse(self, material=None, n_rows: int | None = None) -> Pyramid:
        """D (kd = 1) under `material`: the Lambertian one (kept, every row) for every model but
        `plastic`, whose base is seen through its coating: that D is built for the first `n_rows` rows
        (all by default: a specular round's smaller system needs its head alone) and the latest one is
        kept, serving fewer rows of the same coating as its head."""
        from ..model.materials import PLASTIC

        plastic = material is not None and material.model == PLASTIC
        if not plastic:
            if self._diffuse is None:
                self._diffuse = self._built_one(self._diffuse_rows(None, self.vis.n_pixels), None, "diffuse")
            return self._diffuse
        n = self.vis.n_pixels if n_rows is None else min(int(n_rows), self.vis.n_pixels)
        key = (material.roughness, material.ior, material.distribution)
        if self._coated is not None and self._coated[0] == key and len(self._coated[1].rows) >= n:
            kept = self._coated[1]
            return kept if len(kept.rows) == n else kept.head(n)
        self._coated = None  # (the coating before: its memory goes before the new one is built)
        pyramid = self._built_one(self._diffuse_rows(material, n), material, "diffuse")
        self._coated = (key, pyramid, material)
        return pyramid

    def _diffuse_rows(self, material, n: int) -> Pyramid:
        """D of the first n rows (`render.diffuse_transport`; material None: Lambertian)."""
        from ..model.render import diffuse_transport

        v = self.vis
        D = np.empty((n, v.cube.n_texels), np.float32)
        for sl, V in v.blocks(8192, raw=True):
            if sl.start >= n:
                break
            sl = slice(sl.start, min(sl.stop, n))
            diffuse_transport(V[: sl.stop - sl.start], v.samples.normal[sl], v.cube, material, v.samples.view[sl],
                              out=D[sl])
            if material is not None:  # (a coated D: the matte parts' rows plain)
                self._matte(D[sl], None, V[: sl.stop - sl.start], np.arange(sl.start, sl.stop), material)
        return Pyramid(D, v.cube.tile_sizes)

    def specular(self, material, n_rows: int | None = None) -> Pyramid:
        """S (ks = 1) of `material`'s lobe for the first `n_rows` rows (all by default); the latest one
        is kept (memory), and serves fewer rows of the same lobe as its head."""
        from dataclasses import replace

        n = self.vis.n_pixels if n_rows is None else min(int(n_rows), self.vis.n_pixels)
        unit = replace(material, kd=(1.0, 1.0, 1.0), ks=(1.0, 1.0, 1.0), extra={})
        lobe = (unit.model, unit.shininess, unit.roughness, unit.ior, unit.distribution)
        key = lobe + (n,)
        for (*kept_lobe, kept_n), (pyramid, _) in self._specular.items():
            if tuple(kept_lobe) == lobe and kept_n > n:
                return pyramid.head(n)
        if key not in self._specular:
            from ..model.microfacet import samples_footprint
            from ..model.render import specular_transport

            self._specular = {}  # (the lobe before: its memory goes before the new one is built)
            S = np.empty((n, self.vis.cube.n_texels), np.float32)
            for sl, V in self.vis.blocks(8192, raw=True):
                if sl.start >= n:
                    break
                sl = slice(sl.start, min(sl.stop, n))
                specular_transport(V[: sl.stop - sl.start], self.vis.samples.normal[sl], self.vis.samples.view[sl],
                                   self.vis.cube, unit, out=S[sl], footprint=samples_footprint(self.vis.samples, sl, unit))
                self._matte(None, S[sl], V[: sl.stop - sl.start], np.arange(sl.start, sl.stop), unit)
            self._specular = {key: (self._built_one(Pyramid(S, self.vis.cube.tile_sizes), unit, "specular"), unit)}
        return self._specular[key][0]

    def part(self, material, photo: np.ndarray, weights: np.ndarray, n_pixels: int,
             n_rows: int | None = None, albedo: np.ndarray | None = None, group: np.ndarray | None = None,
             scales: np.ndarray | None = None, split_specular: bool = True,
             ks_scales: np.ndarray | None = None) -> RowsPart:
        """The rows' system under `material` against `photo` ((n, C) values of these rows); with
        `n_rows`, of the first n_rows rows only, standing for the same pixels (weights scaled up, as
        `RowsPart.head`): a specular round's smaller system builds S for those rows alone. `albedo`:
        (rows, 3) the rows' relative albedo (kd per row = material.kd x albedo), None: uniform; with
        `group` (rows,) and `scales` (parts, 3) it is each part's known albedo at factor 1, and the
        rows render with albedo x scales[group] (`RowsPart.group`)."""
        n = self.vis.n_pixels if n_rows is None else min(int(n_rows), self.vis.n_pixels)
        w = np.asarray(weights, np.float64)
        self.keep_only(material)  # (another material's transports go before this one's are built)
        D = self.diffuse(material, n)
        D = D if len(D.rows) == n else D.head(n)
        S = self.specular(material, n) if material.specular else None
        kd = np.asarray(material.kd, float)
        if albedo is not None:
            kd = kd[None, :] * np.asarray(albedo, float)[:n]
        return RowsPart(D, S, kd, np.asarray(material.ks, float),
                        np.asarray(photo, np.float64)[:n], w[:n] * (w.sum() / max(w[:n].sum(), 1e-300)), int(n_pixels),
                        group=None if group is None else np.asarray(group, np.int64)[:n],
                        group_scales=None if scales is None else np.array(scales, np.float64),
                        split_specular=split_specular, group_ks=None if ks_scales is None else np.array(ks_scales, float))
