"""Learning a stage in n moves: a designed log, then refinement rounds, training after each.

A designed log (``microctl collect``) spreads its moves over the workspace without knowing where
the controller will go; the quiet poses eq. 4 seeks are then extrapolated (docs/experiments.md,
Refinement). :func:`learn_stage` spends :data:`~microctl.control.refine.REFINE_SHARE` of the
moves on rounds of :data:`~microctl.control.refine.ROUND_MOVES` moves chosen by the model trained
so far where it is least sure of the optimum (:mod:`microctl.control.refine`), each round
followed by training on the whole log (eq. 3). It is ``collect``, ``train``, ``collect --refine
--append``, ``train``, ... in one call: what ``microctl learn`` and :func:`microctl.api.learn`
run, and the method ``refined`` of ``scripts/bench_rigs.py``. (The experiments' own training,
:func:`microctl.experiments.runner._train`, keeps its YAML-configured rounds and seeds.)
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Callable

from microctl.backends.collect import run_collect
from microctl.control.controller import ControllerSettings
from microctl.control.refine import ROUND_MOVES, check_target_range, learning_rounds, refinement_commands
from microctl.errors import ConfigError
from microctl.measurement.design import DEFAULT_DESIGN, training_moves
from microctl.measurement.log import read_log
from microctl.models.afm import AnalyticForwardModel
from microctl.models.eafm import EAFM
from microctl.models.floor_check import with_floor_check
from microctl.models.training import ResidualModelSettings, residual_dataset, train_residual_model
from microctl.util.fields import check_moves

__all__ = ["learn_stage"]


def learn_stage(afm: AnalyticForwardModel, stage: Any, backend: Any, n: int, log: str | Path,
                target_range_um: tuple[float, float] | None = None, *, out: str | Path | None = None, seed: int = 0,
                design: str = DEFAULT_DESIGN, settings: ResidualModelSettings | None = None,
                controller: ControllerSettings | None = None, replace_log: bool = False, quiet: bool = True,
                say: Callable[[str], None] | None = None):
    """Run the ``n`` moves on ``backend`` and fit the residual model in rounds (module docstring).

    Parameters
    ----------
    afm : AnalyticForwardModel
    stage : microctl.stage.config.Stage
        The stage geometry (the log's columns).
    backend : StageBackend
        Open; every move runs on it, in order.
    n : int
        Moves in all (>= 5): ``n - R`` designed, then ``R = learning_rounds(n)`` rounds of
        :data:`~microctl.control.refine.ROUND_MOVES`.
    log : path
        The measurement log: written, then appended to in each round, row by row. An existing
        file is refused (ConfigError) unless ``replace_log``; it is then replaced once the
        designed moves are complete.
    target_range_um : (float, float), optional
        Targets of the refinement episodes (default: every reading the stage can reach); give
        the range you will work in. Checked (ConfigError) before any move.
    out : path, optional
        The model file, written after every fit: a failure leaves every completed move in the
        log and the last model (``microctl train`` on the log then fits them all).
    seed : int
        Of the design; round r draws its targets with ``[seed, r]``.
    design : str
        Of the first moves (:mod:`microctl.measurement.design`).
    settings : ResidualModelSettings, optional
        Of every fit (default the package's).
    controller : ControllerSettings, optional
        Whose candidate optima the rounds explore (default the package's).
    replace_log : bool
        Replace an existing ``log``.
    quiet : bool
        Hide the moves' progress on stderr.
    say : callable, optional
        Gets a line per fit.

    Returns
    -------
    FittedVHGPR
        The last fit, on all n moves.
    """
    n = check_moves(n, 5, why=" (a model needs 5 to train on)")
    log = Path(log)
    if log.exists() and not replace_log:
        raise ConfigError(f"{log}: the file exists; refusing to overwrite it (replace it, or choose another file name)")
    target_range_um = check_target_range(afm, target_range_um, "target_range_um")
    settings = settings if settings is not None else ResidualModelSettings()
    rounds = learning_rounds(n)
    tell = say if say is not None else (lambda text: None)

    def fit(r: int):
        data = residual_dataset(read_log(log, stage, min_rows=5), afm)
        model, check = with_floor_check(train_residual_model(data, afm, settings), data)
        if out is not None:
            model.save(out)
        tell(f"learn: fit {r + 1} of {rounds + 1} on {len(data.y)} moves"
             + (f", model written to {out}" if out is not None else ""))
        if check is not None:  # a floor the mean correction passes through (microctl.models.floor_check)
            tell(f"learn: warning: {check.describe()}")
        return model

    designed = training_moves(afm, design, n - rounds * ROUND_MOVES, seed)
    run_collect(backend, designed, log, quiet=quiet, mode="replace" if log.exists() else "write")
    model = fit(0)
    for r in range(rounds):
        moves = refinement_commands(EAFM(afm, model), ROUND_MOVES, target_range_um, [seed, r],
                                    lambda: backend.state, controller)
        run_collect(backend, moves, log, quiet=quiet, mode="append", total=ROUND_MOVES)
        model = fit(r + 1)
    return model
