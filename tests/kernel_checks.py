"""Checks shared by the kernel tests (microctl.gp.kernels)."""

from __future__ import annotations

import numpy as np

from microctl.gp.kernels import Kernel
from microctl.gp.shaped_features import ShapedFeatures
from microctl.gp.trend import FeatureTrend


def kernel_family(rng: np.random.Generator, d: int) -> dict[str, Kernel]:
    """One kernel of each part of the family on d inputs, by name: the SE alone (short
    lengthscales), bias + linear with the SE at its floor, bias + linear + a feature trend with
    the SE on, and an input map with a linear part."""
    trend = FeatureTrend(ShapedFeatures(rng.normal(size=(2, d)), rng.normal(size=2), ("sq", "abs"),
                                        np.array([[1.0, 1.0], [0.7, 1.0]]), np.array([1.3, 0.8]), ("a", "b")), 0.4)
    ls = rng.uniform(-0.5, 0.5, d)
    return {
        "se only, short": Kernel(ls, 0.3),
        "bias + linear, se at its floor": Kernel(np.full(d, 6.0), -12.0, 1.0, rng.uniform(-2, 1, d)),
        "bias + linear + trend, se on": Kernel(ls, -1.0, 0.5, rng.uniform(-2, 1, d), trend=trend),
        "input map + linear": Kernel(ls[:2], 0.0, None, np.array([0.2, -0.3]), input_map=rng.normal(size=(2, d))),
    }


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
