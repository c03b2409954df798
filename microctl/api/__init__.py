"""The public Python API of microctl: what a lab script or notebook needs, with types.

Load a stage, train a residual model from a measurement log, build a controller, solve for a
target, move a stage (simulated or hardware) and read the results::

    from microctl import api

    stage = api.load_stage("configs/stage/sim_paper.yaml")
    model = api.train("log.csv", stage, out="model.npz")
    ctl = api.Controller(stage, "model.npz")
    sol = ctl.solve(14.0)                       # ControlResult: u, q, predicted_um, predicted_std_um
    with api.Operator(ctl, stage.open_backend(), log="moves.csv") as op:
        rec = op.move(14.0)                     # MoveRecord: predicted ± std and the measured pose

The command line (``microctl solve``, ``move``, ``serve``) is a thin layer over these names;
``docs/api.md`` has examples that run as tests. Units: µm, mrad. Errors (:mod:`microctl.errors`):
``ConfigError``/``DataError`` for bad input, ``UnreachableTargetError`` for a target outside the
stage's reach, ``BackendError`` from a device, ``SolveError``.
"""

from __future__ import annotations

from microctl.api.controller import Controller
from microctl.api.operator import MOVE_LOG_COLUMNS, Learner, Operator
from microctl.api.stage import Stage, collect, learn, load_stage, read_measurements, refine, train
from microctl.control.controller import ControllerSettings
from microctl.control.result import ControlResult, MoveRecord

__all__ = [
    "Stage", "load_stage", "read_measurements", "collect", "refine", "train", "learn", "Controller", "ControllerSettings",
    "ControlResult", "MoveRecord", "Operator", "Learner", "MOVE_LOG_COLUMNS",
]
