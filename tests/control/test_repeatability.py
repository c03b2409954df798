"""Repeatability that transfers (issue 10): hidden stick-slip found and avoided, caution where
the noise model has no data.

The hidden-effect tests plant stick-slip on one actuator of the simulated stage (the contact
physics of microctl.stage.physics, a different code path from the AFM and the GP that are fitted);
the model is not told which. Collect (the default design, 200 moves), train (the default
residual model), solve 6/12/18/24 µm in sequence with the default controller, each from the
state the previous command left; every chosen pose is scored with the simulator's truth
against the oracle (the truly quietest pose that reaches the target).
"""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from microctl.backends.collect import execute_moves
from microctl.backends.simulated import SimulatedStage
from microctl.control.controller import (
    ControllerSettings,
    OptimalController,
    RedundantSet,
)
from microctl.control.oracle import OracleController
from microctl.measurement.design import training_moves
from microctl.models.afm import AnalyticForwardModel
from microctl.models.eafm import EAFM, bind_to_stage
from microctl.models.training import (
    ResidualModelSettings,
    noise_summary,
    residual_dataset,
    train_residual_model,
)
from microctl.stage.causes import ActuatorFriction, ActuatorGain
from microctl.stage.config import load_stage_config
from microctl.testing import fixed_hyperparameter_model

ROOT = Path(__file__).resolve().parents[2]
TARGETS_UM = (6.0, 12.0, 18.0, 24.0)


class _Log:
    def __init__(self, s_prev, u, t):
        self.s_prev, self.u, self.t = s_prev, u, t


def _rig(actuator: int, friction: float, seed: int):
    """Table I with gains within ±5 %, gauge 0.05 µm, 500 N preload, stick-slip on ``actuator``."""
    base = load_stage_config(ROOT / "configs/stage/sim_paper.yaml")
    rng = np.random.default_rng(seed)
    gains = tuple(ActuatorGain(actuator=i + 1, gain=float(1 + rng.uniform(-0.05, 0.05))) for i in range(4))
    eff = replace(base.backend.simulated.effects, actuator_gain=gains,
                  actuator_friction=(ActuatorFriction(actuator=actuator, std_per_um=friction),))
    sim = replace(base.backend.simulated, effects=eff, seed=seed)
    return replace(base, backend=replace(base.backend, simulated=sim))


@pytest.mark.slow
@pytest.mark.parametrize("actuator", [1, 2, 3, 4])
def test_hidden_stick_slip_is_found_and_avoided(actuator):
    """Tolerance: 1.25 x the oracle's true std (the issue's bar; on the 24-rig benchmark the
    median ratio is 1.00) and 0.1 µm of true error. Found: the default noise model selects a
    source of the planted actuator's step first and no source of another actuator."""
    cfg = _rig(actuator, 0.05, seed=100 + actuator)
    afm = AnalyticForwardModel(cfg.stage)
    with SimulatedStage(cfg, seed=actuator) as st:
        S, U, T = execute_moves(st, training_moves(afm, "covering", 200, seed=actuator))
    model = train_residual_model(residual_dataset(_Log(S, U, T), afm), afm, ResidualModelSettings())
    selected = noise_summary(model, afm)["selection"]["selected"]
    assert selected and selected[0].startswith(f"dq{actuator}:"), selected
    others = [s for s in selected if s[0] in "dqf" and s.split(":")[0].lstrip("dqf") != str(actuator)]
    assert not others, selected
    ctrl = OptimalController(EAFM(afm, model), ControllerSettings())
    with SimulatedStage(cfg, seed=1000 + actuator) as st:
        oracle = OracleController(afm, st)
        prev = None
        for target in TARGETS_UM:
            s = st.state
            res = ctrl.solve(target, s, u_init=prev)
            true_std = math.sqrt(float(st.true_var(s, res.u)))
            oracle_std = oracle.solve(target, s).predicted_std_um
            assert true_std <= 1.25 * oracle_std, (target, true_std, oracle_std, res.q)
            assert abs(float(st.true_mean(s, res.u)) - target) <= 0.1
            st.move(res.u)
            prev = res.u


@pytest.mark.slow
def test_physical_noise_model_recovers_the_planted_friction():
    """The ``physical`` noise model (every actuator's stick-slip, kept as a setting): the fitted
    friction of the planted actuator within 25 % of 0.05 x its gain (the scatter reaches the ball
    scaled by the gain) and the largest other one below a fifth of it."""
    actuator = 2
    cfg = _rig(actuator, 0.05, seed=100 + actuator)
    afm = AnalyticForwardModel(cfg.stage)
    with SimulatedStage(cfg, seed=actuator) as st:
        S, U, T = execute_moves(st, training_moves(afm, "covering", 200, seed=actuator))
    model = train_residual_model(residual_dataset(_Log(S, U, T), afm), afm,
                                 ResidualModelSettings(noise_model="physical"))
    summary = noise_summary(model, afm)["actuators"]
    gain = next(g.gain for g in cfg.backend.simulated.effects.actuator_gain if g.actuator == actuator)
    planted = summary[f"q{actuator}"]["friction_std_per_um"]
    assert planted == pytest.approx(0.05 * gain, rel=0.25)
    others = [a["friction_std_per_um"] for k, a in summary.items() if k != f"q{actuator}"]
    assert max(others) < planted / 5


def test_unvisited_corner_is_not_chosen_on_an_optimistic_prediction():
    """A planted noise landscape (fixed hyperparameters: the objective under test, not a fit):
    log noise variance -5 + 4 exp(-((t_AFM(u) - 15) / 8)^2), i.e. about -1 on the redundant
    set of the target 15 µm and lower elsewhere, and no training pose with rx above the 75th
    percentile of that set. The unvisited corner (rx from 0.33 to 1.03 mrad) is ~3 of g's
    lengthscales (exp(-0.5) standardised, 0.2 mrad) deep, so there g's posterior is its prior:
    mean mu0 (about -4.1, the average planted value) and variance exp(log sf2) = 9. The median
    r_e = exp(mu_g) prefers that corner (-4.1 < -1): the optimiser's curse this test guards
    against; the default upper quantile exp(mu_g + 1.645 s_g) is about exp(0.8) there and keeps
    the pose among the data (measured: median rx 0.64, quantile rx -0.20 mrad)."""
    afm = AnalyticForwardModel(load_stage_config(ROOT / "configs/stage/table1.yaml").stage)
    rng = np.random.default_rng(3)
    target = 15.0
    section, _ = RedundantSet(afm).grid(target, 31)  # the AFM's redundant set of the target
    section = section[afm.workspace.contains(section)]
    rx_cut = float(np.percentile(section[:, 1], 75))
    pool = afm.workspace.sample(4000, rng)
    U = pool[pool[:, 1] <= rx_cut][:300]
    S = np.column_stack([np.zeros(len(U)), np.zeros((len(U), afm.n_q))])  # from the zero state
    h = -5.0 + 4.0 * np.exp(-((afm.t_of(U) - target) / 8.0) ** 2)
    y = 0.01 * rng.standard_normal(len(U))
    m = fixed_hyperparameter_model(np.hstack([S, U]), y, h, f_log_lengthscales=np.full(8, 3.0),
                                   g_log_lengthscales=np.array([3.0, 3, 3, 3, 3, -0.5, -0.5, -0.5]),
                                   g_log_signal_var=math.log(9.0))
    eafm = EAFM(afm, bind_to_stage(m, afm))
    # eq. 4 itself for the median (the least-motion rule, on by default, would also keep it out)
    median = OptimalController(eafm, ControllerSettings(r_e="noise_median", prefer_least_motion=False)).solve(target)
    cautious = OptimalController(eafm, ControllerSettings()).solve(target)
    assert median.u[1] > rx_cut + 0.05, "the test would be vacuous: the median does not go to the corner"
    assert cautious.u[1] <= rx_cut + 0.02
    assert cautious.noise_upper_std_um < median.noise_upper_std_um


def test_diagnosed_friction_restricts_the_noise_features():
    """A stage whose corrections carry diagnosed stick-slip (extended.yaml) gets noise features
    for exactly those actuators; without, every actuator's."""
    from microctl.models.training import noise_features_for

    cfg = load_stage_config(ROOT / "configs/stage/sim_paper.yaml")
    afm = AnalyticForwardModel(cfg.stage)
    assert noise_features_for(afm).names == ("dq1", "dq2", "dq3", "dq4")
    corr = replace(cfg.stage.corrections, actuator_friction=(ActuatorFriction(actuator=4, std_per_um=0.1),))
    afm4 = AnalyticForwardModel(replace(cfg.stage, corrections=corr))
    f = noise_features_for(afm4)
    assert f.names == ("dq4",)
    x = np.concatenate([[1.0], [3.0, 5.0, 7.0, 11.0], [2.0, 0.1, -0.2]])  # [t_prev, q_prev, u]
    assert f.values(x[None, :])[0, 0] == pytest.approx(float(afm.K[3] @ x[5:] - 11.0))
