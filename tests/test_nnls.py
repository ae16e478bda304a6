"""NNLS on the normal equations: same optimum as scipy's NNLS on the tall matrix, KKT holds,
never fails on rank-deficient or unconstrained columns."""

import numpy as np
import pytest
from scipy.optimize import nnls

from pipelines.light.nnls import nnls_gram, nnls_gram_multi


def problem(seed, m, n, density=0.5):
    rng = np.random.default_rng(seed)
    A = np.abs(rng.normal(size=(m, n))) * (rng.random((m, n)) < density)
    x_true = np.maximum(rng.normal(size=n), 0) * (rng.random(n) < 0.3)
    b = A @ x_true + 0.01 * rng.normal(size=m)
    return A, b


@pytest.mark.parametrize("seed, m, n", [(0, 60, 10), (1, 400, 80), (2, 2000, 300)])
def test_matches_scipy_nnls_objective(seed, m, n):
    A, b = problem(seed, m, n)
    res = nnls_gram(A.T @ A, A.T @ b)
    ref, _ = nnls(A, b, maxiter=50 * n)
    ours, theirs = np.sum((A @ res.x - b) ** 2), np.sum((A @ ref - b) ** 2)
    assert ours <= theirs * (1 + 1e-9) + 1e-12
    assert np.all(res.x >= 0)
    assert res.kkt_residual < 1e-9
    assert res.n_free + res.n_bound == n and not res.fallback


def test_duplicate_and_unseen_columns_never_fail():
    A, b = problem(3, 100, 40)
    A = np.hstack([A, A[:, :10], np.zeros((100, 5))])  # exact duplicates and columns no pixel sees
    res = nnls_gram(A.T @ A, A.T @ b)
    assert res.n_unconstrained == 5 and np.all(res.x[-5:] == 0)
    ref, _ = nnls(A, b, maxiter=5000)
    assert np.sum((A @ res.x - b) ** 2) <= np.sum((A @ ref - b) ** 2) * (1 + 1e-6) + 1e-12
    assert res.kkt_residual < 1e-6


def test_objective_no_worse_than_random_feasible_probes():
    A, b = problem(4, 300, 50)
    G, h = A.T @ A, A.T @ b
    res = nnls_gram(G, h)
    rng = np.random.default_rng(5)
    for _ in range(200):
        probe = np.maximum(res.x + 0.05 * rng.normal(size=50), 0)
        assert 0.5 * probe @ G @ probe - h @ probe >= res.objective - 1e-12


def test_multi_channel_and_bad_input():
    A, b = problem(6, 200, 30)
    B = np.column_stack([b, 2 * b, np.zeros_like(b)])
    X, results = nnls_gram_multi(A.T @ A, A.T @ B)
    np.testing.assert_allclose(X[:, 1], 2 * X[:, 0], rtol=1e-8, atol=1e-12)
    assert np.all(X[:, 2] == 0) and len(results) == 3
    with pytest.raises(ValueError):
        nnls_gram(np.eye(3), np.ones(4))
    with pytest.raises(ValueError):
        nnls_gram(np.full((2, 2), np.nan), np.ones(2))
