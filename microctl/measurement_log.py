"""The measurement log: one CSV row per executed move (``shared/spec/measurement-log.md``).

Columns come from the stage config. For the Table I stage::

    seq,time_s,u_z,u_rx,u_ry,q1,q2,q3,q4,t_prev,q1_prev,q2_prev,q3_prev,q4_prev,t[,extra...]

The writer appends, flushes and fsyncs one row per move, so a run cut short keeps every
completed move. The reader enforces the spec's rules with errors naming the file, the row
(its line number, header = line 1) and the column, and drops nothing.
"""

from __future__ import annotations

import csv
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np

from microctl.backends.base import Measurement
from microctl.config import Stage
from microctl.errors import DataError
from microctl.tabular import parse_number, read_table


def pose_columns(stage: Stage) -> list[str]:
    """``u_<dof>`` names, one per DoF."""
    return [f"u_{d}" for d in stage.dof]


def state_columns(stage: Stage) -> list[str]:
    """Names of the state s = [t; q] entries (tool name, actuator names)."""
    return [stage.tool.name, *stage.actuator_names]


def prev_columns(stage: Stage) -> list[str]:
    """``<name>_prev`` columns of the previous state."""
    return [f"{c}_prev" for c in state_columns(stage)]


def log_columns(stage: Stage, extra: Sequence[str] = ()) -> list[str]:
    """The full header a writer produces, in order."""
    return ["seq", "time_s", *pose_columns(stage), *stage.actuator_names, *prev_columns(stage), stage.tool.name, *extra]


def _fmt(value: float) -> str:
    return repr(float(value))


class MeasurementLogWriter:
    """Write a measurement log row by row.

    Parameters
    ----------
    path : str or Path
        The CSV file (created or overwritten).
    stage : Stage
        Gives the column names.
    extra_columns : sequence of str
        Additional columns (e.g. ``trial``, ``target_um``, ``controller``), written after ``t``.
    fsync : bool
        Also ``os.fsync`` after each row (on by default; survives a power cut).
    """

    def __init__(self, path: str | Path, stage: Stage, extra_columns: Sequence[str] = (), fsync: bool = True):
        self.path = Path(path)
        self.stage = stage
        self.extra_columns = tuple(extra_columns)
        self.columns = log_columns(stage, self.extra_columns)
        if len(set(self.columns)) != len(self.columns):
            raise DataError(f"{self.path}: extra columns {list(self.extra_columns)} clash with the log columns")
        self.fsync = fsync
        try:
            self._fh = self.path.open("w", newline="")
        except OSError as exc:
            raise DataError(f"{self.path}: cannot write: {exc.strerror or exc}") from None
        self._csv = csv.writer(self._fh, lineterminator="\n")
        self._write(self.columns)
        self.rows = 0

    def _write(self, row: Sequence[str]) -> None:
        self._csv.writerow(row)
        self._fh.flush()
        if self.fsync:
            try:
                os.fsync(self._fh.fileno())
            except OSError:
                pass

    def write(
        self,
        m: Measurement,
        s_prev: np.ndarray,
        seq: int | None = None,
        extra: Mapping[str, object] | None = None,
    ) -> None:
        """Append one move.

        Parameters
        ----------
        m : Measurement
            The executed move.
        s_prev : ndarray, shape (1 + n_q,)
            The state before the move, [t_prev, q_prev].
        seq : int, optional
            Default: the number of rows written so far.
        extra : mapping, optional
            Values of the extra columns (missing ones are left empty).
        """
        extra = dict(extra or {})
        unknown = set(extra) - set(self.extra_columns)
        if unknown:
            raise DataError(f"{self.path}: columns {sorted(unknown)} were not declared as extra columns")
        s_prev = np.asarray(s_prev, dtype=float).reshape(-1)
        row = [str(self.rows if seq is None else int(seq)), _fmt(m.time_s)]
        row += [_fmt(v) for v in np.asarray(m.u).reshape(-1)]
        row += [_fmt(v) for v in np.asarray(m.q_um).reshape(-1)]
        row += [_fmt(v) for v in s_prev]
        row.append(_fmt(m.t_um))
        row += ["" if extra.get(c) is None else str(extra[c]) for c in self.extra_columns]
        self._write(row)
        self.rows += 1

    def close(self) -> None:
        """Close the file (idempotent)."""
        if not self._fh.closed:
            self._fh.close()

    def __enter__(self) -> "MeasurementLogWriter":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


@dataclass(frozen=True, eq=False)
class MeasurementLog:
    """A measurement log read and validated.

    Attributes
    ----------
    path : Path
    seq : ndarray of int, shape (n,)
    u : ndarray, shape (n, n_p)
        Control signals (µm, mrad).
    q : ndarray, shape (n, n_q)
        Actuator commands sent, µm.
    t : ndarray, shape (n,)
        Measured tool pose, µm.
    s_prev : ndarray, shape (n, 1 + n_q)
        State before each move [t_prev, q_prev] (from the columns, or the previous row).
    time_s : ndarray (n,) or None
        Settling times, if the log has ``time_s``.
    extra : dict of str -> tuple of str
        Every other column, as text.
    prev_from_columns : bool
        Whether ``s_prev`` came from ``*_prev`` columns.
    """

    path: Path
    seq: np.ndarray
    u: np.ndarray
    q: np.ndarray
    t: np.ndarray
    s_prev: np.ndarray
    time_s: np.ndarray | None
    extra: dict = field(default_factory=dict)
    prev_from_columns: bool = True

    def __len__(self) -> int:
        return int(self.t.shape[0])

    def extra_numeric(self, column: str) -> np.ndarray:
        """An extra column as floats, shape (n,) (DataError naming the row if not numeric)."""
        if column not in self.extra:
            raise DataError(f"{self.path}: missing column '{column}' (extra columns: {', '.join(self.extra)})")
        return np.array([parse_number(text, self.path, k + 2, column) for k, text in enumerate(self.extra[column])])


def read_log(path: str | Path, stage: Stage, min_rows: int = 1) -> MeasurementLog:
    """Read and validate a measurement log.

    Parameters
    ----------
    path : str or Path
    stage : Stage
        Gives the column names.
    min_rows : int
        Fewest rows the caller needs (e.g. for a fit).

    Returns
    -------
    MeasurementLog

    Raises
    ------
    DataError
        Naming the file, the row (line number) and the column: missing required column,
        non-numeric or non-finite value, non-integer, duplicate or non-increasing ``seq``,
        ``*_prev`` columns given only in part, too few rows.
    """
    table = read_table(path, min_rows=0)
    p = table.path
    required = ["seq", *pose_columns(stage), *stage.actuator_names, stage.tool.name]
    missing = [c for c in required if not table.has(c)]
    if missing:
        raise DataError(
            f"{p}: missing required column{'s' if len(missing) > 1 else ''} "
            f"{', '.join(repr(c) for c in missing)} (columns present: {', '.join(table.header)})"
        )
    if len(table.rows) < min_rows:
        raise DataError(f"{p}: {len(table.rows)} data rows, at least {min_rows} needed")
    seq_f = table.numeric("seq")
    for k, v in enumerate(seq_f):
        if v != np.floor(v) or v < 0:
            raise DataError(f"{p}: row {k + 2}, column 'seq': {table.rows[k][table.header.index('seq')].strip()!r} "
                            "is not a non-negative integer")
        if k > 0 and v == seq_f[k - 1]:
            raise DataError(f"{p}: row {k + 2}, column 'seq': duplicate seq {int(v)} (also on row {k + 1})")
        if k > 0 and v < seq_f[k - 1]:
            raise DataError(
                f"{p}: row {k + 2}, column 'seq': seq {int(v)} is not increasing (row {k + 1} has {int(seq_f[k - 1])})"
            )
    u = table.numeric_columns(pose_columns(stage))
    q = table.numeric_columns(list(stage.actuator_names))
    t = table.numeric(stage.tool.name)
    prev = prev_columns(stage)
    present = [c for c in prev if table.has(c)]
    if present and len(present) != len(prev):
        absent = [c for c in prev if c not in present]
        raise DataError(
            f"{p}: the previous-state columns must be given all or none; missing "
            f"{', '.join(repr(c) for c in absent)}"
        )
    if present:
        s_prev = table.numeric_columns(prev)
    else:
        s = np.column_stack([t, q])
        s_prev = np.vstack([np.zeros((1, s.shape[1])), s[:-1]]) if len(t) else np.zeros((0, s.shape[1]))
    time_s = table.numeric("time_s") if table.has("time_s") else None
    used = set(required) | set(prev) | {"time_s"}
    extra = {
        c: tuple(row[j] for row in table.rows) for j, c in enumerate(table.header) if c not in used
    }
    arrays = [seq_f, u, q, t, s_prev] + ([time_s] if time_s is not None else [])
    for a in arrays:
        a.setflags(write=False)
    seq = seq_f.astype(np.int64)
    seq.setflags(write=False)
    return MeasurementLog(
        path=p, seq=seq, u=u, q=q, t=t, s_prev=s_prev, time_s=time_s, extra=extra, prev_from_columns=bool(present)
    )
