"""g's kernel on mapped inputs (microctl.gp.kernels ``input_map``, microctl.models.noise_inputs):
the kernel against the plain kernel on inputs mapped by hand, CasADi against NumPy, gradients
against central differences, the posterior's pairwise g against its row-by-row g, the model
file, and a planted noise along a step recovered on the step's axis."""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest

from microctl.errors import ConfigError, DataError
from microctl.gp.fitted import FittedVHGPR
from microctl.gp.kernels import Kernel
from microctl.gp.posterior import Posterior
from microctl.gp.trainer import VHGPR
from kernel_checks import assert_cross_grad_matches_fd


def _kernel(rng, d=3, d_in=4, bias=True, linear=False):
    M = rng.normal(size=(d, d_in))
    return Kernel(rng.normal(0.0, 0.3, d), float(rng.normal(0.0, 0.3)), -1.0 if bias else None,
                  rng.normal(-1.0, 0.3, d) if linear else None, input_map=M), M


@pytest.mark.parametrize("linear", [False, True])
def test_mapped_kernel_is_the_plain_kernel_on_inputs_mapped_by_hand(linear):
    rng = np.random.default_rng(0)
    k, M = _kernel(rng, linear=linear)
    plain = Kernel(k.log_lengthscales, k.log_signal_var, k.log_bias_var, k.log_linear_vars)
    Xa, Xb = rng.normal(size=(7, 4)), rng.normal(size=(9, 4))
    np.testing.assert_allclose(k.matrix(Xa, Xb), plain.matrix(Xa @ M.T, Xb @ M.T), rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(k.diag(Xa), plain.diag(Xa @ M.T), rtol=1e-12)
    # columns beyond the map's d_in (a move's context) are not read
    np.testing.assert_array_equal(k.matrix(np.hstack([Xa, rng.normal(size=(7, 2))]), Xb), k.matrix(Xa, Xb))
    G = rng.normal(size=(9, 9))
    G = G + G.T
    np.testing.assert_allclose(k.grad_traces(G, k.se(Xb, Xb), Xb), plain.grad_traces(G, plain.se(Xb @ M.T, Xb @ M.T),
                                                                                      Xb @ M.T), rtol=1e-10)
    assert k.d == 3 and k.d_in == 4 and k.spec.unpack(k.pack()).matrix(Xa, Xb) == pytest.approx(k.matrix(Xa, Xb))


def test_mapped_kernel_casadi_equals_numpy_at_random_points():
    rng = np.random.default_rng(1)
    k, _ = _kernel(rng, linear=True)
    X = rng.normal(size=(12, 4))
    xs = ca.MX.sym("x", 6)  # two context columns beyond d_in, unread
    col = ca.Function("c", [xs], [k.casadi_column(xs, X), k.casadi_diag(xs)])
    for _ in range(5):
        x = rng.normal(size=6)
        c, dg = (np.asarray(v).ravel() for v in col(x))
        np.testing.assert_allclose(c, k.matrix(x[None, :4], X)[0], rtol=1e-12)
        assert float(dg[0]) == pytest.approx(float(k.diag(x[None, :4])[0]), rel=1e-12)


def test_mapped_cross_grad_matches_central_differences():
    rng = np.random.default_rng(2)
    k, _ = _kernel(rng, linear=True)
    X, w = rng.normal(size=(15, 4)), rng.normal(size=15)
    grad = assert_cross_grad_matches_fd(k, rng.normal(size=(5, 5)), X, w, rtol=1e-6, atol=1e-8,
                                        value_rtol=1e-12)
    assert np.all(grad[:, 4] == 0.0)  # the column beyond the map's inputs is not read


def test_mapped_kernel_refuses_a_map_of_the_wrong_height():
    with pytest.raises(ValueError, match="one row per lengthscale"):
        Kernel(np.zeros(3), 0.0, input_map=np.ones((2, 4)))


def _step_noise_data(n, seed):
    """x = [a, b]; the mean depends on a, the log noise variance on the step b - a only."""
    rng = np.random.default_rng(seed)
    X = rng.uniform(-1.0, 1.0, size=(n, 2))
    log_var = -4.0 + 3.0 * (X[:, 1] - X[:, 0]) ** 2
    y = np.sin(2.0 * X[:, 0]) + np.exp(0.5 * log_var) * rng.standard_normal(n)
    return X, y, log_var


STEP_MAP = np.array([[1.0, 0.0], [-1.0, 1.0]])  # [a, b - a]: a position and a step


@pytest.fixture(scope="module")
def step_model():
    X, y, _ = _step_noise_data(160, 3)
    return VHGPR(n_restarts=1, g_start="f", g_input_map=STEP_MAP, g_input_names=("a", "step")).fit(X, y)


def test_planted_step_noise_found_on_the_steps_axis(step_model):
    """The trainer is not told which row the noise lives on: g's lengthscale along the step must
    come out shorter than along the position (the noise does not change with a at fixed step),
    and the learned log variance must follow the planted one (correlation > 0.9 on fresh
    points; the raw-input fit of the same data is the comparison, not a bar)."""
    ls = np.exp(np.asarray(step_model.g_log_lengthscales))
    assert ls[1] < 0.5 * ls[0], ls
    Xt, _, log_var = _step_noise_data(400, 4)
    g = Posterior(step_model).g_mean_var(Posterior(step_model).standardise(Xt))[0]
    assert np.corrcoef(g, log_var)[0, 1] > 0.9
    assert step_model.g_input_names == ("a", "step")


def test_pairwise_g_equals_row_by_row_g_with_a_map(step_model):
    post = Posterior(step_model)
    rng = np.random.default_rng(5)
    S, U = rng.normal(size=(4, 1)), rng.normal(size=(6, 1))
    mean, var = post.g_pairs(S, U)
    for i, s in enumerate(S):
        m, v = post.g_mean_var(np.column_stack([np.full(6, s[0]), U[:, 0]]))
        np.testing.assert_allclose(mean[i], m, rtol=1e-10, atol=1e-12)
        np.testing.assert_allclose(var[i], v, rtol=1e-10, atol=1e-12)


def test_model_file_keeps_the_map(step_model, tmp_path):
    path = tmp_path / "m.npz"
    step_model.save(path)
    back = FittedVHGPR.load(path)
    np.testing.assert_array_equal(back.g_input_map, step_model.g_input_map)
    assert back.g_input_names == ("a", "step")
    X = np.random.default_rng(6).normal(size=(5, 2))
    np.testing.assert_allclose(Posterior(back).g_mean_var(X)[0], Posterior(step_model).g_mean_var(X)[0], rtol=1e-13)


def test_model_file_with_a_map_of_the_wrong_shape_refused(step_model, tmp_path):
    path = tmp_path / "m.npz"
    step_model.save(path)
    arrays = dict(np.load(path))
    arrays["g_input_map"] = np.ones((2, 3))
    bad = tmp_path / "bad.npz"
    np.savez(bad, **arrays)
    with pytest.raises(DataError, match="g_input_map"):
        FittedVHGPR.load(bad)


def test_trainer_refuses_a_map_of_the_wrong_width():
    X, y, _ = _step_noise_data(30, 7)
    with pytest.raises(DataError, match="g_input_map acts on 3 inputs"):
        VHGPR(n_restarts=1, g_input_map=np.ones((2, 3))).fit(X, y)
    with pytest.raises(ConfigError, match="g_input_names"):
        VHGPR(g_input_map=STEP_MAP, g_input_names=("a",))
