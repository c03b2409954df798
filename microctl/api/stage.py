"""The stage and its training data: load a stage YAML, read a log, collect, refine, train, learn
(:mod:`microctl.api`, docs/api.md)."""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from microctl.control.controller import ControllerSettings
from microctl.errors import ConfigError
from microctl.measurement.design import DEFAULT_DESIGN
from microctl.measurement.log import MeasurementLog, read_log
from microctl.models.afm import T_PLAUSIBLE_FACTOR, AnalyticForwardModel, plausible_t_bound_um
from microctl.models.eafm import EAFM
from microctl.stage.config import StageConfig, load_stage_config
from microctl.util.fields import check_moves


@dataclass(frozen=True, eq=False)
class Stage:
    """A stage configuration with its analytic forward model.

    Attributes
    ----------
    config : StageConfig
        The validated stage YAML (geometry, ranges, backend).
    afm : AnalyticForwardModel
        The AFM f_a(s, u) of eq. 14.
    """

    config: StageConfig
    afm: AnalyticForwardModel

    @property
    def name(self) -> str:
        """The stage's name (from its YAML)."""
        return self.config.stage.name

    @property
    def dof(self) -> tuple[str, ...]:
        """Names of the control signal's entries, n_p of them (``z, rx, ry``)."""
        return self.afm.dof

    @property
    def state_names(self) -> tuple[str, ...]:
        """Names of the state s = [t; q] entries, n_s = 1 + n_q of them."""
        return self.afm.state_names

    @property
    def range_um(self) -> tuple[np.ndarray, np.ndarray]:
        """The configured actuator ranges (lo, hi), each shape (n_q,), µm: no command leaves them."""
        return self.afm.lo.copy(), self.afm.hi.copy()

    def zero_state(self) -> np.ndarray:
        """The zero state, shape (n_s,)."""
        return self.afm.zero_state()

    def check_state(self, state: Sequence[float] | Mapping[str, float] | np.ndarray | None) -> np.ndarray:
        """A possible state s = [t; q] as an array of shape (n_s,); None gives the zero state.

        Parameters
        ----------
        state : sequence of n_s floats, mapping name -> float, or None
            A mapping must name every entry (:attr:`state_names`).

        Raises
        ------
        ConfigError
            Wrong length or names, a non-finite value, an actuator beyond its hardware
            ``limit_um`` or a tool pose beyond the bound a measurement log has.
        """
        if state is None:
            return self.zero_state()
        names = self.state_names
        if isinstance(state, Mapping):
            missing = [n for n in names if n not in state]
            unknown = [k for k in state if k not in names]
            if missing or unknown:
                raise ConfigError(f"state: expected the entries {', '.join(names)}"
                                  + (f"; missing {', '.join(missing)}" if missing else "")
                                  + (f"; unknown {', '.join(map(str, unknown))}" if unknown else ""))
            state = [state[n] for n in names]
        try:
            s = np.asarray(state, dtype=float)
        except (TypeError, ValueError, OverflowError):
            s = None
        if s is None or s.ndim != 1:
            raise ConfigError(f"state: {str(state)[:200]} is not a list of {len(names)} numbers ({', '.join(names)})")
        if s.size != len(names):
            raise ConfigError(f"state: {s.size} value(s), expected {len(names)} ({', '.join(names)})")
        if not np.all(np.isfinite(s)):
            raise ConfigError(f"state: {s.tolist()} has a non-finite value")
        for a, q in zip(self.config.stage.actuators, s[1:]):
            lo, hi = a.limit_um
            if not lo <= q <= hi:
                raise ConfigError(f"state: {a.name} = {q:g} µm is beyond the actuator's hardware limit "
                                  f"[{lo:g}, {hi:g}] µm; no stage can be there")
        t_max = self._t_bound()
        if abs(s[0]) > t_max:
            raise ConfigError(f"state: {names[0]} = {s[0]:g} µm is implausible: the stage reaches at most "
                              f"|t| = {t_max / T_PLAUSIBLE_FACTOR:.6g} µm")
        return s

    def _t_bound(self) -> float:
        """The bound on |t| a measurement log has (computed once: it builds a model of the stage)."""
        cache = self.__dict__.setdefault("_cache", {})
        if "t_bound" not in cache:
            cache["t_bound"] = plausible_t_bound_um(self.config.stage)
        return cache["t_bound"]

    def open_backend(self, **kwargs: Any):
        """The backend the stage YAML names, connected (a :class:`~microctl.backends.base.StageBackend`).

        Parameters
        ----------
        **kwargs
            Passed to the backend (e.g. ``seed`` of the simulated stage).
        """
        from microctl.backends import make_backend

        return make_backend(self.config, **kwargs)


def load_stage(path: str | Path) -> Stage:
    """Read and validate a stage YAML (``configs/stage/*.yaml``); ConfigError naming the field."""
    config = load_stage_config(path)
    return Stage(config, AnalyticForwardModel(config.stage))


def read_measurements(path: str | Path, stage: Stage, min_rows: int = 1) -> MeasurementLog:
    """Read and validate a measurement log (docs/measurement-log.md) of ``stage``; DataError naming row and column."""
    return read_log(path, stage.config.stage, min_rows=min_rows)


def _on_backend(stage: Stage, backend: Any | None, run: Any) -> Any:
    """``run(backend)``; without a backend, on :meth:`Stage.open_backend` (opened and closed here)."""
    if backend is not None:
        return run(backend)
    with stage.open_backend() as b:
        return run(b)


def collect(stage: Stage, n: int, out: str | Path, *, seed: int = 0, design: str = DEFAULT_DESIGN,
            backend: Any | None = None) -> int:
    """Run ``n`` designed training moves on the stage's backend and write them as a measurement log (``microctl collect``).

    Parameters
    ----------
    stage : Stage
    n : int
        Number of moves (>= 1).
    out : path
        The log (overwritten).
    seed : int
        Seed of the move design.
    design : str
        One of :data:`~microctl.measurement.design.DESIGNS`, default ``covering_still``
        (:data:`~microctl.measurement.design.DEFAULT_DESIGN`; ``space_filling`` is the paper's).
    backend : StageBackend, optional
        Default: :meth:`Stage.open_backend` (opened and closed here).

    Returns
    -------
    int
        Moves written.
    """
    from microctl.backends.collect import run_collect
    from microctl.measurement.design import training_moves

    n = check_moves(n, 1)
    moves = training_moves(stage.afm, design, n, seed)
    return _on_backend(stage, backend, lambda b: run_collect(b, moves, out, quiet=True))


def refine(stage: Stage, model: Any, n: int, log: str | Path, *, seed: int = 0,
           target_range_um: tuple[float, float] | None = None, backend: Any | None = None) -> int:
    """Append to ``log`` (the model's training log) ``n`` moves chosen by the trained ``model`` where
    it is least sure of the optimum (``microctl collect --refine --append``, :mod:`microctl.control.refine`),
    targets drawn with ``seed`` from ``target_range_um`` (default: every reading the stage can
    reach), on ``backend`` (default :meth:`Stage.open_backend`); train on the log again afterwards.
    Returns the moves written."""
    from microctl.backends.collect import run_collect
    from microctl.control.refine import check_target_range, refinement_commands

    n = check_moves(n, 1)
    if not Path(log).is_file():
        raise ConfigError(f"{log}: no such measurement log; refine appends to the log the model was trained on")
    eafm = EAFM(stage.afm, model)  # a model of another stage is refused
    targets = check_target_range(eafm, target_range_um, "target_range_um")

    def run(b) -> int:
        moves = refinement_commands(eafm, n, targets, seed, lambda: b.state)
        return run_collect(b, moves, log, quiet=True, mode="append", total=n)

    return _on_backend(stage, backend, run)


def train(log: str | Path | MeasurementLog, stage: Stage, *, out: str | Path | None = None,
          restarts: int = 2, seed: int = 0, noise_model: str = "dictionary", max_time: float | None = None):
    """Fit the residual VHGPR (eq. 3) to a measurement log, as ``microctl train`` does.

    Parameters
    ----------
    log : path or MeasurementLog
        At least 5 moves.
    stage : Stage
    out : path, optional
        Also write the model file there.
    restarts, seed, noise_model : int, int, str
        :class:`~microctl.models.training.ResidualModelSettings` fields.
    max_time : float, optional
        Wall-time budget of the fit, s.

    Returns
    -------
    FittedVHGPR
        Bound to the stage geometry; pass it (or the file) to :class:`Controller`.
    """
    from microctl.models.floor_check import with_floor_check
    from microctl.models.training import ResidualModelSettings, residual_dataset, train_residual_model

    if not isinstance(log, MeasurementLog):
        log = read_measurements(log, stage, min_rows=5)
    elif len(log) < 5:
        raise ConfigError(f"{log.path}: {len(log)} moves, at least 5 needed to train")
    settings = ResidualModelSettings(restarts=restarts, seed=seed, noise_model=noise_model)
    data = residual_dataset(log, stage.afm)
    model, check = with_floor_check(train_residual_model(data, stage.afm, settings, max_time=max_time), data)
    if check is not None:  # degenerate: as `microctl train` prints it
        warnings.warn(f"train: {check.describe()}", RuntimeWarning, stacklevel=2)
    if out is not None:
        model.save(out)
    return model


def learn(stage: Stage, n: int, log: str | Path, *, out: str | Path | None = None, seed: int = 0,
          design: str = DEFAULT_DESIGN, target_range_um: tuple[float, float] | None = None, settings: Any | None = None,
          controller: ControllerSettings | None = None, backend: Any | None = None, replace_log: bool = False,
          quiet: bool = True, say: Any | None = None):
    """Learn a stage in ``n`` moves (``microctl learn``): the design, then rounds of :func:`refine`
    moves, training on the whole log after each; returns the last FittedVHGPR. Parameters as
    :func:`microctl.experiments.learning.learn_stage`; ``backend`` defaults to :meth:`Stage.open_backend`."""
    from microctl.experiments.learning import learn_stage

    return _on_backend(stage, backend, lambda b: learn_stage(
        stage.afm, stage.config.stage, b, n, log, target_range_um, out=out, seed=seed, design=design,
        settings=settings, controller=controller, replace_log=replace_log, quiet=quiet, say=say))
