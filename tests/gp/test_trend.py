"""f's feature trend (microctl.gp.trend): values, gradients, the kernel, CasADi, the model file,
and a planted mean shift recovered."""

from __future__ import annotations

import math

import casadi as ca
import numpy as np
import pytest

from microctl.errors import ConfigError, DataError
from microctl.gp.fitted import FittedVHGPR
from microctl.gp.kernels import Kernel
from microctl.gp.shaped_features import GATED, SHAPES, ShapedFeatures
from microctl.gp.trainer import VHGPR
from microctl.gp.trend import FeatureTrend
from kernel_checks import assert_cross_grad_matches_fd

UNGATED = tuple(k for k in SHAPES if k not in GATED)


def _trend(rng, k=4, log_var=0.3):
    t = len(UNGATED)
    params = np.column_stack([rng.uniform(0.5, 2, t), rng.uniform(0.5, 2, t)])
    return FeatureTrend(ShapedFeatures(rng.normal(size=(t, k)), rng.normal(size=t), UNGATED, params,
                                       rng.uniform(0.5, 2, t), tuple(f"f{j}" for j in range(t))), log_var)


def test_trend_values_are_the_shaped_features_of_the_same_maps():
    """Independent answer: each shape's formula written out here, on the same maps."""
    rng = np.random.default_rng(0)
    tr = _trend(rng)
    f = tr.features
    X = rng.normal(size=(30, 4))
    Z = X @ f.matrix.T + f.offset
    a, b = f.params[:, 0], f.params[:, 1]
    by_hand = {
        "sq": Z**2, "abs": np.sqrt(Z**2 + a**2) - a, "sat": Z**2 / (Z**2 + a**2),
        "up": Z**2 * (1 + np.tanh(Z / a)) / 2, "down": Z**2 * (1 - np.tanh(Z / a)) / 2,
        "bump": np.exp(-((Z - a) ** 2) / (2 * b**2)), "exp": np.exp(Z),
        "step": 1 / (1 + np.exp(-(np.sqrt(Z**2 + b**2) - a) / b)),
    }
    want = np.column_stack([by_hand[kind][:, j] for j, kind in enumerate(f.shapes)]) / f.scale
    np.testing.assert_allclose(tr.values(X), want, rtol=1e-12, atol=1e-12)
    # columns beyond k (a move's context) are not read
    np.testing.assert_array_equal(tr.values(np.hstack([X, rng.normal(size=(30, 2))])), tr.values(X))


def test_trend_gradients_match_central_differences():
    rng = np.random.default_rng(1)
    tr = _trend(rng)
    X = rng.normal(size=(25, 4))
    G = tr.gradients(X)
    h = 1e-6
    for c in range(4):
        E = np.zeros(4)
        E[c] = h
        fd = (tr.values(X + E) - tr.values(X - E)) / (2 * h)
        np.testing.assert_allclose(G[:, :, c], fd, rtol=1e-5, atol=1e-6)


def test_kernel_with_trend_adds_v_phi_phi_and_casadi_equals_numpy():
    rng = np.random.default_rng(2)
    tr = _trend(rng)
    base = Kernel(rng.normal(size=4), 0.2, -1.0, rng.normal(size=4))
    k = Kernel(base.log_lengthscales, base.log_signal_var, base.log_bias_var, base.log_linear_vars, trend=tr)
    Xa, Xb = rng.normal(size=(7, 4)), rng.normal(size=(9, 4))
    want = base.matrix(Xa, Xb) + math.exp(0.3) * tr.values(Xa) @ tr.values(Xb).T
    np.testing.assert_allclose(k.matrix(Xa, Xb), want, rtol=1e-12)
    np.testing.assert_allclose(k.diag(Xa), np.diag(k.matrix(Xa, Xa)), rtol=1e-12)
    x = ca.MX.sym("x", 4)
    col = ca.Function("k", [x], [k.casadi_column(x, Xb), k.casadi_diag(x)])
    for row in Xa:
        c, dg = col(row)
        np.testing.assert_allclose(np.array(c).ravel(), k.matrix(row[None], Xb).ravel(), rtol=1e-11)
        np.testing.assert_allclose(float(dg), k.diag(row[None])[0], rtol=1e-11)
    # k(Xs, X) w and its input gradient (the controller's seeding) against central differences
    assert_cross_grad_matches_fd(k, Xa, Xb, rng.normal(size=9), rtol=1e-5, atol=1e-6)


def test_cross_grad_reads_the_training_side_from_its_precomputed_terms():
    """The controller's seeding computes the training side once per fitted posterior
    (Kernel.cross_terms) and reuses it: with and without bias, linear and trend parts, and with
    context columns beyond the kernel's d (ignored, their gradient zero), the value is
    k(Xs, X) w as the kernel matrix computes it."""
    rng = np.random.default_rng(4)
    tr = _trend(rng)
    for k in (Kernel(rng.normal(size=4), 0.2, -1.0, rng.normal(size=4), trend=tr),
              Kernel(rng.normal(size=4), -0.3, None, None)):
        X, w = rng.normal(size=(40, 4)), rng.normal(size=40)
        terms = k.cross_terms(X, w)
        for m in (1, 17):
            Xs = rng.normal(size=(m, 6))  # two context columns beyond the kernel's d
            v, g = k.cross_grad(Xs, terms)
            assert g.shape == (m, 6) and not np.any(g[:, 4:])
            np.testing.assert_allclose(v, k.matrix(Xs, X) @ w, rtol=1e-11, atol=1e-12)
            v4, g4 = k.cross_grad(Xs[:, :4], terms)
            np.testing.assert_array_equal(v4, v)
            np.testing.assert_array_equal(g4, g[:, :4])


def test_trend_refuses_gated_shapes_and_mismatched_arrays():
    rng = np.random.default_rng(3)
    with pytest.raises(ConfigError, match="rev"):
        FeatureTrend(ShapedFeatures(np.ones((1, 2)), np.zeros(1), ("rev",), np.ones((1, 2)), np.ones(1), ("a",),
                                    np.ones((1, 2))), 0.0)
    with pytest.raises(ConfigError, match="do not match"):
        FeatureTrend(ShapedFeatures(rng.normal(size=(2, 3)), np.zeros(3), ("sq", "abs"), np.ones((2, 2)), np.ones(2),
                                    ("a", "b")), 0.0)
    with pytest.raises(ConfigError, match="log_var"):
        FeatureTrend(ShapedFeatures(np.ones((1, 2)), np.zeros(1), ("sq",), np.zeros((1, 2)), np.ones(1), ("a",)),
                     math.inf)


def _shift_data(rng, n):
    """y = 0.5 x1 + a mean shift 0.8 |x0 - x2| (planted, the trainer is told only the features'
    shapes) + noise whose std grows with |x0 - x2|."""
    X = rng.uniform(-3, 3, size=(n, 3))
    step = np.abs(X[:, 0] - X[:, 2])
    y = 0.5 * X[:, 1] + 0.8 * step + (0.05 + 0.3 * step) * rng.standard_normal(n)
    return X, y, step


def _step_features():
    A = np.array([[1.0, 0.0, -1.0]])
    return ShapedFeatures(A, np.zeros(1), ("abs",), np.array([[0.01, 0.0]]), np.ones(1), ("step",))


def test_a_planted_mean_shift_is_recovered_by_the_trend_and_missed_without_it(tmp_path):
    """Hidden effect: the mean grows with a step the SE kernel has no input for. Extrapolating to
    steps beyond the training range (x0 = -x2 = +-4), the trend's mean error is a fraction of the
    plain model's, and the trend's model is preferred by its bound by more than its BIC cost.
    Tolerances: at these steps the planted shift is 6.4-8, the noise std at the training edge ~2,
    with 150 points the trend coefficient is known to ~5 %: 1.0 on the error bound leaves room."""
    rng = np.random.default_rng(4)
    X, y, _ = _shift_data(rng, 150)
    common = dict(linear=(0, 1, 2), linear_prior_var=10.0, noise_model="hgp", n_restarts=1, g_start="f", se="on")
    plain = VHGPR(**common).fit(X, y)
    trend = VHGPR(**common, mean_features=_step_features()).fit(X, y)
    Xt = np.array([[4.0, 0.0, -4.0], [-4.0, 1.0, 4.0], [3.5, -1.0, -3.5], [0.0, 2.0, 0.0]])
    truth = 0.5 * Xt[:, 1] + 0.8 * np.abs(Xt[:, 0] - Xt[:, 2])
    err_trend = np.abs(trend.predict(Xt).f_mean - truth)
    err_plain = np.abs(plain.predict(Xt).f_mean - truth)
    assert np.max(err_trend) < 1.0, err_trend
    assert np.max(err_plain) > 2.0 * np.max(err_trend), (err_plain, err_trend)
    assert trend.bound - plain.bound > 0.5 * math.log(150)
    # the model file keeps the trend (and the model reads back bit for bit)
    trend.save(tmp_path / "m.npz")
    back = FittedVHGPR.load(tmp_path / "m.npz")
    assert back.f_trend_names == ("step",) and back.f_trend_shapes == ("abs",)
    np.testing.assert_array_equal(back.predict(Xt).f_mean, trend.predict(Xt).f_mean)
    np.testing.assert_array_equal(back.predict(Xt).f_var, trend.predict(Xt).f_var)


def test_a_model_file_with_half_a_trend_is_refused_naming_the_arrays(tmp_path):
    rng = np.random.default_rng(5)
    X, y, _ = _shift_data(rng, 40)
    m = VHGPR(linear=(0, 1, 2), linear_prior_var=10.0, noise_model="hgp", n_restarts=1, g_start="f", se="on",
              mean_features=_step_features(), max_iter=20).fit(X, y)
    m.save(tmp_path / "m.npz")
    with np.load(tmp_path / "m.npz", allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files if k != "f_trend_scale"}
    np.savez(tmp_path / "half.npz", **arrays)
    with pytest.raises(DataError, match="f_trend_scale"):
        FittedVHGPR.load(tmp_path / "half.npz")


def test_a_file_without_the_trends_fields_reads_as_a_model_without_trend_but_a_missing_bias_is_refused(tmp_path):
    """A file written before version 5 has no ``f_trend_log_var``: it reads as None (the field's
    default). An optional float without a default (``f_log_bias_var``) stays required."""
    rng = np.random.default_rng(6)
    X, y, _ = _shift_data(rng, 30)
    m = VHGPR(linear=(0, 1, 2), linear_prior_var=10.0, noise_model="hgp", n_restarts=1, g_start="f", se="on",
              max_iter=20).fit(X, y)
    m.save(tmp_path / "m.npz")
    with np.load(tmp_path / "m.npz", allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    np.savez(tmp_path / "old.npz", **{k: v for k, v in arrays.items() if k != "f_trend_log_var"})
    old = FittedVHGPR.load(tmp_path / "old.npz")
    assert old.f_trend_log_var is None and old.f_trend is None
    np.testing.assert_array_equal(old.predict(X).f_mean, m.predict(X).f_mean)
    np.savez(tmp_path / "nobias.npz", **{k: v for k, v in arrays.items() if k != "f_log_bias_var"})
    with pytest.raises(DataError, match=r"nobias\.npz.*'f_log_bias_var'"):
        FittedVHGPR.load(tmp_path / "nobias.npz")


def test_mean_features_of_the_wrong_type_or_reading_beyond_the_kernels_inputs_are_refused():
    with pytest.raises(ConfigError, match="mean_features must be a ShapedFeatures or None, got dict"):
        VHGPR(mean_features={"step": 1})
    f = ShapedFeatures(np.array([[1.0, 0.0, 0.0, 2.0]]), np.zeros(1), ("sq",), np.zeros((1, 2)), np.ones(1), ("c",))
    with pytest.raises(ConfigError, match="only the first 3 may be read"):
        FeatureTrend.from_original_units(f, np.zeros(3), np.ones(3), 0.0)
