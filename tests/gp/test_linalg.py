"""gp.linalg.tril_inverse (NumPy only, used by the posterior) against LAPACK through SciPy."""

import numpy as np
import pytest
import scipy.linalg as sla

from microctl.gp.linalg import tril_inverse


@pytest.mark.parametrize("n", [1, 2, 31, 32, 33, 100, 257])
def test_tril_inverse_matches_lapack_on_kernel_factors(n):
    # the matrices the posterior inverts: Cholesky factors of an SE kernel plus a noise diagonal
    rng = np.random.default_rng(n)
    X = rng.normal(size=(n, 3))
    K = np.exp(-0.5 * ((X[:, None, :] - X[None, :, :]) ** 2).sum(-1)) + 1e-3 * np.eye(n)
    L = np.linalg.cholesky(K)
    got = tril_inverse(L)
    ref = sla.solve_triangular(L, np.eye(n), lower=True)
    # the condition number of L is at most sqrt((n + 1) / 1e-3) ~ 500: round-off ~ cond * n * eps
    assert np.max(np.abs(got - ref)) <= 1e-10 * np.max(np.abs(ref))
    assert np.all(np.triu(got, 1) == 0.0)
    assert np.max(np.abs(L @ got - np.eye(n))) <= 1e-11


def test_tril_inverse_refuses_a_non_square_matrix():
    with pytest.raises(ValueError, match=r"square matrix, got shape \(3, 2\)"):
        tril_inverse(np.ones((3, 2)))
