"""What the extended model changes in control terms (the gain section of a diagnosis).

The plain EAFM (the residual GP of eq. 3 on the configured AFM) and the extended EAFM (the same
on the AFM with the accepted corrections, its noise model using the diagnosed stick-slip
actuators: :func:`microctl.models.training.noise_features_for`) are trained on the diagnosed log
with the package's default residual model, and the default optimal controller (eq. 4) of each
reaches the same targets in sequence from the zero state. For each chosen pose: the actuator
commands and the predicted scatter; on a simulated stage also the true scatter and true error
from the simulator, and the quietest pose that truly reaches the target (the oracle), so the
report can say whether the extension makes the controller more repeatable, and by how much.
"""

from __future__ import annotations

import math

import numpy as np

from microctl.control.context import ByDirection
from microctl.control.controller import ControllerSettings, OptimalController
from microctl.diagnosis.data import DiagnosisData
from microctl.models import direction
from microctl.models.afm import AnalyticForwardModel
from microctl.models.eafm import EAFM
from microctl.models.training import (
    ResidualModelSettings,
    residual_dataset,
    train_residual_model,
)
from microctl.stage.config import StageConfig

__all__ = ["TARGET_FRACTIONS", "COMPARISON_SETTINGS", "control_comparison"]

#: Targets as fractions of the largest tool pose both EAFMs reach from the zero state.
TARGET_FRACTIONS = (0.15, 0.35, 0.55)

#: Residual-model settings of the comparison's two EAFMs: the package's defaults with one optimiser
#: run, at most 150 L-BFGS-B iterations and f's SE part always on (one variant instead of the BIC
#: choice between two), so that the comparison (two fits on the diagnosed log) keeps ``diagnose`` on
#: a 300-move log well within a minute; the models a user controls the stage with come from
#: ``microctl train`` with the full settings.
COMPARISON_SETTINGS = {"restarts": 1, "max_iter": 150, "se": "on"}


def control_comparison(config: StageConfig, extended: StageConfig, data: DiagnosisData, *, seed: int = 0) -> dict:
    """Plain vs extended EAFM controller on the same targets (see the module docstring).

    Parameters
    ----------
    config : StageConfig
        The configured stage (the plain EAFM).
    extended : StageConfig
        ``extended.yaml``: the stage with the accepted corrections (mean and noise causes).
    data : DiagnosisData
        The rows the diagnosis fitted (outliers left out).
    seed : int

    Returns
    -------
    dict
        ``targets_um`` and, per model (``plain``, ``extended``), per target: ``q_um``,
        ``predicted_std_um``, ``noise_std_um`` and, on a simulated stage, ``true_std_um``,
        ``true_error_um``, ``oracle_std_um``; ``truth`` says whether the truth was available.
    """
    from microctl.backends.simulated import SimulatedStage
    from microctl.control.oracle import OracleController

    truth = config.backend.kind == "simulated"
    settings = ControllerSettings()
    ctrls = {}
    for label, cfg in (("plain", config), ("extended", extended)):
        afm = AnalyticForwardModel(cfg.stage)
        model = train_residual_model(residual_dataset(data, afm), afm, ResidualModelSettings(seed=seed, **COMPARISON_SETTINGS))
        # a model that reads the actuators' last directions: a controller per direction
        ctrls[label] = ByDirection(EAFM(afm, model), lambda e: OptimalController(e, settings))
    zero = ctrls["plain"]().afm.zero_state()
    # targets both models reach from the zero state, as fractions of the common positive range
    hi = min(c().reachable_interval(zero)[1] for c in ctrls.values())
    targets = [float(f * hi) for f in TARGET_FRACTIONS]
    out: dict = {"targets_um": targets, "truth": truth, "models": {}}
    for label, by_dir in ctrls.items():
        rows = []
        stage = SimulatedStage(config, seed=seed) if truth else None
        oracle = OracleController(by_dir().afm, stage) if truth else None
        s, last = zero, direction.initial(len(zero) - 1)
        prev = None
        for target in targets:
            res = by_dir(last).solve(target, s, u_init=prev)
            row = {"target_um": target, "q_um": res.q.tolist(), "predicted_std_um": res.predicted_std_um,
                   "noise_std_um": res.noise_std_um}
            if truth:
                row["true_std_um"] = math.sqrt(float(stage.true_var(s, res.u)))
                row["true_error_um"] = float(stage.true_mean(s, res.u)) - target
                row["oracle_std_um"] = oracle.solve(target, s).predicted_std_um
            rows.append(row)
            last = direction.after_move(last, s[1:], res.q)
            s = np.concatenate([[res.predicted_um], res.q])
            prev = res.u
        out["models"][label] = rows
    if truth:
        plain = np.array([r["true_std_um"] for r in out["models"]["plain"]])
        ext = np.array([r["true_std_um"] for r in out["models"]["extended"]])
        out["true_std_ratio_extended_over_plain"] = (ext / plain).tolist()
    return out
