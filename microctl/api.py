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

import hashlib
import json
import math
import re
import time
import warnings
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from microctl.control.context import ByDirection
from microctl.control.controller import AFMController, ControllerSettings, OptimalController, with_baseline
from microctl.control.memory import MemoryCompensated, with_memory
from microctl.control.result import ControlResult, MoveRecord
from microctl.errors import BackendError, ConfigError, SolveError
from microctl.measurement.appending import append_log_writer
from microctl.measurement.log import Measurement, MeasurementLog, read_log
from microctl.models.afm import T_PLAUSIBLE_FACTOR, AnalyticForwardModel, plausible_t_bound_um
from microctl.models.direction import after_move
from microctl.models.direction import at_commands as directions_at
from microctl.models.eafm import EAFM
from microctl.stage.config import StageConfig, load_stage_config
from microctl.util.signals import interrupts_deferred, raise_if_interrupted

__all__ = [
    "Stage", "load_stage", "read_measurements", "collect", "refine", "train", "Controller", "ControllerSettings", "ControlResult",
    "MoveRecord", "Operator", "Learner", "MOVE_LOG_COLUMNS",
]

#: Extra columns of a log that ``Operator`` creates (the measurement-log contract allows extra
#: columns; ``train`` ignores them).
MOVE_LOG_COLUMNS = ("target_um", "controller", "predicted_um", "predicted_std_um")


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


def collect(stage: Stage, n: int, out: str | Path, *, seed: int = 0, design: str = "covering",
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
        ``covering`` (default) or ``space_filling`` (:mod:`microctl.measurement.design`).
    backend : StageBackend, optional
        Default: :meth:`Stage.open_backend` (opened and closed here).

    Returns
    -------
    int
        Moves written.
    """
    from microctl.backends.collect import run_collect
    from microctl.measurement.design import training_moves

    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 1:
        raise ConfigError(f"n: expected a number of moves >= 1, got {n!r}")
    moves = training_moves(stage.afm, design, int(n), seed)
    if backend is not None:
        return run_collect(backend, moves, out, quiet=True)
    with stage.open_backend() as b:
        return run_collect(b, moves, out, quiet=True)


def refine(stage: Stage, model: Any, n: int, log: str | Path, *, seed: int = 0,
           target_range_um: tuple[float, float] | None = None, backend: Any | None = None) -> int:
    """Append to ``log`` (the model's training log) ``n`` moves chosen by the trained ``model`` where
    it is least sure of the optimum (``microctl collect --refine --append``, :mod:`microctl.control.refine`),
    targets drawn with ``seed`` from ``target_range_um`` (default: every reading the stage can
    reach), on ``backend`` (default :meth:`Stage.open_backend`); train on the log again afterwards.
    Returns the moves written."""
    from microctl.backends.collect import run_collect
    from microctl.control.refine import check_target_range, refinement_commands

    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 1:
        raise ConfigError(f"n: expected a number of moves >= 1, got {n!r}")
    if not Path(log).is_file():
        raise ConfigError(f"{log}: no such measurement log; refine appends to the log the model was trained on")
    eafm = EAFM(stage.afm, model)  # a model of another stage is refused
    targets = check_target_range(eafm, target_range_um, "target_range_um")

    def run(b) -> int:
        moves = refinement_commands(eafm, int(n), targets, seed, lambda: b.state)
        return run_collect(b, moves, log, quiet=True, mode="append", total=int(n))

    if backend is not None:
        return run(backend)
    with stage.open_backend() as b:
        return run(b)


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


class Controller:
    """The EAFM optimal controller of eq. 4 for one stage and residual model.

    Parameters
    ----------
    stage : Stage
    model : path or FittedVHGPR
        A model file from ``microctl train`` / :func:`train` (checked against the stage geometry).
    settings : ControllerSettings, optional
        r_e, kappa and the solver settings (default: the package's).
    """

    def __init__(self, stage: Stage, model: Any, settings: ControllerSettings | None = None):
        self.stage = stage
        self.settings = settings or ControllerSettings()
        self._load(model)

    def _load(self, model: Any) -> None:
        eafm = EAFM(self.stage.afm, model)
        # with hysteresis corrections the controller meets the target with the play states; a
        # model that reads the actuators' last directions gets a controller per direction
        self._by_direction = ByDirection(eafm, lambda e: with_memory(OptimalController(e, self.settings),
                                                                     self.stage.afm))
        self.eafm, self.optimal = eafm, self._by_direction(None)
        self.model_source = eafm.source
        self._baseline: AFMController | None = None

    def reload(self, model: Any | None = None) -> None:
        """Load the model again (default: the same file, e.g. after a refit) and rebuild the solver."""
        if model is None:
            if self.model_source.startswith("<"):
                raise ConfigError("reload: the controller's model was given in memory; give a model file")
            model = self.model_source
        self._load(model)

    @property
    def n_train(self) -> int:
        """Number of moves the residual model was trained on."""
        return self.eafm.n_train

    def reachable_interval(self, state: Sequence[float] | np.ndarray | None = None) -> tuple[float, float]:
        """EAFM-mean tool poses reachable from ``state`` (µm; default the zero state)."""
        return self.optimal.reachable_interval(self.stage.check_state(state))

    def solve(self, target_um: float, state: Sequence[float] | np.ndarray | None = None, *,
              baseline: bool = False, memory: np.ndarray | None = None,
              direction: np.ndarray | None = None) -> ControlResult:
        """The optimal control signal for ``target_um`` from ``state`` (default the zero state).

        Parameters
        ----------
        target_um : float
        state : array_like, shape (n_s,), optional
        baseline : bool
            Also solve the AFM baseline from the same state and say whether the chosen pose is
            credibly quieter (``result.baseline``, ``result.vs_baseline``).
        memory : ndarray, shape (n_q, N_PLAY), optional
            The hysteresis play states before the move, for a stage with hysteresis corrections
            (:mod:`microctl.control.memory`; default: one move from the zero state to the
            state's q). :class:`Operator` passes them from the commands it sent.
        direction : ndarray, shape (n_q,), optional
            Each actuator's last direction of motion (+1 or -1), read by a model with a reversal
            noise source (:mod:`microctl.models.direction`; default: the zero state's, all +1).
            :class:`Operator` passes it from the commands it sent.

        Returns
        -------
        ControlResult
            ``u`` (n_p,), ``q`` (n_q,) inside the ranges, ``predicted_um`` ± ``predicted_std_um``.

        Raises
        ------
        ConfigError
            A target that is not a finite number, an impossible state.
        UnreachableTargetError
            The target is outside what the stage reaches from ``state`` (the message gives the interval).
        """
        target = _finite(target_um, "target_um")
        s = self.stage.check_state(state)
        optimal = self._by_direction(direction)
        carries = isinstance(optimal, MemoryCompensated)
        if carries and memory is None:
            memory = optimal.default_memory(s)
        res = optimal.solve(target, s, memory=memory) if carries else optimal.solve(target, s)
        if baseline:
            if self._baseline is None:
                self._baseline = with_memory(AFMController(self.stage.afm, self.settings, reporter=self.eafm),
                                             self.stage.afm)
            res = with_baseline(self.eafm.with_direction(direction), res, self._baseline, self.settings.credible_level,
                                memory=memory if carries else None)
        return res

    def to_dict(self, res: ControlResult) -> dict:
        """A result as the JSON object ``microctl solve --json`` prints (docs/cli.md)."""
        afm, dof = self.stage.afm, self.stage.dof
        out = {
            "target_um": res.target_um, "state": dict(zip(afm.state_names, map(float, res.state))),
            "u": dict(zip(dof, map(float, res.u))), "q_um": res.q.tolist(), "predicted_um": res.predicted_um,
            "predicted_std_um": res.predicted_std_um, "noise_std_um": res.noise_std_um,
            "noise_upper_std_um": res.noise_upper_std_um, "bias_std_um": res.bias_std_um,
            "hysteresis_um": res.hysteresis_um,
            "objective": res.objective, "r_e": self.settings.r_e, "kappa": self.settings.kappa,
            "status": res.status, "success": res.success, "iterations": res.iterations,
            "solve_time_s": res.solve_time_s, "model": {"noise_model": self.eafm.model.noise_model},
        }
        if res.vs_baseline is not None and res.baseline is not None:
            b = res.baseline
            out["credibly_quieter_than_baseline"] = res.vs_baseline.credible
            out["vs_baseline"] = res.vs_baseline.to_dict()
            out["baseline"] = {"controller": "afm", "u": dict(zip(dof, map(float, b.u))), "q_um": b.q.tolist(),
                               "predicted_um": b.predicted_um, "predicted_std_um": b.predicted_std_um,
                               "predicted_by": "eafm", "status": b.status}
        return out


def _finite(value: Any, name: str) -> float:
    """``value`` as a finite float; ConfigError naming ``name`` otherwise (bools are refused)."""
    if isinstance(value, bool):
        raise ConfigError(f"{name}: expected a number of µm, got {value!r}")
    try:
        v = float(value)
    except (TypeError, ValueError, OverflowError):
        raise ConfigError(f"{name}: expected a number of µm, got {value!r}") from None
    if not math.isfinite(v):
        raise ConfigError(f"{name}: {value!r} is not a finite number")
    return v


class Operator:
    """Moves a stage with a controller and keeps every executed move in a measurement log.

    Parameters
    ----------
    controller : Controller
    backend : StageBackend
        From :meth:`Stage.open_backend` (closed by :meth:`close`); its state is where each move
        starts (the serial backend reads it at connect).
    log : path, optional
        Measurement log the moves are appended to (created with the collect columns and
        :data:`MOVE_LOG_COLUMNS` when missing), so it trains (``microctl train``).

    Notes
    -----
    A move is solved first; an unreachable target raises before anything is sent. The command
    is checked against the configured ranges again by the backend (nothing outside them is
    sent). The move and its log row are one step that Ctrl-C does not split: an interrupt
    arriving during the move is raised after the row is written. A Ctrl-C that reached the command
    line's handler during the solve ends the move before anything is sent, even where its
    KeyboardInterrupt was lost on the way (:func:`microctl.util.signals.raise_if_interrupted`).
    """

    def __init__(self, controller: Controller, backend: Any, log: str | Path | None = None):
        self.controller = controller
        self.stage = controller.stage
        self.backend = backend
        self.moves = 0
        self._writer = None
        self._seq = 0
        self._time_offset = 0.0
        afm = self.stage.afm
        # the hysteresis play states (stage corrections with hysteresis only), stepped with every
        # command sent; before the first: one move from the zero state to the backend's q
        self.memory = afm.memory.step(None, np.asarray(backend.state, dtype=float)[1:]) if afm.memory.active \
            else None
        # each actuator's last direction of motion, stepped with every command sent (the same
        # convention: one move from the zero state to the backend's q before the first)
        self.direction = directions_at(np.asarray(backend.state, dtype=float)[1:])
        if log is not None:
            self._writer, self._seq, self._time_offset = append_log_writer(log, self.stage.config.stage,
                                                                           MOVE_LOG_COLUMNS)

    @property
    def state(self) -> np.ndarray:
        """The stage's state s = [t; q] now, shape (n_s,)."""
        return self.backend.state

    @property
    def log_path(self) -> Path | None:
        """The measurement log, if any."""
        return None if self._writer is None else self._writer.path

    def move(self, target_um: float) -> MoveRecord:
        """Solve for ``target_um`` from the stage's state, execute it, read the gauge, log the move.

        Returns
        -------
        MoveRecord

        Raises
        ------
        ConfigError, UnreachableTargetError
            Before anything is sent.
        BackendError
            From the device (the log keeps every completed move).
        """
        s, last = self.backend.state, self.direction
        res = self.controller.solve(target_um, s, direction=last) if self.memory is None else \
            self.controller.solve(target_um, s, memory=self.memory, direction=last)
        lo, hi = self.stage.range_um
        tol = self.controller.settings.range_tol
        if not (np.all(np.isfinite(res.q)) and np.all(res.q >= lo - tol) and np.all(res.q <= hi + tol)):
            raise SolveError(f"the command q = {res.q.tolist()} µm leaves the configured ranges; nothing was sent")
        raise_if_interrupted()  # a Ctrl-C during the solve whose KeyboardInterrupt was lost: nothing is sent
        with interrupts_deferred():
            m: Measurement = self.backend.move(res.u)
            if self._time_offset:
                m = replace(m, time_s=m.time_s + self._time_offset)  # the log's clock continues
            seq = self._seq
            if self._writer is not None:
                extra = {"target_um": repr(float(res.target_um)), "controller": "eafm",
                         "predicted_um": repr(float(res.predicted_um)),
                         "predicted_std_um": repr(float(res.predicted_std_um))}
                self._writer.write(m, s, seq=seq, extra={k: v for k, v in extra.items()
                                                         if k in self._writer.extra_columns})
            self._seq += 1
            self.moves += 1
            if self.memory is not None:
                self.memory = self.stage.afm.memory.step(self.memory, np.asarray(m.q_um, dtype=float))
            self.direction = after_move(self.direction, np.asarray(s, dtype=float)[1:],
                                                  np.asarray(m.q_um, dtype=float))
        return MoveRecord(seq=seq, target_um=res.target_um, state_before=s, u=np.asarray(m.u, dtype=float),
                          q_um=np.asarray(m.q_um, dtype=float), predicted_um=res.predicted_um,
                          predicted_std_um=res.predicted_std_um, measured_um=float(m.t_um), time_s=float(m.time_s),
                          solution=res, direction_before=last)

    def close(self) -> None:
        """Close the log and the backend (idempotent)."""
        try:
            if self._writer is not None:
                self._writer.close()
        finally:
            try:
                self.backend.close()
            except BackendError:
                pass

    def __enter__(self) -> "Operator":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class Learner:
    """Folds the moves an :class:`Operator` logs into the model: a refit every ``every`` moves.

    Each refit trains on the whole log (:func:`train`, seeded) and writes a new, versioned model
    file beside the original, ``MODEL.v1.npz``, ``MODEL.v2.npz``, ..., never overwriting one; a
    line per version in ``MODEL.versions.jsonl`` records the log rows it was trained on (count
    and SHA-256 of those lines), the seed and restarts, so ``head -n ROWS+1 LOG.csv`` and
    ``microctl train`` reproduce it. The controller then uses the new version.

    Parameters
    ----------
    operator : Operator
        With a log.
    model : path
        The model file the controller started from.
    every : int
        Moves between refits (>= 1).
    restarts, seed : int
        Of each refit.
    update : bool
        Also fold every move into the controller's model as soon as it is made, without a refit
        (:func:`microctl.gp.sparse.update`, hyperparameters fixed). In memory only: the log holds
        the move, and the next refit (a file) supersedes it.
    """

    def __init__(self, operator: Operator, model: str | Path, every: int = 50, restarts: int = 1, seed: int = 0,
                 update: bool = False):
        if operator.log_path is None:
            raise ConfigError("learning needs a measurement log the moves are appended to")
        if isinstance(every, bool) or not isinstance(every, int) or every < 1:
            raise ConfigError(f"every: expected a number of moves >= 1, got {every!r}")
        self.operator, self.model, self.every = operator, Path(model), every
        self.restarts, self.seed, self._since, self.update = restarts, seed, 0, bool(update)
        self.manifest = self.model.with_name(f"{self.model.stem}.versions.jsonl")

    def next_version(self) -> int:
        """One past the largest version file beside the model (1 when there is none)."""
        found = [int(m.group(1)) for f in self.model.parent.glob(f"{self.model.stem}.v*.npz")
                 if (m := re.fullmatch(rf"{re.escape(self.model.stem)}\.v(\d+)\.npz", f.name))]
        return max(found, default=0) + 1

    def after_move(self, record: MoveRecord | None = None) -> Path | None:
        """Count a move; refit after ``every`` (the new file), else fold ``record`` in if ``update`` (eq. 3)."""
        self._since += 1
        if self._since >= self.every:
            return self.refit()
        if self.update and record is not None:
            from microctl.gp.sparse import update

            ctl, u = self.operator.controller, np.asarray(record.u, dtype=float)
            x = np.concatenate([np.asarray(record.state_before, dtype=float), u])
            if ctl.eafm.uses_direction:  # the move's context, after x = [s; u]
                x = np.concatenate([x, ctl.eafm.with_direction(record.direction_before).direction])
            y = record.measured_um - float(np.ravel(self.operator.stage.afm.t_of(u[None, :]))[0])
            if record.solution is not None:  # the hysteresis loop's part of the AFM prediction (0 without)
                y -= record.solution.hysteresis_um
            ctl.reload(update(ctl.eafm.model, x[None, :], [y]))
        return None

    def refit(self) -> Path:
        """Train on the log as it is now, write the next version, switch the controller to it."""

        path = self.operator.log_path
        raw = path.read_bytes()
        log = read_measurements(path, self.operator.stage, min_rows=5)
        version = self.next_version()
        out = self.model.with_name(f"{self.model.stem}.v{version}.npz")
        train(log, self.operator.stage, out=out, restarts=self.restarts, seed=self.seed)
        entry = {"version": version, "model": out.name, "log": str(path), "rows": len(log),
                 "log_sha256": hashlib.sha256(raw).hexdigest(), "restarts": self.restarts, "seed": self.seed,
                 "time_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
                 "reproduce": f"head -n {len(log) + 1} {path} > rows.csv && microctl train rows.csv --config STAGE.yaml "
                              f"-o {out.name} --restarts {self.restarts} --seed {self.seed}"}
        with self.manifest.open("a", encoding="utf-8") as fh:
            fh.write(json.dumps(entry) + "\n")
        self.operator.controller.reload(out)
        self._since = 0
        return out

