"""Tests for the per-tile Haar quadtree bases in pipelines.haar."""

import numpy as np
import pytest
import scipy.sparse as sp

from pipelines.light.haar import HaarTree, analyse, basis_matrix, coefficients_to_leaf_values, leaf_matrix, leaf_values_to_coefficients, prune, subdivide, synthesise, tree_depth_image

HEMISPHERE = (32,) + (16,) * 8
SMALL = (4,) + (2,) * 8
LAYOUTS = [HEMISPHERE, SMALL]


def random_tree(tile_sizes, seed, rounds=4, p=0.4):
    """Partial tree grown by subdividing random leaves a few times."""
    rng = np.random.default_rng(seed)
    tree = HaarTree.roots(tile_sizes)
    for _ in range(rounds):
        tree = subdivide(tree, rng.random(tree.n_leaves) < p)
    return tree


def trees_for(tile_sizes):
    return [
        HaarTree.roots(tile_sizes),
        HaarTree.full(tile_sizes),
        HaarTree.full(tile_sizes, depth=2),
        random_tree(tile_sizes, seed=1),
        random_tree(tile_sizes, seed=2, rounds=6, p=0.6),
    ]


CASES = [
    pytest.param(tree, id=f"{len(sizes)}x{sizes[0]}-{k}")
    for sizes in LAYOUTS
    for k, tree in enumerate(trees_for(sizes))
]


def max_abs(matrix):
    return abs(matrix).max() if sp.issparse(matrix) else np.abs(matrix).max()


@pytest.mark.parametrize("tree", CASES)
def test_basis_is_orthonormal(tree):
    basis = basis_matrix(tree)
    assert basis.shape == (tree.n_texels, tree.n_coefficients)
    gram = (basis.T @ basis) - sp.identity(tree.n_coefficients)
    assert max_abs(gram) < 1e-12


@pytest.mark.parametrize("tree", CASES)
def test_basis_spans_leaf_indicators(tree):
    assert tree.n_coefficients == tree.n_leaves == len(tree.leaves())
    basis = basis_matrix(tree)
    leaves = leaf_matrix(tree)
    assert leaves.shape == (tree.n_texels, tree.n_leaves)
    # Each texel belongs to exactly one leaf.
    np.testing.assert_array_equal(np.asarray(leaves.sum(axis=1)).ravel(), 1.0)
    residual = leaves - basis @ (basis.T @ leaves)
    assert max_abs(residual) < 1e-12


@pytest.mark.parametrize("sizes", LAYOUTS)
def test_full_transform_round_trip_and_parseval(sizes):
    tree = HaarTree.full(sizes)
    rng = np.random.default_rng(0)
    texels = rng.normal(size=(tree.n_texels, 3)) * 10.0
    coefficients = analyse(texels, tree)
    assert coefficients.shape == (tree.n_coefficients, 3)
    back = synthesise(coefficients, tree)
    assert np.abs(back - texels).max() / np.abs(texels).max() < 1e-12
    energy = np.sum(texels**2, axis=0)
    np.testing.assert_allclose(np.sum(coefficients**2, axis=0), energy, rtol=1e-12)


@pytest.mark.parametrize("tree", CASES)
def test_analyse_inverts_synthesise_on_partial_trees(tree):
    rng = np.random.default_rng(3)
    coefficients = rng.normal(size=tree.n_coefficients)
    back = analyse(synthesise(coefficients, tree), tree)
    assert back.shape == coefficients.shape
    assert np.abs(back - coefficients).max() < 1e-12


@pytest.mark.parametrize("tree", CASES)
def test_fast_transform_matches_sparse_matrix(tree):
    rng = np.random.default_rng(4)
    basis = basis_matrix(tree)
    texels = rng.normal(size=(tree.n_texels, 2))
    coefficients = rng.normal(size=(tree.n_coefficients, 2))
    assert np.abs(analyse(texels, tree) - basis.T @ texels).max() < 1e-12
    assert np.abs(synthesise(coefficients, tree) - basis @ coefficients).max() < 1e-12


@pytest.mark.parametrize("tree", CASES)
def test_analyse_projects_onto_tree_span(tree):
    rng = np.random.default_rng(5)
    texels = rng.normal(size=tree.n_texels)
    projected = synthesise(analyse(texels, tree), tree)
    # The residual of an orthogonal projection is orthogonal to the basis.
    residual = basis_matrix(tree).T @ (texels - projected)
    assert np.abs(residual).max() < 1e-12


@pytest.mark.parametrize("tree", CASES)
def test_coefficient_index_matches_basis_columns(tree):
    index = tree.coefficient_index()
    assert len(index) == tree.n_coefficients
    basis = basis_matrix(tree).tocsc()
    for k in np.random.default_rng(6).choice(len(index), size=20):
        tile, kind, level, i, j = index[k]
        size = tree.tile_sizes[tile]
        side = size >> level
        column = basis[:, k].toarray().ravel()
        offset = sum(s * s for s in tree.tile_sizes[:tile])
        block = column[offset : offset + size * size].reshape(size, size)
        node = block[i * side : (i + 1) * side, j * side : (j + 1) * side]
        assert np.abs(node).sum() == pytest.approx(side, rel=1e-12)
        half = side // 2
        if kind == "h":
            assert node[0, 0] > 0 and node[0, half] < 0
        elif kind == "v":
            assert node[0, 0] > 0 and node[half, 0] < 0
        elif kind == "d":
            assert node[0, 0] > 0 and node[half, half] > 0 and node[0, half] < 0


@pytest.mark.parametrize("size, value", [(1, 2.0), (2, -1.5), (8, 3.0), (16, 0.25)])
def test_constant_tile_has_only_scaling_coefficient(size, value):
    tree = HaarTree.full([size])
    coefficients = analyse(np.full(size * size, value), tree)
    assert coefficients[0] == pytest.approx(value * size, rel=1e-14)
    assert np.abs(coefficients[1:]).max(initial=0.0) < 1e-14


def test_two_by_two_by_hand():
    tree = HaarTree.full([2])
    # Tile [[1, 2], [3, 4]]: sum/2, (left-right)/2, (top-bottom)/2, (diag-anti)/2.
    coefficients = analyse(np.array([1.0, 2.0, 3.0, 4.0]), tree)
    np.testing.assert_allclose(coefficients, [5.0, -1.0, -2.0, 0.0], atol=1e-15)
    assert tree.coefficient_index() == [
        (0, "scaling", 0, 0, 0),
        (0, "h", 0, 0, 0),
        (0, "v", 0, 0, 0),
        (0, "d", 0, 0, 0),
    ]


def test_four_by_four_impulse_by_hand():
    tree = HaarTree.full([4])
    texels = np.zeros((4, 4))
    texels[1, 2] = 1.0
    coefficients = analyse(texels.ravel(), tree)
    expected = np.zeros(16)
    # Root: texel is in the right (h -) and top (v +) halves, top-right (d -).
    expected[:4] = [0.25, -0.25, 0.25, -0.25]
    # Node (1, 0, 1), stored after (0,0,0) and (1,0,0): texel is bottom-left.
    expected[7:10] = [0.5, -0.5, -0.5]
    np.testing.assert_allclose(coefficients, expected, atol=1e-15)


def test_full_depth_is_clamped_per_tile():
    tree = HaarTree.full([8, 2, 1], depth=2)
    assert [len(nodes) for nodes in tree.subdivided] == [5, 1, 0]
    assert tree.n_coefficients == 3 + 3 * 6
    assert tree.n_texels == 64 + 4 + 1
    assert HaarTree.full([8, 2, 1]) == HaarTree.full([8, 2, 1], depth=10)
    depth = tree_depth_image(tree)
    np.testing.assert_array_equal(depth[:64], 2)
    np.testing.assert_array_equal(depth[64:], [1, 1, 1, 1, 0])


def test_tree_is_hashable_and_normalised():
    a = HaarTree([4, 2], [[(0, 0, 0), (1, 1, 0)], []])
    b = HaarTree((4, 2), (frozenset({(1, 1, 0), (0, 0, 0)}), frozenset()))
    assert a == b and hash(a) == hash(b)
    assert len({a, b}) == 1
    assert a.tile_sizes == (4, 2)


def test_leaves_and_depth_image_of_partial_tree():
    tree = HaarTree([4], [{(0, 0, 0), (1, 1, 0)}])
    assert tree.leaves() == [
        (0, 1, 0, 0),
        (0, 1, 0, 1),
        (0, 1, 1, 1),
        (0, 2, 2, 0),
        (0, 2, 2, 1),
        (0, 2, 3, 0),
        (0, 2, 3, 1),
    ]
    expected = np.array(
        [[1, 1, 1, 1], [1, 1, 1, 1], [2, 2, 1, 1], [2, 2, 1, 1]]
    ).ravel()
    np.testing.assert_array_equal(tree_depth_image(tree), expected)
    leaf = leaf_matrix(tree).toarray().argmax(axis=1).reshape(4, 4)
    np.testing.assert_array_equal(
        leaf, [[0, 0, 1, 1], [0, 0, 1, 1], [3, 4, 2, 2], [5, 6, 2, 2]]
    )


@pytest.mark.parametrize("tree", CASES)
@pytest.mark.parametrize("channels", [None, 3])
def test_leaf_values_round_trip(tree, channels):
    rng = np.random.default_rng(7)
    shape = (tree.n_leaves,) if channels is None else (tree.n_leaves, channels)
    leaf_values = rng.normal(size=shape)
    coefficients = leaf_values_to_coefficients(leaf_values, tree)
    assert coefficients.shape == (tree.n_coefficients,) + shape[1:]
    expected = basis_matrix(tree).T @ (leaf_matrix(tree) @ leaf_values)
    assert np.abs(coefficients - expected).max() < 1e-12
    back = coefficients_to_leaf_values(coefficients, tree)
    assert np.abs(back - leaf_values).max() < 1e-12


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_subdivide_then_prune_zero_wavelets_restores_tree(seed):
    tree = random_tree(SMALL + (8,), seed=seed)
    coefficients = np.random.default_rng(seed).normal(size=tree.n_coefficients)
    finer = subdivide(tree, np.ones(tree.n_leaves, dtype=bool))
    assert finer.n_coefficients > tree.n_coefficients
    finer_coefficients = analyse(synthesise(coefficients, tree), finer)
    pruned, pruned_coefficients = prune(finer, finer_coefficients, tol=0.0)
    assert pruned == tree
    assert np.abs(pruned_coefficients - coefficients).max() < 1e-12


def test_subdivide_leaves_single_texels_alone():
    tree = HaarTree.full([2, 4], depth=1)
    finer = subdivide(tree, np.ones(tree.n_leaves, dtype=bool))
    assert finer.subdivided[0] == tree.subdivided[0]
    assert finer == HaarTree.full([2, 4])


def test_prune_keeps_nodes_with_nonzero_wavelets():
    tree = HaarTree.full([4])
    index = tree.coefficient_index()
    coefficients = np.zeros(tree.n_coefficients)
    coefficients[0] = 3.0
    coefficients[index.index((0, "d", 1, 1, 0))] = 1e-3
    pruned, kept = prune(tree, coefficients)
    # The root's wavelets are zero but it still has a subdivided child.
    assert pruned.subdivided == (frozenset({(0, 0, 0), (1, 1, 0)}),)
    assert pruned.coefficient_index()[kept.argmax()] == (0, "scaling", 0, 0, 0)
    assert kept[pruned.coefficient_index().index((0, "d", 1, 1, 0))] == 1e-3
    np.testing.assert_allclose(
        synthesise(kept, pruned), synthesise(coefficients, tree), atol=1e-15
    )
    coarse, coarse_coefficients = prune(tree, coefficients, tol=1e-2)
    assert coarse == HaarTree.roots([4])
    np.testing.assert_array_equal(coarse_coefficients, [3.0])


def test_prune_rgb_removes_only_when_all_channels_negligible():
    tree = HaarTree.full([2, 2])
    coefficients = np.zeros((tree.n_coefficients, 3))
    # Tile 1's horizontal wavelet is non-zero in the blue channel only.
    coefficients[5, 2] = 0.5
    pruned, kept = prune(tree, coefficients)
    assert pruned.subdivided == (frozenset(), frozenset({(0, 0, 0)}))
    assert kept.shape == (5, 3)
    assert kept[2, 2] == 0.5
    coefficients[5, 2] = 0.0
    pruned, kept = prune(tree, coefficients)
    assert pruned == HaarTree.roots([2, 2])
    assert kept.shape == (2, 3)


@pytest.mark.parametrize(
    "make, message",
    [
        (lambda: HaarTree.roots([4, 12]), "tile size 12 .*not a power of two"),
        (lambda: HaarTree.roots([0]), "not a power of two"),
        (lambda: HaarTree([4], []), "1 tiles"),
        (lambda: HaarTree([4], [{(0, 0, 0), (1, 2, 0)}]), r"\(1, 2, 0\) lies outside"),
        (lambda: HaarTree([4], [{(-1, 0, 0)}]), "lies outside"),
        (lambda: HaarTree([4], [{(1, 0, 1)}]), r"orphan node \(1, 0, 1\)"),
        (lambda: HaarTree([2], [{(0, 0, 0), (1, 0, 0)}]), "single texel"),
        (lambda: HaarTree([4], [{(0, 0)}]), "integer triples"),
        (lambda: HaarTree.full([4], depth=-1), "depth must be non-negative"),
    ],
)
def test_invalid_trees_raise(make, message):
    with pytest.raises(ValueError, match=message):
        make()


def test_invalid_arrays_raise():
    tree = HaarTree.full([4])
    with pytest.raises(ValueError, match="texels has 15 rows, expected 16"):
        analyse(np.zeros(15), tree)
    with pytest.raises(ValueError, match="coefficients has 4 rows, expected 16"):
        synthesise(np.zeros(4), tree)
    with pytest.raises(ValueError, match="1-D or 2-D"):
        analyse(np.zeros((16, 1, 1)), tree)
    with pytest.raises(ValueError, match="leaf_values has 3 rows"):
        leaf_values_to_coefficients(np.zeros(3), tree)
    with pytest.raises(ValueError, match="leaf_mask must be a boolean array"):
        subdivide(tree, np.ones(tree.n_leaves))
    with pytest.raises(ValueError, match="leaf_mask must be a boolean array"):
        subdivide(tree, np.ones(3, dtype=bool))
    with pytest.raises(ValueError, match="tol must be non-negative"):
        prune(tree, np.zeros(16), tol=-1.0)
