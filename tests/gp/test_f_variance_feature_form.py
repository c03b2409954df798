"""f's posterior variance in the feature form of its kernel (microctl.gp.kernels, feature form;
microctl.gp.posterior, class docstring): the form rebuilds the kernel, its remainder is PSD, the
low-rank variance lies in the stated interval above the exact one (computed here by a plain
linear solve, not by the package's Cholesky inverse), and the CasADi graph equals NumPy and
its gradient finite differences."""

from __future__ import annotations

import math

import casadi as ca
import numpy as np
import pytest

from kernel_checks import kernel_family

from microctl.gp.posterior import F_SE_REMAINDER_NEGLIGIBLE, Posterior
from microctl.gp.trainer import VHGPR


def test_feature_form_rebuilds_the_kernel_and_its_remainder_is_psd():
    """``psi(Xa) diag(w) psi(Xb)^T + e(Xa, Xb) = k(Xa, Xb)`` for every part of the family (to
    1e-12 of the kernel's scale: a sum of a few O(1) terms), e's diagonal is ``e(x, x)``, e's
    Gram matrix has no eigenvalue below -1e-12 of its largest (round-off), and CasADi's psi
    and e column equal NumPy's (1e-13: the same operations in another order)."""
    rng = np.random.default_rng(1)
    d = 4
    Xa, Xb = rng.normal(size=(9, d)), rng.normal(size=(30, d))
    x = ca.MX.sym("x", d)
    for name, k in kernel_family(rng, d).items():
        K = k.matrix(Xa, Xb)
        form = (k.features(Xa) * k.feature_weights) @ k.features(Xb).T + k.se_remainder(Xa, Xb)
        scale = float(np.max(np.abs(K)))
        np.testing.assert_allclose(form, K, rtol=0, atol=1e-12 * scale, err_msg=name)
        E = k.se_remainder(Xb, Xb)
        np.testing.assert_allclose(np.diag(E), k.se_remainder_diag(Xb), rtol=1e-12, atol=1e-300, err_msg=name)
        ev = np.linalg.eigvalsh(E)
        assert ev.min() >= -1e-12 * max(ev.max(), 1e-300), name
        f = ca.Function("f", [x], [k.features_casadi(x), k.se_remainder_casadi_column(x, Xb)])
        for row in Xa[:3]:
            psi, e = (np.array(v).ravel() for v in f(row))
            np.testing.assert_allclose(psi, k.features(row[None])[0], rtol=1e-13, atol=1e-15, err_msg=name)
            np.testing.assert_allclose(e, k.se_remainder(row[None], Xb)[0], rtol=1e-13,
                                       atol=1e-13 * k.signal_var, err_msg=name)


def _exact_f_var(post: Posterior, xs: np.ndarray) -> np.ndarray:
    """k** - k*^T (L L^T)^-1 k* by a plain linear solve (independent of the Cholesky inverse)."""
    L = np.asarray(post.f_chol)
    Ks = post.f_kernel.matrix(xs, post.X)
    return post.f_kernel.diag(xs) - np.einsum("ij,ji->i", Ks, np.linalg.solve(L @ L.T, Ks.T))


def _fit(se: str, seed: int = 3, n: int = 80):
    rng = np.random.default_rng(seed)
    X = rng.uniform(0, 1, (n, 2))
    y = 1 + 0.5 * X[:, 0] - X[:, 1] + 0.3 * np.sin(6 * X[:, 0]) + 0.05 * rng.standard_normal(n)
    return VHGPR(bias=True, linear=True, linear_prior_var=10.0, se=se, n_restarts=1).fit(X, y), rng


@pytest.fixture(scope="module")
def se_off():
    return _fit("off")


def test_with_the_se_part_off_the_variance_is_low_rank_and_exact_to_round_off(se_off):
    """A fit with f's SE part switched off takes the feature form; its variance is never below
    the exact one and above it by at most e(x*, x*) (+ round-off 1e-12 of k**: the exact
    variance is a difference of O(k**) terms), at the data and beyond it."""
    m, rng = se_off
    post = m.posterior
    assert post.f_low_rank
    assert np.max(post.f_kernel.se_remainder_diag(post.X)) <= F_SE_REMAINDER_NEGLIGIBLE
    xs = np.vstack([post.X, rng.normal(0, 3, (200, post.X.shape[1]))])
    low, exact = post.f_var_std(xs), _exact_f_var(post, xs)
    tol = 1e-12 * np.max(post.f_kernel.diag(xs))
    assert np.all(low >= exact - tol)
    assert np.all(low <= exact + post.f_kernel.se_remainder_diag(xs) + tol)
    assert np.min(exact) > 100 * tol  # the comparison is not one of round-off alone
    # the prediction reads the same form (y_scale^2 c*^2)
    X0 = m.x_mean + m.x_scale * xs[:5]
    np.testing.assert_allclose(m.predict(X0).f_var, m.y_scale**2 * np.maximum(low[:5], 0), rtol=1e-12)


def test_the_interval_holds_where_the_remainder_is_large_and_is_not_vacuous():
    """With the SE part on (the posterior keeps the dense form) the feature form, forced here,
    still never falls below the exact variance nor exceeds it by more than e(x*, x*), and it
    does exceed it by a fifth of that at some point: the dropped ||L^-1 e*||^2 is real, so a
    wrong cross term (a factor 1 for 2) or a missing one would break the bounds."""
    m, rng = _fit("on")
    post = m.posterior
    assert not post.f_low_rank
    xs = np.vstack([post.X, rng.normal(0, 2, (200, post.X.shape[1]))])
    exact = _exact_f_var(post, xs)
    np.testing.assert_allclose(post.f_var_std(xs), exact, rtol=0, atol=1e-12 * np.max(post.f_kernel.diag(xs)))
    forced = Posterior(m, f_form="features")
    assert forced.f_low_rank
    np.testing.assert_array_equal(Posterior(m, f_form="dense").f_var_std(xs), post.f_var_std(xs))
    low, width = forced.f_var_std(xs), post.f_kernel.se_remainder_diag(xs)
    tol = 1e-12 * np.max(post.f_kernel.diag(xs))
    assert np.all(low >= exact - tol)
    assert np.all(low <= exact + width + tol)
    assert np.max((low - exact) / width) > 0.2


def test_an_unknown_form_is_refused_naming_the_valid_ones(se_off):
    with pytest.raises(ValueError, match=r"f_form must be one of \('auto', 'dense', 'features'\), got 'fast'"):
        Posterior(se_off[0], f_form="fast")


def test_the_low_rank_graph_equals_numpy_and_its_gradient_central_differences(se_off):
    """CasADi's f_var (original units) equals NumPy's at random points (1e-12 relative: the same
    sums in another order) and its gradient equals central differences of NumPy's (step 1e-5
    in standardised inputs, truncation ~1e-10 of the curvature scale; 1e-6 relative)."""
    m, rng = se_off
    post = m.posterior
    d = post.X.shape[1]
    x = ca.MX.sym("x", d)
    v = post.casadi(x, ("f_var",))["f_var"]
    f = ca.Function("fvar", [x], [v, ca.gradient(v, x)], ["xs"], ["f_var", "grad"])
    h = 1e-5
    for row in rng.normal(0, 1.5, (8, d)):
        val, grad = f(row)
        ref = m.y_scale**2 * post.f_var_std(row[None])[0]
        assert float(val) == pytest.approx(ref, rel=1e-12)
        fd = np.array([(post.f_var_std((row + h * e)[None])[0] - post.f_var_std((row - h * e)[None])[0]) / (2 * h)
                       for e in np.eye(d)]) * m.y_scale**2
        np.testing.assert_allclose(np.array(grad).ravel(), fd, rtol=1e-6, atol=1e-9 * max(1.0, math.fabs(ref)))
