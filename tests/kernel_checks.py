"""Checks shared by the kernel tests (microctl.gp.kernels)."""

from __future__ import annotations

import numpy as np


def assert_cross_grad_matches_fd(k, Xs: np.ndarray, X: np.ndarray, w: np.ndarray, *, rtol: float, atol: float,
                                 value_rtol: float = 1e-11, h: float = 1e-6) -> np.ndarray:
    """``k.cross_grad``'s value equals ``k(Xs, X) w`` and its gradient central differences of it in
    every column of Xs (m, d') (tolerances: the caller's); returns the gradient (m, d') for further checks."""
    value, grad = k.cross_grad(Xs, k.cross_terms(X, w))
    np.testing.assert_allclose(value, k.matrix(Xs, X) @ w, rtol=value_rtol)
    for c in range(Xs.shape[1]):
        e = np.zeros(Xs.shape[1])
        e[c] = h
        fd = (k.matrix(Xs + e, X) @ w - k.matrix(Xs - e, X) @ w) / (2 * h)
        np.testing.assert_allclose(grad[:, c], fd, rtol=rtol, atol=atol)
    return grad
