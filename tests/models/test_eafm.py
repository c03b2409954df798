"""The EAFM CasADi graph against the NumPy reference (FittedVHGPR.predict + AFM)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import casadi as ca
import numpy as np
import pytest

import microctl.gp.vhgpr as vh
from microctl.errors import ConfigError
from microctl.gp.vhgpr import VHGPR
from microctl.models.afm import AnalyticForwardModel
from microctl.models.eafm import EAFM, bind_to_stage
from microctl.models.training import actuator_step_features
from microctl.stage.config import load_stage_config
from microctl.testing import fixed_hyperparameter_model

ROOT = Path(__file__).resolve().parents[2]
NAMES = ("t_mean", "f_mean", "f_var", "g_mean", "g_var")


@pytest.fixture(scope="module")
def afm() -> AnalyticForwardModel:
    return AnalyticForwardModel(load_stage_config(ROOT / "configs/stage/table1.yaml").stage)


def _model(afm: AnalyticForwardModel, n: int = 60, seed: int = 0):
    rng = np.random.default_rng(seed)
    U = afm.workspace.sample(n, rng)
    S = np.column_stack([rng.uniform(0, 30, n), rng.uniform(0, 32, (n, afm.n_q))])
    ln = np.log(0.1**2) - 2.0 * np.exp(-((U[:, 1] - 0.4) ** 2 + U[:, 2] ** 2) / 0.1)
    y = 0.3 * np.sin(U[:, 0] / 8) + 0.2 * U[:, 1] + 0.05 * S[:, 0] / 30 + np.exp(ln / 2) * rng.standard_normal(n)
    m = fixed_hyperparameter_model(np.hstack([S, U]), y, ln,
                                   f_log_lengthscales=np.array([1.0, 2, 2, 2, 2, 0.0, -0.5, -0.5]))
    return bind_to_stage(m, afm)


def _physical_model(afm: AnalyticForwardModel, n: int = 50, seed: int = 0):
    """A fitted residual VHGPR with every part the default uses and more: the physical noise
    prior (features dq_i), the affine trend on u, f's SE part on, and the noise parameters'
    variance propagated into g (so every branch of the graph is compared)."""
    rng = np.random.default_rng(seed)
    U = afm.workspace.sample(n, rng)
    S = np.column_stack([rng.uniform(0, 30, n), rng.uniform(0, 32, (n, afm.n_q))])
    dq = U @ afm.K.T - S[:, 1:]
    y = 0.02 * U[:, 0] + 0.3 * U[:, 1] + np.sqrt(0.05**2 + (0.03 * dq[:, 3]) ** 2) * rng.standard_normal(n)
    m = VHGPR(linear=(5, 6, 7), linear_prior_var=10.0, se="on", noise_features=actuator_step_features(afm),
              n_restarts=1, max_iter=40, propagate_noise_parameter_uncertainty=True).fit(np.hstack([S, U]), y)
    return bind_to_stage(m, afm)


@pytest.fixture(scope="module", params=["paper_hgp", "physical"])
def eafm(afm, request):
    """Every EAFM test runs with the paper's noise model (fixed hyperparameters) and with the
    physical noise model, affine trend and propagated parameter variance (fitted)."""
    model = _model(afm) if request.param == "paper_hgp" else _physical_model(afm)
    return EAFM(afm, model)


def _points(afm, m, seed=1):
    rng = np.random.default_rng(seed)
    U = afm.workspace.sample(m, rng)
    S = np.column_stack([rng.uniform(0, 30, m), rng.uniform(0, 32, (m, afm.n_q))])
    return S, U


def test_graph_equals_numpy_reference(afm, eafm):
    S, U = _points(afm, 25)
    out = eafm.function(s=ca.DM(S.T), u=ca.DM(U.T))
    ref = eafm.model.predict(np.hstack([S, U]))
    want = {"t_mean": afm.t_of(U) + ref.f_mean, "f_mean": ref.f_mean, "f_var": ref.f_var,
            "g_mean": ref.g_mean, "g_var": ref.g_var}
    for k in NAMES:
        got = np.array(out[k]).ravel()
        np.testing.assert_allclose(got, want[k], rtol=1e-9, atol=0, err_msg=k)
    np.testing.assert_allclose(np.array(out["q"]).T, U @ afm.K.T, rtol=1e-12, atol=1e-12)
    assert eafm.function.name_in() == ["s", "u"]
    assert eafm.function.name_out() == ["t_mean", "f_mean", "f_var", "g_mean", "g_var", "q"]


def test_graph_gradient_matches_finite_differences(afm, eafm):
    s = ca.MX.sym("s", afm.n_s)
    u = ca.MX.sym("u", afm.n_p)
    e = eafm.expressions(s, u, NAMES)
    x = ca.vertcat(s, u)
    jac = ca.Function("eafm_jacobian", [s, u], [ca.jacobian(ca.vertcat(*[e[k] for k in NAMES]), x)])
    S, U = _points(afm, 4, seed=3)
    # scaled steps: inputs in µm and mrad
    h = np.concatenate([np.full(afm.n_s, 1e-4), [1e-4, 1e-6, 1e-6]])
    for s0, u0 in zip(S, U):
        J = np.array(jac(s0, u0))
        x0 = np.concatenate([s0, u0])
        for j in range(x0.size):
            xp, xm = x0.copy(), x0.copy()
            xp[j] += h[j]
            xm[j] -= h[j]
            fp = np.array([[np.array(eafm.function(xp[:afm.n_s], xp[afm.n_s:])[i]).item() for i in range(5)]])
            fm = np.array([[np.array(eafm.function(xm[:afm.n_s], xm[afm.n_s:])[i]).item() for i in range(5)]])
            fd = ((fp - fm) / (2 * h[j])).ravel()
            np.testing.assert_allclose(J[:, j], fd, rtol=1e-5, atol=1e-7 * (1 + np.abs(J[:, j]).max()))


def test_vectorised_seeding_helpers_match(afm, eafm):
    S, U = _points(afm, 10, seed=4)
    s = S[0]
    ref = eafm.predict(s, U)
    t, dt = eafm.mean_and_grad_u(s, U)
    np.testing.assert_allclose(t, ref.t_mean, rtol=1e-12)
    np.testing.assert_allclose(eafm.g_mean_np(s, U), ref.g_mean, rtol=1e-12)
    # f's variance alone (the objective's epistemic term, the least-motion rule): predict's, bit for bit
    np.testing.assert_array_equal(eafm.f_var_np(s, U), ref.f_var)
    assert np.all(ref.f_var > 0)  # the comparison is not between two arrays of zeros
    sym_s, sym_u = ca.MX.sym("s", afm.n_s), ca.MX.sym("u", afm.n_p)
    g = ca.Function("g", [sym_s, sym_u], [ca.gradient(eafm.expressions(sym_s, sym_u, ("t_mean",))["t_mean"], sym_u)])
    for k in range(U.shape[0]):
        np.testing.assert_allclose(np.array(g(s, U[k])).ravel(), dt[k], rtol=1e-9, atol=1e-12)


def test_model_file_round_trip(afm, eafm, tmp_path):
    path = tmp_path / "model.npz"
    eafm.model.save(path)
    e2 = EAFM(afm, path)
    S, U = _points(afm, 5, seed=5)
    np.testing.assert_allclose(e2.predict(S, U).t_mean, eafm.predict(S, U).t_mean, rtol=1e-14)


def test_geometry_hash_mismatch_refused(afm, eafm, tmp_path):
    path = tmp_path / "other.npz"
    info = {k: v for k, v in eafm.model.info.items() if k != "stage"}  # no record of the geometry alone
    dataclasses.replace(eafm.model, geometry_hash="0" * 64, info=info).save(path)
    with pytest.raises(ConfigError, match="other.npz.*another stage geometry"):
        EAFM(afm, path)
    # the same geometry alone recorded: only the model corrections differ (issue 22 item 5)
    dataclasses.replace(eafm.model, geometry_hash="0" * 64).save(path)
    with pytest.raises(ConfigError, match="other.npz.*same geometry with other model corrections"):
        EAFM(afm, path)
    unbound = tmp_path / "unbound.npz"
    dataclasses.replace(eafm.model, geometry_hash=None).save(unbound)
    with pytest.raises(ConfigError, match="unbound.npz.*not bound"):
        EAFM(afm, unbound)


def test_wrong_input_dimension_refused(afm):
    rng = np.random.default_rng(0)
    X = rng.standard_normal((20, 3))
    m = fixed_hyperparameter_model(X, X[:, 0], np.full(20, -4.0), f_log_lengthscales=np.zeros(3))
    with pytest.raises(ConfigError, match="3 inputs"):
        EAFM(afm, bind_to_stage(m, afm))


def test_noise_helpers_match_the_reference(afm, eafm):
    """g_np, g_joint and noise_uncertainty against FittedVHGPR.predict (independent NumPy path)."""
    S, U = _points(afm, 6, seed=6)
    s = S[0]
    ref = eafm.predict(s, U)
    mean, var = eafm.g_np(s, U)
    np.testing.assert_allclose(mean, ref.g_mean, rtol=1e-12)
    np.testing.assert_allclose(var, ref.g_var, rtol=1e-9, atol=1e-12)
    jm, jc = eafm.g_joint(s, U)
    np.testing.assert_allclose(jm, ref.g_mean, rtol=1e-12)
    np.testing.assert_allclose(np.diag(jc), ref.g_var, rtol=1e-9, atol=1e-12)
    assert np.all(np.linalg.eigvalsh(jc) > -1e-9)
    unc = eafm.noise_uncertainty(s, U)
    assert np.all(unc >= var - 1e-12)
    # the least-motion rule's three from one standardisation: g_joint's and f_var_np's arrays
    m2, c2, fv = eafm.g_joint_and_f_var(s, U)
    assert np.array_equal(m2, jm) and np.array_equal(c2, jc) and np.array_equal(fv, eafm.f_var_np(s, U))


def test_negligible_gp_variance_is_bounded_consistently(afm):
    """With g's GP prior variance <= 1e-4 (vhgpr.G_GP_VAR_NEGLIGIBLE) its posterior variance is
    taken as the prior bound k**: the graph equals the NumPy prediction, and the value lies
    between the exact variance and the exact variance + 1e-4 (conservative, never below)."""
    exact_model = _model(afm)
    tiny = dataclasses.replace(exact_model, g_log_signal_var=float(np.log(5e-5)))
    S, U = _points(afm, 12, seed=9)
    X = np.hstack([S, U])
    bounded = tiny.predict(X).g_var
    old = vh.G_GP_VAR_NEGLIGIBLE
    try:  # the exact variance of the same model, with the rule switched off
        vh.G_GP_VAR_NEGLIGIBLE = 0.0
        want = tiny.predict(X).g_var
    finally:
        vh.G_GP_VAR_NEGLIGIBLE = old
    assert np.all(bounded >= want - 1e-15) and np.all(bounded <= want + 1e-4)
    e = EAFM(afm, tiny)
    got = np.array(e.function(s=ca.DM(S.T), u=ca.DM(U.T))["g_var"]).ravel()
    np.testing.assert_allclose(got, bounded, rtol=1e-12)
    mean, var = e.g_np(S[0], U)
    np.testing.assert_allclose(var, tiny.predict(np.hstack([np.tile(S[0], (len(U), 1)), U])).g_var, rtol=1e-12)
