"""Moving a stage with a controller, every move logged, and learning from those moves while
operating (:mod:`microctl.api`, docs/api.md)."""

from __future__ import annotations

import hashlib
import json
import re
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from microctl.api.controller import Controller
from microctl.api.stage import read_measurements, train
from microctl.control.result import MoveRecord
from microctl.errors import BackendError, ConfigError, SolveError
from microctl.measurement.appending import append_log_writer
from microctl.measurement.log import Measurement
from microctl.models.direction import after_move
from microctl.models.direction import at_commands as directions_at
from microctl.util.signals import interrupts_deferred, raise_if_interrupted

#: Extra columns of a log that ``Operator`` creates (the measurement-log contract allows extra
#: columns; ``train`` ignores them).
MOVE_LOG_COLUMNS = ("target_um", "controller", "predicted_um", "predicted_std_um")


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
