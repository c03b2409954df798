"""Refinement moves (microctl.control.refine, microctl collect --refine).

Independent answers: the episode structure recounted from the yielded moves; the explored pose
checked against the noise uncertainty of every candidate recomputed here; the on-policy move
against the controller's own solve from the same state; the ranges from the stage's limits.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from microctl.backends.collect import execute_moves
from microctl.backends.simulated import SimulatedStage
from microctl.control.context import ByDirection
from microctl.control.controller import ControllerSettings, OptimalController
from microctl.control.refine import EXPLORE_RATIO, check_target_range, explore, refinement_moves
from microctl.errors import ConfigError, SolveError
from microctl.measurement.design import training_moves
from microctl.models.afm import AnalyticForwardModel
from microctl.models.eafm import EAFM
from microctl.models.training import ResidualModelSettings, residual_dataset, train_residual_model
from microctl.stage.config import load_stage_config

ROOT = Path(__file__).resolve().parents[2]
TARGETS_UM = (0.0, 30.0)


@pytest.fixture(scope="module")
def trained():
    """sim_paper (stick-slip on PZT 4), 60 covering moves, the default model and controller."""
    cfg = load_stage_config(ROOT / "configs/stage/sim_paper.yaml")
    afm = AnalyticForwardModel(cfg.stage)
    with SimulatedStage(cfg, seed=5) as st:
        S, U, T = execute_moves(st, training_moves(afm, "covering", 60, seed=5))

    class Log:
        s_prev, u, t = S, U, T

    eafm = EAFM(afm, train_residual_model(residual_dataset(Log, afm), afm, ResidualModelSettings()))
    return cfg, afm, eafm, OptimalController(eafm, ControllerSettings())


def _run(cfg, eafm, ctrl, n, strategy="uncertainty", seed=0):
    """Execute n refinement moves on a fresh stage; the moves and the state before each."""
    out = []
    with SimulatedStage(cfg, seed=11) as st:
        for mv in refinement_moves(ByDirection(eafm, lambda e: ctrl), n, TARGETS_UM, np.random.default_rng(seed),
                                   lambda: st.state, strategy=strategy):
            out.append((mv, st.state.copy()))
            st.move(mv.u)
    return out


def test_episodes_start_at_zero_and_climb_through_sorted_targets_in_range(trained):
    cfg, afm, eafm, ctrl = trained
    moves = _run(cfg, eafm, ctrl, 13)
    assert len(moves) == 13
    labels = [mv.label for mv, _ in moves]
    assert [i for i, lab in enumerate(labels) if lab == "zero"] == [0, 5, 10]  # 1 return + 4 targets per episode
    for start in (0, 5, 10):
        targets = [mv.target_um for mv, _ in moves[start + 1:start + 5]]
        assert targets == sorted(targets)
        assert all(TARGETS_UM[0] <= t <= TARGETS_UM[1] for t in targets)
    for mv, s in moves:
        q = afm.q_of(mv.u)
        assert np.all(q >= afm.lo - 1e-9) and np.all(q <= afm.hi + 1e-9)
        if mv.label == "zero":
            assert np.array_equal(mv.u, np.zeros(afm.n_p))
        else:  # every refinement move reaches its target on the EAFM's mean
            assert abs(float(eafm.predict(s, mv.u).t_mean[0]) - mv.target_um) < 1e-4


def test_the_explored_pose_is_the_least_certain_candidate(trained):
    cfg, afm, eafm, ctrl = trained
    explored = 0
    for mv, s in _run(cfg, eafm, ctrl, 10):
        if mv.label == "zero":
            continue
        u_opt = ctrl.solve(mv.target_um, s).u  # the controller's choice, solved again from the same state
        U, obj = ctrl.candidates(mv.target_um, s, max_ratio=EXPLORE_RATIO)
        assert np.all(obj <= EXPLORE_RATIO * obj.min() + 1e-12)
        pool = np.vstack([u_opt[None, :], U])
        unc = np.array([float(eafm.noise_uncertainty(s, p[None, :])[0]) for p in pool])
        assert float(eafm.noise_uncertainty(s, mv.u[None, :])[0]) == pytest.approx(unc.max(), rel=1e-9)
        explored += mv.label == "explore"
    assert explored >= 1  # on this rig some candidate is less certain than the controller's choice


def test_on_policy_moves_are_the_controllers_choice(trained):
    cfg, afm, eafm, ctrl = trained
    for mv, s in _run(cfg, eafm, ctrl, 5, strategy="on_policy"):
        if mv.label != "zero":
            assert mv.label == "eafm"
            np.testing.assert_allclose(mv.u, ctrl.solve(mv.target_um, s).u, atol=1e-6)


def test_a_target_that_cannot_be_solved_is_skipped(trained):
    cfg, afm, eafm, _ = trained

    class Failing:
        calls = 0

        def solve(self, target, s, u_init=None):
            Failing.calls += 1
            raise SolveError("no solution")

    moves = list(refinement_moves(ByDirection(eafm, lambda e: Failing()), 3, TARGETS_UM, np.random.default_rng(0),
                                  lambda: np.zeros(afm.n_s), strategy="on_policy"))
    assert [mv.label for mv in moves] == ["zero"] * 3  # each episode's four targets fail: only the returns
    assert Failing.calls == 8


def test_target_range_and_strategy_are_checked(trained):
    cfg, afm, eafm, ctrl = trained
    lo, hi = afm.t_range()
    assert check_target_range(eafm, None, "x") == (lo, hi)
    assert check_target_range(eafm, (0, 30), "x") == (0.0, 30.0)
    with pytest.raises(ConfigError, match=r"--target-range: 0,1000 µm is not inside the stage's reachable range"):
        check_target_range(eafm, (0, 1000), "--target-range")
    with pytest.raises(ConfigError, match="LO < HI"):
        check_target_range(eafm, (5, 5), "--target-range")
    with pytest.raises(ConfigError, match="uncertainty, on_policy"):
        next(refinement_moves(ByDirection(eafm, lambda e: ctrl), 2, TARGETS_UM, np.random.default_rng(0), lambda: None,
                              strategy="greedy"))


def test_explore_keeps_the_controllers_choice_when_it_is_the_least_certain(trained, monkeypatch):
    cfg, afm, eafm, ctrl = trained
    s = np.zeros(afm.n_s)
    u_opt = ctrl.solve(12.0, s).u
    monkeypatch.setattr(type(eafm), "noise_uncertainty", lambda self, s, U: -np.arange(len(U), dtype=float))
    u, label = explore(ctrl, eafm, 12.0, s, u_opt)
    assert label == "eafm" and np.array_equal(u, u_opt)
