"""The simulated stage's truth (true_mean / true_var): exact where first order is exact, Monte Carlo
where a ball may change contact, and in both cases what repeated moves of the stage itself give."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from microctl.backends.simulated import TRUTH_DRAWS, SimulatedStage
from microctl.models.afm import AnalyticForwardModel
from microctl.stage.causes import SensorNonlinearity
from microctl.stage.config import load_stage_config

ROOT = Path(__file__).resolve().parents[2]


def _repeat_moves(cfg, s_moves: np.ndarray, u: np.ndarray, n: int, seed: int) -> np.ndarray:
    """Readings of the move u from the state the moves ``s_moves`` leave, n times on fresh stages
    (each its own noise stream): an estimate independent of the truth's own draws."""
    out = np.empty(n)
    for k in range(n):
        with SimulatedStage(cfg, seed=seed + k) as st:
            for v in s_moves:
                st.move(v)
            out[k] = st.move(u).t_um
    return out


@pytest.mark.parametrize("config", ["sim_paper.yaml", "sim_paper_scale.yaml"])
def test_truth_matches_repeated_moves_of_the_stage(config):
    """Mean and std of 400 executed moves (the stage's own random streams) agree with the truth
    within 4 standard errors (mean: 4 sd/sqrt(400); std: 4 sd/sqrt(800), plus the truth's own Monte
    Carlo error where it is not exact, 4 sd/sqrt(2 TRUTH_DRAWS))."""
    cfg = load_stage_config(ROOT / "configs/stage" / config)
    afm = AnalyticForwardModel(cfg.stage)
    rng = np.random.default_rng(5)
    prior = afm.workspace.sample(2, rng)
    U = afm.workspace.sample(2, rng)
    for u in U:
        with SimulatedStage(cfg, seed=0) as st:
            for v in prior:
                st.move(v)
            mean, var = st.true_moments(st.state, u[None, :])
        t = _repeat_moves(cfg, prior, u, 400, seed=10_000)
        sd = float(np.sqrt(var[0]))
        assert abs(t.mean() - mean[0]) <= 4 * sd / np.sqrt(400) + 1e-9
        rel = 4 / np.sqrt(800) + 4 / np.sqrt(2 * TRUTH_DRAWS)
        assert abs(t.std(ddof=1) / sd - 1) <= rel


def test_monte_carlo_equals_the_exact_formula_where_no_ball_can_lift():
    """On sim_paper almost every pose is exact; there the Monte Carlo branch (forced) gives the
    same moments within its sampling error (std within 4/sqrt(2 TRUTH_DRAWS), mean to 1e-6 µm: the
    antithetic pairs cancel the odd terms of a linear map)."""
    cfg = load_stage_config(ROOT / "configs/stage/sim_paper.yaml")
    afm = AnalyticForwardModel(cfg.stage)
    U = afm.workspace.sample(50, np.random.default_rng(1))
    with SimulatedStage(cfg, seed=0) as st:
        mean, var = st.true_moments(st.state, U)
        dq, pred = st._oracle(st.state, U)
        q_act = st.truth.actual_positions(pred.q, st.truth.next_direction(dq, st.direction))
        exact = st._first_order_exact(pred, dq, q_act)
        mc_mean, mc_var = st._monte_carlo(q_act, dq)
    assert exact.mean() > 0.8
    assert np.max(np.abs(mc_mean - mean)[exact]) < 1e-6
    assert np.max(np.abs(np.sqrt(mc_var / var) - 1)[exact]) < 4 / np.sqrt(2 * TRUTH_DRAWS)


def test_quadratic_gauge_moments_are_exact():
    """A quadratic gauge on a stage where no ball lifts: the exact moments of a quadratic of a
    Gaussian agree with the forced Monte Carlo (mean within 4 MC standard errors)."""
    cfg = load_stage_config(ROOT / "configs/stage/sim_paper.yaml")
    sim = cfg.backend.simulated
    effects = sim.effects.with_(SensorNonlinearity.make(None, (0.01,)))
    cfg2 = replace(cfg, backend=replace(cfg.backend, simulated=replace(sim, effects=effects)))
    afm = AnalyticForwardModel(cfg2.stage)
    U = afm.workspace.sample(30, np.random.default_rng(2))
    with SimulatedStage(cfg2, seed=0) as st:
        assert not st.model.sensor.is_linear
        mean, var = st.true_moments(st.state, U)
        dq, pred = st._oracle(st.state, U)
        q_act = st.truth.actual_positions(pred.q, st.truth.next_direction(dq, st.direction))
        exact = st._first_order_exact(pred, dq, q_act)
        mc_mean, mc_var = st._monte_carlo(q_act, dq)
    assert exact.mean() > 0.8
    se = np.sqrt(var / TRUTH_DRAWS)
    assert np.all(np.abs(mc_mean - mean)[exact] <= 4 * se[exact])
    assert np.max(np.abs(np.sqrt(mc_var / var) - 1)[exact]) < 4 / np.sqrt(2 * TRUTH_DRAWS)


@pytest.mark.parametrize("config", ["sim_paper.yaml", "sim_paper_scale.yaml"])
def test_enumerated_equilibrium_equals_the_newton_solver(config):
    """The Monte Carlo's contact-set enumeration and the simulator's semismooth Newton give the same
    poses (to 1e-9 µm) on random ball heights, lift-offs included."""
    from microctl.backends.simulated import enumerated_equilibrium
    from microctl.stage.physics import ball_heights, solve_equilibrium

    cfg = load_stage_config(ROOT / "configs/stage" / config)
    with SimulatedStage(cfg, seed=0) as st:
        q = np.random.default_rng(3).uniform(-5, 37, size=(500, cfg.stage.n_act))
        h = ball_heights(st.model, q)
        p_newton, active = solve_equilibrium(st.model, h)
        p_enum = enumerated_equilibrium(st.model, h)
    assert (~active).any()  # some balls lift off
    np.testing.assert_allclose(p_enum, p_newton, atol=1e-9, rtol=0)


def test_truth_variance_where_balls_lift_off_is_never_below_the_gauge_noise():
    """On the paper-scale rig (stick-slip 0.5 µm per µm, a ball 2 µm low) many moves are Monte
    Carlo; their variance is at least the gauge noise's (the gauge noise is added to every
    reading), and within its sampling error of the plain sample variance of the same draws where
    the control variate does not apply. Regression: the variance estimate with the control
    variate at coefficient 1 went negative where a ball lifts off in most draws (the experiment
    runner died with a math domain error). Tolerance: the two estimates use the same 1024 draws;
    the adjusted one differs from the plain one by beta^2 (exact var_L - sample var_L), at most
    a few sampling errors 4 sqrt(2/1024) of the linear part."""
    cfg = load_stage_config(ROOT / "configs/stage/sim_paper_scale.yaml")
    afm = AnalyticForwardModel(cfg.stage)
    rng = np.random.default_rng(11)
    gauge = cfg.backend.simulated.gauge_noise_std_um ** 2
    n_mc = 0
    for start in afm.workspace.sample(6, rng):
        with SimulatedStage(cfg, seed=0) as st:
            st.move(start)
            U = afm.workspace.sample(80, rng)
            mean, var = st.true_moments(st.state, U)
            dq, pred = st._oracle(st.state, U)
            q_act = st.truth.actual_positions(pred.q, st.truth.next_direction(dq, st.direction))
            mc = ~st._first_order_exact(pred, dq, q_act)
            _, plain = st._monte_carlo(q_act[mc], dq[mc])
        n_mc += int(mc.sum())
        assert np.all(var >= gauge * (1 - 1e-9))
        assert np.all(np.abs(var[mc] - plain) <= 4 * np.sqrt(2 / TRUTH_DRAWS) * plain + 1e-9)
    assert n_mc >= 20  # the test exercises the Monte Carlo branch
