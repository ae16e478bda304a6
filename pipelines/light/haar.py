"""Adaptive 2-D Haar wavelet bases on the square tiles of a cube map.

Each tile (a cube-map face or half-face, side a power of two) carries a Haar
quadtree, following Upright et al., "Wavelet-based light reconstruction from a
single image". The root node covers the whole tile and carries the scaling
function; every subdivided node carries three wavelets (horizontal, vertical,
diagonal) that split it into its four children. The basis functions of any
tree are therefore a subset of the complete Haar basis of the tile, which is
what lets every transform here run through one fast full-resolution pyramid.

Node ids are ``(level, i, j)``: a node at ``level`` of a tile of side ``size``
has side ``s = size >> level`` and covers rows ``i*s .. (i+1)*s - 1`` and
columns ``j*s .. (j+1)*s - 1``. Texels are ordered tile by tile, row-major
inside a tile. Orthonormality is with respect to the plain texel inner product
(sum over texels, unit weight).
"""

from __future__ import annotations

import operator
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

__all__ = [
    "HaarTree",
    "analyse",
    "basis_matrix",
    "coefficients_to_leaf_values",
    "leaf_matrix",
    "leaf_values_to_coefficients",
    "prune",
    "subdivide",
    "synthesise",
    "tree_depth_image",
]

NodeId = tuple[int, int, int]

# Kinds of coefficient, in their storage order within a node.
WAVELET_KINDS = ("h", "v", "d")


def _log2_exact(size: int) -> int:
    return size.bit_length() - 1


def _node_keys(nodes: np.ndarray) -> np.ndarray:
    """Breadth-first heap index of each node (shape (n, 3) -> (n,)).

    Levels occupy consecutive key ranges and nodes within a level are
    row-major, so sorting by key is sorting by ``(level, i, j)``.
    """
    level, i, j = nodes[:, 0], nodes[:, 1], nodes[:, 2]
    return ((1 << (2 * level)) - 1) // 3 + (i << level) + j


def _children(nodes: np.ndarray) -> np.ndarray:
    """All four children of each node, shape (n, 3) -> (4n, 3)."""
    offsets = np.array([[1, 0, 0], [1, 0, 1], [1, 1, 0], [1, 1, 1]], dtype=np.int64)
    doubled = nodes * np.array([1, 2, 2], dtype=np.int64)
    return (doubled[:, None, :] + offsets[None, :, :]).reshape(-1, 3)


def _sorted_node_array(nodes: Iterable[NodeId]) -> np.ndarray:
    """Node ids as an int64 array of shape (n, 3) sorted by (level, i, j)."""
    return np.array(sorted(nodes), dtype=np.int64).reshape(-1, 3)


@dataclass(frozen=True)
class HaarTree:
    """Per-tile Haar quadtrees over a list of square tiles.

    Parameters
    ----------
    tile_sizes : sequence of int, length T
        Side length of each tile, each a power of two.
    subdivided : sequence of iterables of (level, i, j), length T
        For each tile, the ids of its subdivided nodes. Every subdivided node
        other than a root must have a subdivided parent, and single-texel
        nodes cannot be subdivided.

    Raises
    ------
    ValueError
        If a size is not a power of two, the number of node sets does not
        match the number of tiles, a node lies outside its tile, a
        single-texel node is subdivided or a node's parent is not subdivided.
    """

    tile_sizes: tuple[int, ...]
    subdivided: tuple[frozenset[NodeId], ...]

    def __post_init__(self) -> None:
        sizes = tuple(int(s) for s in self.tile_sizes)
        for t, size in enumerate(sizes):
            if size < 1 or size & (size - 1):
                raise ValueError(
                    f"tile size {size} (tile {t}) is not a power of two"
                )
        subdivided = tuple(
            frozenset(_as_node_id(node) for node in nodes)
            for nodes in self.subdivided
        )
        if len(subdivided) != len(sizes):
            raise ValueError(
                f"subdivided has {len(subdivided)} node sets but there are "
                f"{len(sizes)} tiles"
            )
        for t, (size, nodes) in enumerate(zip(sizes, subdivided)):
            _validate_tile_nodes(t, size, nodes)
        # Frozen dataclass: normalised values must bypass __setattr__.
        object.__setattr__(self, "tile_sizes", sizes)
        object.__setattr__(self, "subdivided", subdivided)

    @classmethod
    def roots(cls, tile_sizes: Sequence[int]) -> HaarTree:
        """Tree with nothing subdivided (one scaling function per tile)."""
        return cls(tuple(tile_sizes), tuple(frozenset() for _ in tile_sizes))

    @classmethod
    def full(cls, tile_sizes: Sequence[int], depth: int | None = None) -> HaarTree:
        """Tree subdivided uniformly ``depth`` levels below each root.

        Parameters
        ----------
        tile_sizes : sequence of int, length T
        depth : int or None
            Number of subdivided levels per tile, clamped to each tile's
            maximum ``log2(size)``. None subdivides down to single texels.
        """
        if depth is not None and depth < 0:
            raise ValueError(f"depth must be non-negative, got {depth}")
        subdivided = []
        for size in tile_sizes:
            # Invalid sizes are reported by the constructor; only avoid a
            # negative range here.
            max_depth = max(_log2_exact(int(size)), 0)
            levels = max_depth if depth is None else min(depth, max_depth)
            subdivided.append(
                frozenset(
                    (level, i, j)
                    for level in range(levels)
                    for i in range(1 << level)
                    for j in range(1 << level)
                )
            )
        return cls(tuple(tile_sizes), tuple(subdivided))

    @property
    def n_tiles(self) -> int:
        """Number of tiles."""
        return len(self.tile_sizes)

    @property
    def n_texels(self) -> int:
        """Total number of texels over all tiles."""
        return sum(size * size for size in self.tile_sizes)

    @property
    def n_coefficients(self) -> int:
        """One scaling function per tile plus three wavelets per subdivided node."""
        return self.n_tiles + 3 * sum(len(nodes) for nodes in self.subdivided)

    @property
    def n_leaves(self) -> int:
        """Number of leaves; each subdivision turns one leaf into four."""
        return self.n_coefficients

    def leaves(self) -> list[tuple[int, int, int, int]]:
        """Leaf nodes as (tile, level, i, j), per tile sorted by (level, i, j)."""
        return [
            (t, int(level), int(i), int(j))
            for t, nodes in enumerate(_leaf_nodes(self))
            for level, i, j in nodes
        ]

    def coefficient_index(self) -> list[tuple[int, str, int, int, int]]:
        """Description of each coefficient as (tile, kind, level, i, j).

        Per tile: the scaling function (kind ``'scaling'``, node (0, 0, 0))
        first, then the subdivided nodes sorted by (level, i, j), each
        contributing its wavelets in the order ``'h'``, ``'v'``, ``'d'``.
        """
        index: list[tuple[int, str, int, int, int]] = []
        for t, nodes in enumerate(_subdivided_nodes(self)):
            index.append((t, "scaling", 0, 0, 0))
            for level, i, j in nodes:
                for kind in WAVELET_KINDS:
                    index.append((t, kind, int(level), int(i), int(j)))
        return index


def _as_node_id(node: object) -> NodeId:
    try:
        level, i, j = (operator.index(v) for v in node)
    except (TypeError, ValueError):
        raise ValueError(
            f"node ids must be (level, i, j) integer triples, got {node!r}"
        ) from None
    return (level, i, j)


def _validate_tile_nodes(tile: int, size: int, nodes: frozenset[NodeId]) -> None:
    if not nodes:
        return
    arr = _sorted_node_array(nodes)
    level, i, j = arr[:, 0], arr[:, 1], arr[:, 2]
    max_level = _log2_exact(size)
    outside = (level < 0) | (level > max_level)
    outside |= (i < 0) | (j < 0)
    # Clip the shift so out-of-range levels cannot overflow before masking.
    extent = np.left_shift(1, np.clip(level, 0, max_level))
    outside |= (i >= extent) | (j >= extent)
    if outside.any():
        node = tuple(int(v) for v in arr[np.argmax(outside)])
        raise ValueError(f"node {node} lies outside tile {tile} of size {size}")
    single = level == max_level
    if single.any():
        node = tuple(int(v) for v in arr[np.argmax(single)])
        raise ValueError(
            f"node {node} of tile {tile} is a single texel and cannot be subdivided"
        )
    non_root = arr[level > 0]
    parents = np.stack(
        [non_root[:, 0] - 1, non_root[:, 1] >> 1, non_root[:, 2] >> 1], axis=1
    )
    orphan = ~np.isin(_node_keys(parents), _node_keys(arr))
    if orphan.any():
        node = tuple(int(v) for v in non_root[np.argmax(orphan)])
        parent = tuple(int(v) for v in parents[np.argmax(orphan)])
        raise ValueError(
            f"orphan node {node} in tile {tile}: its parent {parent} is not subdivided"
        )


def _subdivided_nodes(tree: HaarTree) -> list[np.ndarray]:
    """Per tile, the subdivided nodes as (n_t, 3) arrays sorted by (level, i, j)."""
    return [_sorted_node_array(nodes) for nodes in tree.subdivided]


def _leaf_nodes(tree: HaarTree) -> list[np.ndarray]:
    """Per tile, the leaf nodes as (m_t, 3) arrays sorted by (level, i, j)."""
    leaves = []
    for nodes in _subdivided_nodes(tree):
        if len(nodes) == 0:
            leaves.append(np.zeros((1, 3), dtype=np.int64))
            continue
        children = _children(nodes)
        children = children[~np.isin(_node_keys(children), _node_keys(nodes))]
        leaves.append(children[np.argsort(_node_keys(children))])
    return leaves


def _texel_offsets(tile_sizes: Sequence[int]) -> np.ndarray:
    """Index of each tile's first texel, shape (T + 1,) ending with the total."""
    return np.concatenate([[0], np.cumsum([s * s for s in tile_sizes])]).astype(
        np.int64
    )


def _coefficient_positions(tree: HaarTree) -> np.ndarray:
    """Position of each tree coefficient in the full-tree coefficient vector.

    The full tree of a tile has exactly size**2 coefficients, so full-tree
    coefficients share the texel offsets. Returns an increasing int array of
    shape (n_coefficients,).
    """
    offsets = _texel_offsets(tree.tile_sizes)
    positions = []
    for t, nodes in enumerate(_subdivided_nodes(tree)):
        wavelets = 1 + 3 * _node_keys(nodes)[:, None] + np.arange(3)
        positions.append([offsets[t]])
        positions.append(offsets[t] + wavelets.ravel())
    return np.concatenate(positions).astype(np.int64)


def _as_columns(values: np.ndarray, n_rows: int, name: str) -> np.ndarray:
    """View ``values`` ((n,) or (n, C)) as a float (n, C) array, checking n."""
    arr = np.asarray(values, dtype=float)
    if arr.ndim not in (1, 2):
        raise ValueError(f"{name} must be 1-D or 2-D, got shape {arr.shape}")
    if arr.shape[0] != n_rows:
        raise ValueError(f"{name} has {arr.shape[0]} rows, expected {n_rows}")
    return arr.reshape(n_rows, -1)


def _restore_shape(columns: np.ndarray, like: np.ndarray) -> np.ndarray:
    return columns[:, 0] if np.ndim(like) == 1 else columns


def _forward_tile(image: np.ndarray) -> np.ndarray:
    """Complete orthonormal 2-D Haar transform of one tile.

    Parameters
    ----------
    image : ndarray, shape (size, size, C)

    Returns
    -------
    ndarray, shape (size**2, C)
        Scaling coefficient, then per level from coarse to fine the nodes in
        row-major order with their (h, v, d) wavelets.
    """
    # ``a`` holds each node's texel sum divided by its side, i.e. its
    # projection on the node's normalised box function.
    a = image
    channels = image.shape[-1]
    details = []
    while a.shape[0] > 1:
        m = a.shape[0] // 2
        q = a.reshape(m, 2, m, 2, channels)
        tl, tr = q[:, 0, :, 0], q[:, 0, :, 1]
        bl, br = q[:, 1, :, 0], q[:, 1, :, 1]
        h = 0.5 * ((tl + bl) - (tr + br))
        v = 0.5 * ((tl + tr) - (bl + br))
        d = 0.5 * ((tl + br) - (tr + bl))
        details.append(np.stack([h, v, d], axis=2).reshape(3 * m * m, channels))
        a = 0.5 * ((tl + tr) + (bl + br))
    return np.concatenate([a.reshape(1, channels)] + details[::-1])


def _inverse_tile(coefficients: np.ndarray, size: int) -> np.ndarray:
    """Inverse of :func:`_forward_tile`: (size**2, C) -> (size, size, C)."""
    channels = coefficients.shape[-1]
    a = coefficients[:1].reshape(1, 1, channels)
    start = 1
    m = 1
    while m < size:
        w = coefficients[start : start + 3 * m * m].reshape(m, m, 3, channels)
        h, v, d = w[:, :, 0], w[:, :, 1], w[:, :, 2]
        out = np.empty((m, 2, m, 2, channels))
        out[:, 0, :, 0] = 0.5 * (a + h + v + d)
        out[:, 0, :, 1] = 0.5 * (a - h + v - d)
        out[:, 1, :, 0] = 0.5 * (a + h - v - d)
        out[:, 1, :, 1] = 0.5 * (a - h - v + d)
        a = out.reshape(2 * m, 2 * m, channels)
        start += 3 * m * m
        m *= 2
    return a


def _forward_full(texels: np.ndarray, tile_sizes: Sequence[int]) -> np.ndarray:
    """Full-tree coefficients of (n_texels, C) texels, shape (n_texels, C)."""
    offsets = _texel_offsets(tile_sizes)
    out = np.empty_like(texels)
    for t, size in enumerate(tile_sizes):
        tile = texels[offsets[t] : offsets[t + 1]].reshape(size, size, -1)
        out[offsets[t] : offsets[t + 1]] = _forward_tile(tile)
    return out


def _inverse_full(coefficients: np.ndarray, tile_sizes: Sequence[int]) -> np.ndarray:
    """Texels (n_texels, C) from full-tree coefficients (n_texels, C)."""
    offsets = _texel_offsets(tile_sizes)
    out = np.empty_like(coefficients)
    for t, size in enumerate(tile_sizes):
        tile = _inverse_tile(coefficients[offsets[t] : offsets[t + 1]], size)
        out[offsets[t] : offsets[t + 1]] = tile.reshape(size * size, -1)
    return out


def analyse(texels: np.ndarray, tree: HaarTree) -> np.ndarray:
    """Project texels onto the tree's orthonormal basis (``B.T @ texels``).

    Parameters
    ----------
    texels : ndarray, shape (n_texels,) or (n_texels, C)
    tree : HaarTree

    Returns
    -------
    ndarray, shape (n_coefficients,) or (n_coefficients, C)
    """
    columns = _as_columns(texels, tree.n_texels, "texels")
    # Tree basis functions are a subset of the full basis, so projecting onto
    # them is selecting entries of the full transform.
    full = _forward_full(columns, tree.tile_sizes)
    return _restore_shape(full[_coefficient_positions(tree)], texels)


def synthesise(coefficients: np.ndarray, tree: HaarTree) -> np.ndarray:
    """Texels of a coefficient vector on the tree's basis (``B @ coefficients``).

    Parameters
    ----------
    coefficients : ndarray, shape (n_coefficients,) or (n_coefficients, C)
    tree : HaarTree

    Returns
    -------
    ndarray, shape (n_texels,) or (n_texels, C)
    """
    columns = _as_columns(coefficients, tree.n_coefficients, "coefficients")
    full = np.zeros((tree.n_texels, columns.shape[1]))
    full[_coefficient_positions(tree)] = columns
    return _restore_shape(_inverse_full(full, tree.tile_sizes), coefficients)


def basis_matrix(tree: HaarTree) -> sp.csc_matrix:
    """Orthonormal Haar basis of the tree as explicit texel vectors.

    Built directly from the box and sign patterns, independently of the fast
    pyramid used by :func:`analyse` and :func:`synthesise`.

    Parameters
    ----------
    tree : HaarTree

    Returns
    -------
    scipy.sparse.csc_matrix, shape (n_texels, n_coefficients)
        Column k is the basis function described by
        ``tree.coefficient_index()[k]``.
    """
    texel_offsets = _texel_offsets(tree.tile_sizes)
    rows, cols, data = [], [], []
    column = 0
    for t, (size, nodes) in enumerate(zip(tree.tile_sizes, _subdivided_nodes(tree))):
        rows.append(texel_offsets[t] + np.arange(size * size))
        cols.append(np.full(size * size, column))
        data.append(np.full(size * size, 1.0 / size))
        first_wavelet = column + 1
        for level in np.unique(nodes[:, 0]):
            at_level = np.flatnonzero(nodes[:, 0] == level)
            side = size >> int(level)
            r, c = np.divmod(np.arange(side * side), side)
            left = np.where(c < side // 2, 1.0, -1.0)
            top = np.where(r < side // 2, 1.0, -1.0)
            i, j = nodes[at_level, 1:2], nodes[at_level, 2:3]
            texel = texel_offsets[t] + (i * side + r) * size + (j * side + c)
            for k, pattern in enumerate((left, top, left * top)):
                rows.append(texel.ravel())
                col = first_wavelet + 3 * at_level + k
                cols.append(np.repeat(col, side * side))
                data.append(np.tile(pattern / side, len(at_level)))
        column = first_wavelet + 3 * len(nodes)
    return sp.csc_matrix(
        (np.concatenate(data), (np.concatenate(rows), np.concatenate(cols))),
        shape=(tree.n_texels, tree.n_coefficients),
    )


def _texel_leaf_index(tree: HaarTree) -> tuple[np.ndarray, np.ndarray]:
    """Leaf (in ``tree.leaves()`` order) and leaf level of every texel.

    Returns
    -------
    leaf : ndarray of int, shape (n_texels,)
    depth : ndarray of int, shape (n_texels,)
    """
    leaf_parts, depth_parts = [], []
    leaf_offset = 0
    for size, nodes, leaves in zip(
        tree.tile_sizes, _subdivided_nodes(tree), _leaf_nodes(tree)
    ):
        max_level = _log2_exact(size)
        rows = np.arange(size)
        depth = np.zeros((size, size), dtype=np.int64)
        # Subdivided sets are closed under parents, so a texel's leaf level
        # is the number of its ancestors that are subdivided.
        for level in range(max_level):
            grid = np.zeros((1 << level, 1 << level), dtype=np.int64)
            at_level = nodes[nodes[:, 0] == level]
            grid[at_level[:, 1], at_level[:, 2]] = 1
            ancestor = rows >> (max_level - level)
            depth += grid[np.ix_(ancestor, ancestor)]
        shift = max_level - depth
        i = rows[:, None] >> shift
        j = rows[None, :] >> shift
        keys = _node_keys(np.stack([depth, i, j], axis=-1).reshape(-1, 3))
        leaf_parts.append(leaf_offset + np.searchsorted(_node_keys(leaves), keys))
        depth_parts.append(depth.ravel())
        leaf_offset += len(leaves)
    return np.concatenate(leaf_parts), np.concatenate(depth_parts)


def leaf_matrix(tree: HaarTree) -> sp.csc_matrix:
    """0/1 indicator of each leaf's texels.

    Parameters
    ----------
    tree : HaarTree

    Returns
    -------
    scipy.sparse.csc_matrix, shape (n_texels, n_leaves)
        Column k indicates the texels of ``tree.leaves()[k]``; it spans the
        same space as :func:`basis_matrix`.
    """
    leaf, _ = _texel_leaf_index(tree)
    n = tree.n_texels
    return sp.csc_matrix(
        (np.ones(n), (np.arange(n), leaf)), shape=(n, tree.n_leaves)
    )


def leaf_values_to_coefficients(leaf_values: np.ndarray, tree: HaarTree) -> np.ndarray:
    """Wavelet coefficients of a piecewise-constant function given per leaf.

    Parameters
    ----------
    leaf_values : ndarray, shape (n_leaves,) or (n_leaves, C)
        Constant texel value on each leaf, in ``tree.leaves()`` order.
    tree : HaarTree

    Returns
    -------
    ndarray, shape (n_coefficients,) or (n_coefficients, C)
    """
    columns = _as_columns(leaf_values, tree.n_leaves, "leaf_values")
    leaf, _ = _texel_leaf_index(tree)
    return _restore_shape(analyse(columns[leaf], tree), leaf_values)


def coefficients_to_leaf_values(coefficients: np.ndarray, tree: HaarTree) -> np.ndarray:
    """Per-leaf constant values of the function with the given coefficients.

    Parameters
    ----------
    coefficients : ndarray, shape (n_coefficients,) or (n_coefficients, C)
    tree : HaarTree

    Returns
    -------
    ndarray, shape (n_leaves,) or (n_leaves, C)
        Value on each leaf, in ``tree.leaves()`` order.
    """
    columns = _as_columns(coefficients, tree.n_coefficients, "coefficients")
    texels = synthesise(columns, tree)
    leaf, _ = _texel_leaf_index(tree)
    # Texels within a leaf agree up to rounding; averaging them is the
    # least-squares leaf value and smooths that rounding out.
    sums = np.zeros((tree.n_leaves, texels.shape[1]))
    np.add.at(sums, leaf, texels)
    counts = np.bincount(leaf, minlength=tree.n_leaves)
    return _restore_shape(sums / counts[:, None], coefficients)


def subdivide(tree: HaarTree, leaf_mask: np.ndarray) -> HaarTree:
    """Subdivide the selected leaves.

    Parameters
    ----------
    tree : HaarTree
    leaf_mask : ndarray of bool, shape (n_leaves,)
        Selection over ``tree.leaves()``. Selected single-texel leaves are
        left as they are.

    Returns
    -------
    HaarTree
    """
    mask = np.asarray(leaf_mask)
    if mask.dtype != bool or mask.shape != (tree.n_leaves,):
        raise ValueError(
            f"leaf_mask must be a boolean array of shape ({tree.n_leaves},), "
            f"got dtype {mask.dtype} and shape {mask.shape}"
        )
    added: list[set[NodeId]] = [set() for _ in tree.tile_sizes]
    for selected, (t, level, i, j) in zip(mask, tree.leaves()):
        if selected and tree.tile_sizes[t] >> level > 1:
            added[t].add((level, i, j))
    return HaarTree(
        tree.tile_sizes,
        tuple(nodes | new for nodes, new in zip(tree.subdivided, added)),
    )


def prune(
    tree: HaarTree, coefficients: np.ndarray, tol: float = 0.0
) -> tuple[HaarTree, np.ndarray]:
    """Merge subdivisions whose wavelets are negligible, bottom-up.

    A subdivided node is removed when all its children are leaves (after
    removals below it) and its three wavelet coefficients are all at most
    ``tol`` in absolute value, in every column.

    Parameters
    ----------
    tree : HaarTree
    coefficients : ndarray, shape (n_coefficients,) or (n_coefficients, C)
    tol : float
        Non-negative threshold.

    Returns
    -------
    new_tree : HaarTree
    new_coefficients : ndarray, shape (new_tree.n_coefficients,) or (..., C)
        The coefficients of the remaining basis functions, unchanged; the
        synthesised texels differ only by the removed wavelets.
    """
    if not tol >= 0:
        raise ValueError(f"tol must be non-negative, got {tol}")
    columns = _as_columns(coefficients, tree.n_coefficients, "coefficients")
    negligible = np.all(np.abs(columns) <= tol, axis=1)
    kept: list[frozenset[NodeId]] = []
    start = 0
    for nodes in _subdivided_nodes(tree):
        # Skip the scaling coefficient; then three wavelets per node.
        node_negligible = negligible[start + 1 : start + 1 + 3 * len(nodes)]
        node_negligible = node_negligible.reshape(-1, 3).all(axis=1)
        remaining = {tuple(int(v) for v in node) for node in nodes}
        # Reverse (level, i, j) order visits children before their parents,
        # so one pass sees every removal that could free a parent.
        for (level, i, j), drop in zip(nodes[::-1].tolist(), node_negligible[::-1]):
            if not drop:
                continue
            children = [
                (level + 1, 2 * i + di, 2 * j + dj) for di in (0, 1) for dj in (0, 1)
            ]
            if not any(child in remaining for child in children):
                remaining.discard((level, i, j))
        kept.append(frozenset(remaining))
        start += 1 + 3 * len(nodes)
    new_tree = HaarTree(tree.tile_sizes, tuple(kept))
    old_positions = _coefficient_positions(tree)
    new_positions = _coefficient_positions(new_tree)
    selected = np.searchsorted(old_positions, new_positions)
    return new_tree, _restore_shape(columns[selected], coefficients)


def tree_depth_image(tree: HaarTree) -> np.ndarray:
    """Level of the leaf containing each texel.

    Parameters
    ----------
    tree : HaarTree

    Returns
    -------
    ndarray of int, shape (n_texels,)
        0 where the tile root is a leaf, up to log2(size) for single texels.
    """
    _, depth = _texel_leaf_index(tree)
    return depth


def uniform_tree(cube, face_resolution: int) -> HaarTree:
    """Tree whose leaves are the texels of a cube map of face resolution `face_resolution` (<= R);
    `cube` is the `CubeMap` whose tiles the tree covers."""
    R = cube.resolution
    if face_resolution < 1 or face_resolution > R or face_resolution & (face_resolution - 1):
        raise ValueError(f"face resolution must be a power of two from 1 to {R}, got {face_resolution}")
    shrink = int(np.log2(R // face_resolution))
    nodes = []
    for size in cube.tile_sizes:
        depth = max(int(np.log2(size)) - shrink, 0)
        nodes.append([(lv, i, j) for lv in range(depth) for i in range(1 << lv) for j in range(1 << lv)])
    return HaarTree(cube.tile_sizes, tuple(frozenset(n) for n in nodes))
