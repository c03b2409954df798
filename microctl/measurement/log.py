"""The measurement log: one CSV row per executed move (``shared/spec/measurement-log.md``).

Columns come from the stage config. For the Table I stage::

    seq,time_s,u_z,u_rx,u_ry,q1,q2,q3,q4,t_prev,q1_prev,q2_prev,q3_prev,q4_prev,t[,extra...]

The writer appends, flushes and fsyncs one row per move, so a run cut short keeps every
completed move; a row that cannot be written whole (a full disk) is cut off again, so the
file always ends with the last complete row. The reader enforces the spec's rules with
errors naming the file, the row (its line number, header = line 1) and the column, and
drops nothing. It also refuses rows that no stage of the given config can have produced
(see :func:`read_log`): a command outside the actuator ranges or inconsistent with the
control signal, a gauge reading far beyond what the stage can reach, a clock that is
negative or runs backwards.
"""

from __future__ import annotations

import csv
import errno
import io
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np

from microctl.errors import DataError, MicroctlError
from microctl.models.afm import (
    T_PLAUSIBLE_FACTOR,
    AnalyticForwardModel,
    plausible_t_bound_um,
)
from microctl.stage.geometry import Stage
from microctl.util.tabular import parse_number, read_table


@dataclass(frozen=True)
class Measurement:
    """The result of one executed move.

    Attributes
    ----------
    t_um : float
        Tool pose read by the gauge after settling, µm, relative to the zero state.
    q_um : ndarray, shape (n_q,)
        Actuator displacements sent to the drivers, µm.
    u : ndarray, shape (n_p,)
        The control signal (platform pose) commanded, µm / mrad.
    time_s : float
        Seconds since the start of the run when the move had settled.
    """

    t_um: float
    q_um: np.ndarray
    u: np.ndarray
    time_s: float


#: How far a logged actuator command may lie outside its ``range_um`` (``*_prev``: outside its
#: ``limit_um``) and how far it may differ from K u of the logged control signal, µm: the
#: drivers' positioning accuracy (paper: 0.01 µm), so a log written with 4 decimals reads.
LOG_Q_TOLERANCE_UM = 0.01


#: Largest ``time_s`` accepted, s (about 30 years: the clock counts from the start of the run).
MAX_TIME_S = 1e9

#: Largest ``seq`` accepted (every integer up to it is exact in a float and in int64).
MAX_SEQ = 2**53


#: OS errors that are the machine's fault, not the user's (exit status 1, not 2).
_ENVIRONMENT_ERRNOS = {errno.ENOSPC, errno.EIO, getattr(errno, "EDQUOT", errno.ENOSPC)}


class LogWriteError(MicroctlError):
    """A measurement-log row could not be written (e.g. the disk is full).

    An environment failure (exit status 1): the file keeps every row completed before, and
    the message says how many.
    """


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
            self._fh = self.path.open("wb", buffering=0)
        except OSError as exc:
            cls = LogWriteError if exc.errno in _ENVIRONMENT_ERRNOS else DataError
            raise cls(f"{self.path}: cannot write: {exc.strerror or exc}") from None
        self._size = 0
        self.rows = 0
        try:
            self._write(self.columns, what="the header")
        except LogWriteError:
            self.close()
            raise

    def _write(self, row: Sequence[str], *, what: str) -> None:
        """Append one whole CSV line; on failure cut the file back to its last complete line."""
        buf = io.StringIO()
        csv.writer(buf, lineterminator="\n").writerow(row)
        data = buf.getvalue().encode("utf-8")
        fd = self._fh.fileno()
        try:
            view = memoryview(data)
            while view:
                n = os.write(fd, view)
                view = view[n:]
            if self.fsync:
                try:
                    os.fsync(fd)
                except OSError as exc:
                    if exc.errno not in (errno.EINVAL, errno.ENOTSUP, errno.EROFS):  # e.g. a pipe or /dev/null
                        raise
        except OSError as exc:
            try:
                os.ftruncate(fd, self._size)
                os.lseek(fd, self._size, os.SEEK_SET)
            except OSError:
                pass
            raise LogWriteError(
                f"{self.path}: cannot write {what}: {exc.strerror or exc}; the log keeps the "
                f"{self.rows} completed move{'' if self.rows == 1 else 's'} written before"
            ) from None
        self._size += len(data)

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
        self._write(row, what=f"the row of move {self.rows + 1} (the move was executed)")
        self.rows += 1

    def close(self) -> None:
        """Close the file (idempotent; every row is already on disk)."""
        if not self._fh.closed:
            try:
                self._fh.close()
            except OSError:
                pass

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
    implausible : tuple of ImplausibleRow
        Rows the stage cannot have produced, when read with ``plausibility="report"``.
    """

    path: Path
    seq: np.ndarray
    u: np.ndarray
    q: np.ndarray
    t: np.ndarray
    s_prev: np.ndarray
    time_s: np.ndarray | None
    extra: dict = field(default_factory=dict)
    implausible: tuple = ()
    prev_from_columns: bool = True

    def __len__(self) -> int:
        return int(self.t.shape[0])

    def extra_numeric(self, column: str) -> np.ndarray:
        """An extra column as floats, shape (n,) (DataError naming the row if not numeric)."""
        if column not in self.extra:
            raise DataError(f"{self.path}: missing column '{column}' (extra columns: {', '.join(self.extra)})")
        return np.array([parse_number(text, self.path, k + 2, column) for k, text in enumerate(self.extra[column])])


def read_log(path: str | Path, stage: Stage, min_rows: int = 1, *, plausibility: str = "raise") -> MeasurementLog:
    """Read and validate a measurement log.

    Parameters
    ----------
    path : str or Path
    stage : Stage
        Gives the column names.
    min_rows : int
        Fewest rows the caller needs (e.g. for a fit).
    plausibility : {"raise", "report"}
        What a row the stage cannot have produced (:func:`implausible_rows`) does: ``raise``
        (default: a DataError for the first) or ``report`` (kept, listed in
        ``MeasurementLog.implausible``: for ``diagnose``, which sets such rows aside as
        outliers and names them).

    Returns
    -------
    MeasurementLog

    Raises
    ------
    DataError
        Naming the file, the row (line number) and the column: missing required column,
        non-numeric or non-finite value, non-integer, duplicate or non-increasing ``seq``,
        ``seq`` above :data:`MAX_SEQ`, ``*_prev`` columns given only in part, too few rows;
        and rows the stage cannot have produced (:func:`implausible_rows`).
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
    seq_f = _read_seq(table)
    u = table.numeric_columns(pose_columns(stage))
    q = table.numeric_columns(list(stage.actuator_names))
    t = table.numeric(stage.tool.name)
    prev = prev_columns(stage)
    present, s_prev = _read_prev(table, prev, t, q)
    time_s = table.numeric("time_s") if table.has("time_s") else None
    used = set(required) | set(prev) | {"time_s"}
    extra = {
        c: tuple(row[j] for row in table.rows) for j, c in enumerate(table.header) if c not in used
    }
    if plausibility not in ("raise", "report"):
        raise ValueError(f"plausibility must be 'raise' or 'report', got {plausibility!r}")
    implausible = tuple(implausible_rows(stage, u, q, t, s_prev if present else None, time_s))
    if implausible and plausibility == "raise":
        raise _implausible_error(p, implausible[0])
    arrays = [seq_f, u, q, t, s_prev] + ([time_s] if time_s is not None else [])
    for a in arrays:
        a.setflags(write=False)
    seq = seq_f.astype(np.int64)
    seq.setflags(write=False)
    return MeasurementLog(
        path=p, seq=seq, u=u, q=q, t=t, s_prev=s_prev, time_s=time_s, extra=extra, prev_from_columns=bool(present),
        implausible=implausible,
    )



def append_log_writer(path: str | Path, stage: Stage, extra_columns: Sequence[str] = (),
                      fsync: bool = True) -> tuple[MeasurementLogWriter, int, float]:
    """A writer that appends moves to the measurement log at ``path`` (``microctl move``).

    A missing or empty file is created with the columns of ``stage`` and ``extra_columns``. An
    existing log is read and validated first (:func:`read_log`) and must have the columns a
    writer produces for ``stage`` (its own extra columns, whatever they are, are kept and
    filled where the caller gives them); its last line must be complete. Rows are appended
    with the writer's usual guarantees (one whole line at a time, flushed).

    Parameters
    ----------
    path : str or Path
    stage : Stage
    extra_columns : sequence of str
        Extra columns of a new file.
    fsync : bool

    Returns
    -------
    writer : MeasurementLogWriter
        Its ``extra_columns`` are the file's.
    next_seq : int
        The ``seq`` of the next row (one past the log's last).
    last_time_s : float
        The log's last ``time_s`` (0 when it has none): a new run's clock continues from it,
        since ``time_s`` must not decrease along ``seq``.

    Raises
    ------
    DataError
        The file is not a log of this stage that a writer can append to (naming why).
    """
    path = Path(path)
    if not path.exists() or (path.is_file() and path.stat().st_size == 0):
        return MeasurementLogWriter(path, stage, extra_columns, fsync=fsync), 0, 0.0
    log = read_log(path, stage, min_rows=0, plausibility="report")
    raw = path.read_bytes()
    header = next(csv.reader(io.StringIO(raw.decode("utf-8-sig").split("\n", 1)[0])))
    base = log_columns(stage)
    if header[: len(base)] != base:
        raise DataError(f"{path}: cannot append: its columns {header} are not those a measurement-log writer "
                        f"produces for stage '{stage.name}' ({base} then extra columns); give a new file")
    if not raw.endswith(b"\n"):
        raise DataError(f"{path}: cannot append: its last line is incomplete (no line break at the end)")
    writer = MeasurementLogWriter.__new__(MeasurementLogWriter)
    writer.path, writer.stage, writer.fsync = path, stage, fsync
    writer.extra_columns = tuple(header[len(base):])
    writer.columns = list(header)
    try:
        writer._fh = path.open("ab", buffering=0)
    except OSError as exc:
        cls = LogWriteError if exc.errno in _ENVIRONMENT_ERRNOS else DataError
        raise cls(f"{path}: cannot write: {exc.strerror or exc}") from None
    writer._size = len(raw)
    writer.rows = len(log)
    last_time = float(log.time_s[-1]) if log.time_s is not None and len(log) else 0.0
    return writer, (int(log.seq[-1]) + 1 if len(log) else 0), last_time


def _read_seq(table) -> np.ndarray:
    """The ``seq`` column, shape (n,): non-negative integers up to :data:`MAX_SEQ`, increasing."""
    p = table.path
    seq_f = table.numeric("seq")
    for k, v in enumerate(seq_f):
        if v > MAX_SEQ:
            raise DataError(f"{p}: row {k + 2}, column 'seq': {table.rows[k][table.header.index('seq')].strip()!r} "
                            f"is too large (at most {MAX_SEQ})")
        if v != np.floor(v) or v < 0:
            raise DataError(f"{p}: row {k + 2}, column 'seq': {table.rows[k][table.header.index('seq')].strip()!r} "
                            "is not a non-negative integer")
        if k > 0 and v == seq_f[k - 1]:
            raise DataError(f"{p}: row {k + 2}, column 'seq': duplicate seq {int(v)} (also on row {k + 1})")
        if k > 0 and v < seq_f[k - 1]:
            raise DataError(
                f"{p}: row {k + 2}, column 'seq': seq {int(v)} is not increasing (row {k + 1} has {int(seq_f[k - 1])})"
            )
    return seq_f


def _read_prev(table, prev: list, t: np.ndarray, q: np.ndarray) -> tuple[bool, np.ndarray]:
    """The previous state s_prev, shape (n, 1 + n_q): from the ``*_prev`` columns (all or none),
    else the row before (zeros before the first). Returns whether the columns were present too."""
    p = table.path
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
    return bool(present), s_prev



@dataclass(frozen=True)
class ImplausibleRow:
    """A log row no stage of the config can have produced (:func:`implausible_rows`).

    Attributes
    ----------
    row : int
        0-based data row (CSV line ``row + 2``).
    column : str
        The column at fault (or the pose columns, comma-separated).
    message : str
        What is wrong, without the file and row prefix.
    """

    row: int
    column: str
    message: str


def implausible_rows(
    stage: Stage,
    u: np.ndarray,
    q: np.ndarray,
    t: np.ndarray,
    s_prev: np.ndarray | None = None,
    time_s: np.ndarray | None = None,
) -> list[ImplausibleRow]:
    """Every log row that no stage of this config can have produced, in row order.

    Rules:

    - u in the workspace: every K u (CAD inverse kinematics, eq. 12) within its actuator's
      ``range_um`` ± :data:`LOG_Q_TOLERANCE_UM`;
    - each q within its ``range_um`` ± the tolerance, and within the tolerance of K u;
    - each ``*_prev`` q within its hardware ``limit_um`` ± the tolerance (a run may start
      where another left the stage);
    - |t| and |t_prev| at most :func:`plausible_t_bound_um`;
    - ``time_s`` in [0, :data:`MAX_TIME_S`] and not decreasing from row to row.

    Parameters
    ----------
    stage : Stage
    u : ndarray, shape (n, n_p)
    q : ndarray, shape (n, n_q)
    t : ndarray, shape (n,)
    s_prev : ndarray, shape (n, 1 + n_q), optional
        From ``*_prev`` columns (None: not in the file).
    time_s : ndarray, shape (n,), optional
    """
    if len(t) == 0:
        return []
    out = _command_rows(stage, u, q)
    if s_prev is not None:
        out += _prev_rows(stage, s_prev[:, 1:])
    tname, t_max = stage.tool.name, plausible_t_bound_um(stage)
    out += _reading_rows(t_max, tname, t)
    if s_prev is not None:
        out += _reading_rows(t_max, f"{tname}_prev", s_prev[:, 0])
    if time_s is not None:
        out += _time_rows(time_s)
    return sorted(out, key=lambda r: r.row)  # stable: within a row, in the order of the rules


def _each(bad: np.ndarray):
    """(row, column index) of the first bad column of every bad row of ``bad`` (n, m)."""
    for k in np.flatnonzero(bad.any(axis=1)):
        yield int(k), int(np.argmax(bad[k]))


def _command_rows(stage: Stage, u: np.ndarray, q: np.ndarray) -> list[ImplausibleRow]:
    """Rows whose u is outside the workspace, whose q is outside its range or differs from K u (eq. 12)."""
    afm = AnalyticForwardModel(stage)
    names = stage.actuator_names
    lo, hi = stage.range_lo, stage.range_hi
    tol = LOG_Q_TOLERANCE_UM
    ucols = ",".join(pose_columns(stage))
    out: list[ImplausibleRow] = []
    Ku = u @ afm.K.T
    for k, i in _each((Ku < lo - tol) | (Ku > hi + tol)):
        out.append(ImplausibleRow(k, ucols, f"u = [{', '.join(f'{v:.6g}' for v in u[k])}] is outside the workspace: "
                                            f"K u puts actuator {names[i]} at {Ku[k, i]:.4f} µm, outside its range "
                                            f"[{lo[i]:g}, {hi[i]:g}] µm"))
    for k, i in _each((q < lo - tol) | (q > hi + tol)):
        out.append(ImplausibleRow(k, names[i], f"{q[k, i]:.6g} µm is outside the actuator's range [{lo[i]:g}, "
                                               f"{hi[i]:g}] µm (range_um in the stage config; tolerance {tol:g} µm)"))
    for k, i in _each(np.abs(q - Ku) > tol):
        out.append(ImplausibleRow(k, names[i], f"{q[k, i]:.6g} µm differs from K u = {Ku[k, i]:.6g} µm of this row's "
                                               f"control signal by {abs(q[k, i] - Ku[k, i]):.3g} µm (tolerance {tol:g} "
                                               "µm); the log does not belong to this stage geometry, or its q or u "
                                               "columns are wrong"))
    return out


def _prev_rows(stage: Stage, q_prev: np.ndarray) -> list[ImplausibleRow]:
    """Rows whose ``*_prev`` q (n, n_q) is outside its hardware limit."""
    names = stage.actuator_names
    tol = LOG_Q_TOLERANCE_UM
    lim_lo = np.array([a.limit_um[0] for a in stage.actuators])
    lim_hi = np.array([a.limit_um[1] for a in stage.actuators])
    return [ImplausibleRow(k, f"{names[i]}_prev", f"{q_prev[k, i]:.6g} µm is outside the actuator's "
                                                  f"hardware limit [{lim_lo[i]:g}, {lim_hi[i]:g}] µm "
                                                  "(limit_um in the stage config)")
            for k, i in _each((q_prev < lim_lo - tol) | (q_prev > lim_hi + tol))]


def _reading_rows(t_max: float, name: str, col: np.ndarray) -> list[ImplausibleRow]:
    """Rows whose reading ``col`` (n,) is beyond ``t_max`` (:func:`plausible_t_bound_um`)."""
    return [ImplausibleRow(k, name, f"{col[k]:.6g} µm is implausible: the stage reaches at most |t| = "
                                    f"{t_max / T_PLAUSIBLE_FACTOR:.6g} µm and readings beyond "
                                    f"{T_PLAUSIBLE_FACTOR:g} times that are refused (wrong unit, an untared "
                                    "gauge or a corrupt file?)")
            for k, _ in _each((np.abs(col) > t_max)[:, None])]


def _time_rows(time_s: np.ndarray) -> list[ImplausibleRow]:
    """Rows whose ``time_s`` is outside [0, :data:`MAX_TIME_S`] or earlier than the row before."""
    out = [ImplausibleRow(k, "time_s", f"{time_s[k]:.6g} s is outside [0, {MAX_TIME_S:g}] (seconds since "
                                       "the start of the run)")
           for k, _ in _each(((time_s < 0) | (time_s > MAX_TIME_S))[:, None])]
    back = np.concatenate([[False], np.diff(time_s) < 0])
    for k, _ in _each(back[:, None]):
        out.append(ImplausibleRow(k, "time_s", f"{time_s[k]:.6g} s is earlier than {time_s[k - 1]:.6g} s on row "
                                               f"{k + 1}; time_s must not decrease in seq order"))
    return out


def _implausible_error(path: Path | str, r: ImplausibleRow) -> DataError:
    col = f"columns {r.column}" if "," in r.column else f"column '{r.column}'"
    return DataError(f"{path}: row {r.row + 2}, {col}: {r.message}")
