"""Hidden effect: a hinge that slips with the platform's rotation, found by refinement.

The stage is written here on the independent generator's physics (tests/independent_stage.py,
nothing of microctl's physics or simulator): the platform's pose from its own equilibrium, the
reading the tool point's height plus gauge noise, and a hinge whose slip turns the platform by
a random fraction (std ``SLIP``) of the rotation each move makes about each axis. The package is
not told: it trains the default model on covering moves and then refinement moves
(``microctl.control.refine``, what ``microctl collect --refine`` runs), and its controller must
then choose the quiet moves, which make no rotation (a pure lift of every actuator: the truth's
scatter there is the gauge's alone), and state their repeatability correctly.

Bars (issue 18's, per target): true std at the chosen pose <= 1.25 x the quietest reaching
pose's (the gauge noise), and true std / predicted std in [0.67, 1.5]; over seeded stages, with
125 training moves, met on >= 75 % of them. Seed 1 of the fast test is one where 125 covering
moves alone miss the calibration bar (the floor is understated: true / predicted 0.64-0.70,
measured with this file's stage on seeds 0-8: covering alone met the bars on 5 of 9, covering
plus refinement on 7 of 9).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

import independent_stage as ind
from microctl.backends.collect import run_collect
from microctl.control.controller import ControllerSettings, OptimalController
from microctl.control.refine import refinement_commands
from microctl.measurement.design import training_moves
from microctl.measurement.log import Measurement, read_log
from microctl.models.afm import AnalyticForwardModel
from microctl.models.eafm import EAFM
from microctl.models.training import ResidualModelSettings, residual_dataset, train_residual_model
from microctl.stage.config import load_stage_config

ROOT = Path(__file__).resolve().parents[2]
CONFIG = ROOT / "configs/stage/sim_paper.yaml"
GAUGE_UM = 0.05
#: The hinge slip: std of the rotation error per unit of rotation made (3 %: with the tool
#: 50 mm from the centre, a 0.5 mrad turn scatters the reading by 0.75 µm, 15x the gauge).
SLIP = 0.03
DESIGNED, REFINED = 85, 40  # 125 training moves, as in the paper


class HingeStage:
    """The independent stage with a slipping hinge, as a backend (``stage``, ``state``, ``move``)."""

    def __init__(self, stage, seed: int):
        geom = ind.load_geometry(CONFIG)
        self.truth = ind.random_truth(geom, np.random.default_rng(seed), gauge_um=GAUGE_UM,
                                      physics=ind.load_physics(CONFIG))
        self.stage = stage
        self.rng = np.random.default_rng(seed + 1)
        self.q = np.zeros(4)
        self.zero = float(self._read(self._pose(self.q)))
        self.t = 0.0
        self.time_s = 0.0
        x, y = self.truth.geometry.tool_mm
        self.tool_per_mrad = np.array([y, -x])  # the tool's rise per mrad about x and y (tool_height)

    def _pose(self, q: np.ndarray) -> np.ndarray:
        return ind.platform_pose(self.truth, q[None, :])[0]

    def _read(self, pose: np.ndarray) -> float:
        return float(ind.gauge(self.truth, ind.tool_height(self.truth, pose[None, :]))[0])

    @property
    def state(self) -> np.ndarray:
        return np.r_[self.t, self.q]

    def move(self, u: np.ndarray) -> Measurement:
        q = self.truth.geometry.commands(u)[0]
        pose = self._pose(q)
        turn = pose[1:] - self._pose(self.q)[1:]
        slipped = pose + np.r_[0.0, SLIP * np.abs(turn) * self.rng.standard_normal(2)]
        self.t = self._read(slipped) - self.zero + GAUGE_UM * float(self.rng.standard_normal())
        self.q, self.time_s = q, self.time_s + 1.0
        return Measurement(self.t, q.copy(), np.asarray(u, dtype=float).copy(), self.time_s)

    def true_std(self, q_prev: np.ndarray, u: np.ndarray) -> float:
        """The reading's scatter after moving from q_prev to the pose u (the slip is small: linear)."""
        turn = self._pose(self.truth.geometry.commands(u)[0])[1:] - self._pose(q_prev)[1:]
        return math.sqrt(GAUGE_UM**2 + float(np.sum((SLIP * np.abs(turn) * self.tool_per_mrad) ** 2)))


def _trained(seed: int, tmp: Path):
    """(stage, afm, eafm): DESIGNED covering moves, then REFINED refinement moves, each followed by training."""
    cfg = load_stage_config(CONFIG)
    afm = AnalyticForwardModel(cfg.stage)
    log = tmp / f"train{seed}.csv"
    stage = HingeStage(cfg.stage, seed=seed)
    run_collect(stage, training_moves(afm, "covering", DESIGNED, seed=seed), log, quiet=True)
    eafm = EAFM(afm, train_residual_model(residual_dataset(read_log(log, cfg.stage), afm), afm, ResidualModelSettings()))
    moves = refinement_commands(eafm, REFINED, (0.0, 30.0), seed, lambda: stage.state)
    run_collect(stage, moves, log, quiet=True, mode="append", total=REFINED)
    model = train_residual_model(residual_dataset(read_log(log, cfg.stage), afm), afm, ResidualModelSettings())
    return stage, afm, EAFM(afm, model)


def _bars_met(stage, afm, eafm) -> list[tuple[float, float, float]]:
    """Per target (6, 12, 18, 24 µm in sequence from the zero state): the chosen pose's true std
    over the quietest pose's, true / predicted std, and whether both bars are met (1.0 or 0.0)."""
    ctrl = OptimalController(eafm, ControllerSettings())
    q_prev, t_prev, out = np.zeros(4), 0.0, []
    for target in (6.0, 12.0, 18.0, 24.0):
        res = ctrl.solve(target, np.r_[t_prev, q_prev])
        true = stage.true_std(q_prev, res.u)
        # the quietest reaching pose makes no turn: the gauge's scatter alone
        ok = true <= 1.25 * GAUGE_UM and 0.67 <= true / res.predicted_std_um <= 1.5
        out.append((true / GAUGE_UM, true / res.predicted_std_um, float(ok)))
        q_prev, t_prev = afm.q_of(res.u), target
    return out


def test_the_refined_model_finds_the_quiet_moves_and_states_their_scatter(tmp_path):
    per_target = _bars_met(*_trained(1, tmp_path))
    assert all(ok for *_, ok in per_target), per_target


@pytest.mark.slow
def test_the_bars_are_met_on_three_quarters_of_seeded_stages(tmp_path):
    met = [all(ok for *_, ok in _bars_met(*_trained(seed, tmp_path))) for seed in range(9)]
    assert sum(met) >= 0.75 * len(met), met
