"""Diagnosis building blocks: identifiability, noise fit, tests, extended model, the CLI."""

from __future__ import annotations

import json

import numpy as np
import pytest
from conftest import CONFIGS

from microctl.backends.simulated import SimulatedStage
from microctl.cli import main
from microctl.diagnosis.causes import (
    CauseSpec,
    candidate_specs,
    fit_mean,
    merge_effects,
)
from microctl.diagnosis.data import data_from_arrays
from microctl.diagnosis.noise import fit_noise
from microctl.diagnosis.residuals import breusch_pagan, generic_basis, structure_f_test
from microctl.models.afm import AnalyticForwardModel
from microctl.models.extended import ExtendedForwardModel
from microctl.stage.causes import (
    ActuatorGain,
    Backlash,
    ContactOffset,
    Effects,
    SensorScale,
    ToolOffset,
)
from microctl.stage.config import load_stage_config
from microctl.testing.plant import simulate, with_effects


@pytest.fixture(scope="module")
def cfg():
    return load_stage_config(CONFIGS / "stage" / "sim_paper.yaml")


def _noise_free(cfg, effects, n=150, seed=0):
    """Readings of the physics with ``effects`` and no noise, for space-filling moves."""
    data = simulate(cfg, Effects(), n, seed=seed)
    t = ExtendedForwardModel(cfg.stage, effects).predict_q(data.q, direction=data.direction, time_s=data.time_s).t
    return data.with_t(t)


def _c(stage, i):
    """c_i = w · pinv(K) e_i: reading per µm of ball i in the rigid least-squares limit."""
    afm = AnalyticForwardModel(stage)
    return float(afm.w @ np.linalg.pinv(afm.K)[:, i - 1])


@pytest.mark.parametrize("act", [1, 2, 3, 4])
def test_contact_offset_is_reproduced_by_a_tool_offset(cfg, act):
    """First order: δt = −c_i (dy·rx − dx·ry), a tool offset (−c_i dx, −c_i dy) gives the same."""
    dx, dy = 0.8, -0.5
    data = _noise_free(cfg, Effects(contact_offset=(ContactOffset(act, dx, dy),)))
    spec = next(s for s in candidate_specs(cfg.stage) if s.cause == "tool_offset")
    fit = fit_mean(cfg.stage, Effects(), [spec], data)
    rms = np.sqrt(fit.rss / data.n)
    signal = np.sqrt(np.mean((data.t - fit_mean(cfg.stage, Effects(), [], data).pred) ** 2))
    assert signal > 0.3  # the offset is visible ...
    assert rms < 2e-3 * signal + 1e-3  # ... and the tool offset reproduces it to ~0.1 % (elastic terms)
    c = _c(cfg.stage, act)
    np.testing.assert_allclose(fit.theta, [-c * dx, -c * dy], rtol=0.05)


def test_gain_changes_the_z_coefficient_offsets_do_not(cfg):
    """The exact argument: K has a column of ones, so offsets keep t's z coefficient at 1."""
    stage = cfg.stage
    U = np.array([[10.0, 0, 0], [20.0, 0, 0]])
    q = U @ AnalyticForwardModel(stage).K.T
    ones = np.ones_like(q)
    for eff, changes in [
        (Effects(contact_offset=(ContactOffset(2, 1.0, 1.0),)), False),
        (Effects(tool_offset=ToolOffset(1.0, -1.0)), False),
        (Effects(actuator_gain=(ActuatorGain(2, 1.1),)), True),
        (Effects(sensor_scale=SensorScale(1.1)), True),
    ]:
        t = ExtendedForwardModel(stage, eff).predict_q(q, direction=ones).t
        slope = (t[1] - t[0]) / 10.0
        assert bool(abs(slope - 1.0) > 0.01) == changes, eff


def test_merge_effects_replaces_same_cause_and_actuator():
    base = Effects(actuator_gain=(ActuatorGain(1, 1.1), ActuatorGain(3, 0.9)))
    spec = CauseSpec(ActuatorGain, 3, (0.2,), (5.0,))
    out = merge_effects(base, [(spec, [0.95])])
    assert out.actuator_gain == (ActuatorGain(1, 1.1), ActuatorGain(3, 0.95))
    assert spec.start_from(base) == (0.9,)


def test_extended_model_matches_the_simulator_with_backlash(cfg):
    eff = Effects(backlash=(Backlash(2, 0.3),), actuator_gain=(ActuatorGain(4, 0.9),))
    sim = SimulatedStage(with_effects(cfg, eff))
    ext = ExtendedForwardModel(cfg.stage, eff)
    rng = np.random.default_rng(0)
    afm = AnalyticForwardModel(cfg.stage)
    for u in afm.workspace.sample(5, rng):
        s = sim.state.copy()
        expected = sim.true_mean(s, u)
        got = ext.predict(s, u, time_s=sim.time_s + 1.0)[0]
        assert got == pytest.approx(expected, abs=1e-9)
        sim.move(u)


def test_fit_noise_recovers_friction():
    rng = np.random.default_rng(1)
    n = 400
    dq = rng.uniform(-30, 30, (n, 4))
    J = np.tile([-1.1, -0.7, 1.6, 1.2], (n, 1))
    std = np.sqrt(0.05**2 + (J[:, 2] * 0.03 * dq[:, 2]) ** 2)
    r = std * rng.standard_normal(n)
    f0 = fit_noise(r, J, dq)
    f1 = fit_noise(r, J, dq, (3,))
    assert f1.bic < f0.bic - 50
    assert abs(f1.std_per_um[0] - 0.03) < 4 * f1.stderr_per_um[0]
    assert abs(f1.std_um - 0.05) < 4 * f1.stderr_std_um


def test_breusch_pagan_detects_scatter_growing_with_the_step():
    rng = np.random.default_rng(2)
    z = rng.uniform(0, 30, (300, 1))
    assert breusch_pagan(rng.standard_normal(300), z).p_value > 1e-3
    assert breusch_pagan((0.1 + z[:, 0]) * rng.standard_normal(300), z).p_value < 1e-6


def test_structure_f_test_has_its_nominal_size(cfg):
    """Under the null (white noise) the F-test rejects at about its level."""
    data = simulate(cfg, Effects(), 150, seed=3)
    rng = np.random.default_rng(4)
    p = np.array([structure_f_test(rng.standard_normal(data.n), data).p_value for _ in range(200)])
    assert 0.0 <= np.mean(p < 0.05) <= 0.1
    # intercept, cubic in u, directions, time; directions × (u, u²) and time², time³ when n >= 3 p
    big = simulate(cfg, Effects(), 200, seed=3)
    assert generic_basis(big).shape == (200, 1 + 19 + 4 + 1 + 4 * 9 + 2)
    assert generic_basis(data).shape == (150, 1 + 19 + 4 + 1)


def test_data_from_arrays_directions_keep_sign_on_zero_steps():
    q = np.array([[1.0, 0], [0.5, 0], [0.5, 1.0]])
    d = data_from_arrays(np.zeros((3, 3)), q, np.zeros(3))
    np.testing.assert_array_equal(d.direction, [[1, 1], [-1, 1], [-1, 1]])


# ---- command line ---------------------------------------------------------------------


@pytest.mark.slow
def test_cli_diagnose_writes_report_figures_and_extended_config(cfg, tmp_path, capsys):
    cfg_path = CONFIGS / "stage" / "table1.yaml"
    table1 = load_stage_config(cfg_path)
    sim_cfg = with_effects(table1, Effects(actuator_gain=(ActuatorGain(3, 0.93),)))
    log = tmp_path / "log.csv"
    simulate(sim_cfg, Effects(actuator_gain=(ActuatorGain(3, 0.93),)), 150, seed=1, log_path=log)
    out = tmp_path / "out"
    rc = main(["diagnose", str(log), "--config", str(cfg_path), "--out", str(out), "--no-gp", "--quiet"])
    assert rc == 0
    rep = json.loads((out / "report.json").read_text())
    for key in ("rows", "discrepancy", "accepted", "mean_causes", "noise_causes", "gain"):
        assert key in rep
    assert set(rep["discrepancy"]) >= {"significant", "afm_rmse_um", "noise_std_um", "p_value"}
    assert rep["accepted"]["mean"] == ["actuator_gain"]
    first = rep["mean_causes"][0]
    assert set(first) >= {"cause", "params", "stderr", "delta_bic", "equivalent"}
    assert first["params"]["actuator"] == 3 and abs(first["params"]["gain"] - 0.93) < 0.005
    assert set(rep["gain"]) >= {"method", "rmse_um", "p_value"}
    assert (out / "report.md").read_text().startswith("# Model-discrepancy diagnosis")
    for f in rep["figures"]["files"]:
        assert (out / f).stat().st_size > 1000
    ext = load_stage_config(out / "extended.yaml")
    assert ext.stage.corrections.actuator_gain[0].actuator == 3
    assert ext.stage.corrections.actuator_gain[0].gain == pytest.approx(first["params"]["gain"])


def test_cli_diagnose_input_errors_exit_2(tmp_path, capsys):
    cfg_path = CONFIGS / "stage" / "table1.yaml"
    log = tmp_path / "short.csv"
    log.write_text("seq,u_z,u_rx,u_ry,q1,q2,q3,q4,t\n0,1,0,0,1,1,1,1,1\n")
    rc = main(["diagnose", str(log), "--config", str(cfg_path), "--out", str(tmp_path / "o")])
    assert rc == 2
    err = capsys.readouterr().err
    assert "short.csv" in err and "at least" in err and "Traceback" not in err
    bad = tmp_path / "bad.csv"
    bad.write_text("seq,u_z,u_rx,q1,q2,q3,q4,t\n0,1,0,1,1,1,1,1\n")
    assert main(["diagnose", str(bad), "--config", str(cfg_path), "--out", str(tmp_path / "o")]) == 2
    assert "u_ry" in capsys.readouterr().err


@pytest.mark.slow
def test_rediagnosing_with_the_extended_config_finds_nothing(tmp_path):
    """extended.yaml carries the accepted causes (incl. dynamic ones): the same data is then clean."""
    cfg_path = CONFIGS / "stage" / "table1.yaml"
    table1 = load_stage_config(cfg_path)
    eff = Effects(backlash=(Backlash(1, 0.3),))
    log = tmp_path / "log.csv"
    simulate(table1, eff, 150, seed=2, log_path=log)
    out1, out2 = tmp_path / "a", tmp_path / "b"
    assert main(["diagnose", str(log), "--config", str(cfg_path), "--out", str(out1), "--no-gp", "--quiet"]) == 0
    rep1 = json.loads((out1 / "report.json").read_text())
    assert rep1["accepted"]["mean"] == ["backlash"]
    assert main(["diagnose", str(log), "--config", str(out1 / "extended.yaml"), "--out", str(out2), "--no-gp",
                 "--quiet"]) == 0
    rep2 = json.loads((out2 / "report.json").read_text())
    assert rep2["discrepancy"]["significant"] is False
    assert rep2["accepted"]["mean"] == []


@pytest.mark.slow
def test_log_without_time_has_no_drift_candidate(cfg):
    from microctl.diagnosis.pipeline import run_diagnosis

    data = simulate(cfg, Effects(actuator_gain=(ActuatorGain(1, 1.05),)), 100, seed=3)
    no_time = data_from_arrays(data.u, data.q, data.t, q_prev=data.q_prev, t_prev=data.t_prev)
    rep = run_diagnosis(cfg, no_time, gain=False).report
    assert rep["accepted"]["mean"] == ["actuator_gain"]
    assert all(e["cause"] != "drift" for e in rep["mean_causes"])
    assert all(w["variable"] != "time_s" for w in rep["discrepancy"]["where"])


@pytest.mark.slow
def test_a_gauge_zero_offset_is_a_nuisance_not_a_discrepancy(cfg):
    """Readings relative to one noisy zero reading: a constant offset must not be flagged."""
    from microctl.diagnosis.pipeline import run_diagnosis

    data = simulate(cfg, Effects(), 200, seed=4)
    sigma = cfg.backend.simulated.gauge_noise_std_um
    rep = run_diagnosis(cfg, data.with_t(data.t + 2 * sigma), gain=False).report
    assert rep["discrepancy"]["significant"] is False
    assert rep["accepted"]["mean"] == []
    z, se = rep["nuisance"]["gauge_zero_um"], rep["nuisance"]["stderr"]["gauge_zero_um"]
    assert abs(z - 2 * sigma) <= 4 * se  # se = σ/√n


def test_diagnosis_gp_likelihood_gradient_matches_finite_differences():
    """The residual GP of the diagnosis (microctl.gp.kernels' SE + white noise): analytic gradient
    of the negative log marginal likelihood against central differences."""
    from microctl.diagnosis.residuals import _gp_nll

    rng = np.random.default_rng(5)
    X, y = rng.standard_normal((15, 3)), rng.standard_normal(15)
    theta = np.array([0.2, -0.4, 0.6, -0.3, -1.5])
    _, g = _gp_nll(theta, X, y)
    fd = np.array([(_gp_nll(theta + e, X, y)[0] - _gp_nll(theta - e, X, y)[0]) / 2e-6
                   for e in np.eye(theta.size) * 1e-6])
    np.testing.assert_allclose(g, fd, rtol=1e-6, atol=1e-8)
