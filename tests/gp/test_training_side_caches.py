"""What the posterior computes once of its training inputs gives the same numbers, to the last bit,
as computing it per call: ``Kernel.matrix(xs, X, side=rows_side(X))`` against ``matrix(xs, X)``,
``se_remainder(xs, X, side_b=se_remainder_side(X))`` against ``se_remainder(xs, X)``, and
``cross_value_parts`` / ``cross_gradient`` (the value and the gradient apart, for a Newton step's check)
against an independent sum over the training rows of ``k(x, X_i) w_i`` and its finite differences;
and ``feature_form``, which computes what they share once, against the separate calls, to the
last bit."""

from __future__ import annotations

import numpy as np
from kernel_checks import kernel_family


def test_cached_training_sides_give_the_same_numbers():
    rng = np.random.default_rng(3)
    d = 4
    X = rng.normal(size=(40, d + 1))  # a column beyond the kernel's inputs, as a posterior's context
    for name, k in kernel_family(rng, d).items():
        side = k.rows_side(X)
        rem_side = k.se_remainder_side(X)
        for m in (1, 7):
            xs = rng.normal(size=(m, d + 1))
            assert np.array_equal(k.matrix(xs, X, side=side), k.matrix(xs, X)), name
            assert np.array_equal(k.se_remainder(xs, X, side_b=rem_side), k.se_remainder(xs, X)), name


def test_value_and_gradient_apart_match_a_plain_sum_and_central_differences():
    """The value equals ``sum_i k(x, X_i) w_i`` from ``Kernel.matrix`` (1e-12 relative: another
    summation order); the gradient equals central differences of that sum (step 1e-6: the error
    is O(h^2) ~ 1e-12 of the curvature, plus round-off ~ 1e-16 / 1e-6; 1e-7 relative)."""
    rng = np.random.default_rng(4)
    d = 4
    X = rng.normal(size=(30, d))
    w = rng.normal(size=30)
    h = 1e-6
    for name, k in kernel_family(rng, d).items():
        terms = k.cross_terms(X, w)
        xs = rng.normal(size=(5, d))
        value, se, se_w = k.cross_value_parts(xs, terms)
        grad = k.cross_gradient(xs, terms, se, se_w)
        plain = k.matrix(xs, X) @ w
        np.testing.assert_allclose(value, plain, rtol=1e-12, atol=1e-12 * np.max(np.abs(plain)), err_msg=name)
        fd = np.empty_like(grad)
        for j in range(d):
            e = np.zeros(d)
            e[j] = h
            fd[:, j] = (k.matrix(xs + e, X) @ w - k.matrix(xs - e, X) @ w) / (2 * h)
        np.testing.assert_allclose(grad, fd, rtol=1e-7, atol=1e-7 * np.max(np.abs(fd)), err_msg=name)
        v2, g2 = k.cross_grad(xs, terms)
        assert np.array_equal(v2, value) and np.array_equal(g2, grad), name


def test_shared_parts_give_the_separate_calls_numbers():
    """``feature_form`` is ``features``, ``se_remainder`` and ``diag`` at once: the same arrays;
    ``cross_value_parts``'s ``se @ weights`` is the product of its own two parts."""
    rng = np.random.default_rng(5)
    d = 4
    X = rng.normal(size=(30, d + 1))
    w = rng.normal(size=30)
    for name, k in kernel_family(rng, d).items():
        side = k.se_remainder_side(X)
        terms = k.cross_terms(X, w)
        for m in (1, 6):
            xs = rng.normal(size=(m, d + 1))
            psi, E, diag = k.feature_form(xs, side)
            assert np.array_equal(psi, k.features(xs)), name
            assert np.array_equal(E, k.se_remainder(xs, X, side_b=side)), name
            assert np.array_equal(diag, k.diag(xs)), name
            value, se, se_w = k.cross_value_parts(xs, terms)
            assert np.array_equal(se_w, se @ terms.weights), name
