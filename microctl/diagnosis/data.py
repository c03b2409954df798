"""The measured data a diagnosis works on, as arrays (built from a measurement log).

Everything the causes need per executed move k: the pose command u_k, the actuator
commands q_k (eq. 12, as sent), the state before the move s_k = [t_prev; q_prev], the
settling time, and the direction each actuator last moved (backlash state: the sign of
Δq_i, a zero step keeping the previous row's sign, the first rows starting "up" as the
zero state of :mod:`microctl.stage.physics`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from microctl.errors import DataError
from microctl.measurement.log import MeasurementLog
from microctl.stage.geometry import Stage
from microctl.stage.physics import directions_from_steps

#: Fewest moves a diagnosis accepts (the largest joint fit has ~8 parameters, the
#: structure test ~25 regressors; below this nothing is significant anyway).
MIN_ROWS = 40


@dataclass(frozen=True, eq=False)
class DiagnosisData:
    """Measured moves in execution order.

    Attributes
    ----------
    u : ndarray, shape (n, n_p)
        Commanded platform poses (µm, mrad).
    q : ndarray, shape (n, n_q)
        Actuator commands, µm.
    q_prev : ndarray, shape (n, n_q)
        Actuator commands before each move, µm.
    t : ndarray, shape (n,)
        Measured tool pose, µm.
    t_prev : ndarray, shape (n,)
        Measured tool pose before each move, µm.
    time_s : ndarray, shape (n,) or None
        Settling time of each move, s (None when the log has no ``time_s``).
    direction : ndarray, shape (n, n_q)
        Direction (±1) each actuator last moved, for backlash.
    source : str
        Where the data came from (for messages).
    seq : ndarray of int, shape (n,), optional
        The log's ``seq`` of each row (default 0..n−1).
    line : ndarray of int, shape (n,), optional
        Line number of each row in the log file (header = line 1), when read from a file.
    """

    u: np.ndarray
    q: np.ndarray
    q_prev: np.ndarray
    t: np.ndarray
    t_prev: np.ndarray
    time_s: np.ndarray | None
    direction: np.ndarray
    source: str = "<memory>"
    seq: np.ndarray | None = None
    line: np.ndarray | None = None

    def row_ids(self, idx: np.ndarray) -> list[dict]:
        """``{"index", "seq", "line"}`` of rows ``idx`` (0-based indices into this data), for reports."""
        out = []
        for k in np.asarray(idx, dtype=int):
            out.append({"index": int(k), "seq": int(self.seq[k]) if self.seq is not None else int(k),
                        "line": int(self.line[k]) if self.line is not None else None})
        return out

    @property
    def n(self) -> int:
        """Number of moves."""
        return int(self.t.shape[0])

    @property
    def dq(self) -> np.ndarray:
        """Actuator steps q − q_prev, shape (n, n_q)."""
        return self.q - self.q_prev

    @property
    def s_prev(self) -> np.ndarray:
        """State before each move [t_prev, q_prev], shape (n, 1 + n_q) (the EAFM's s)."""
        return np.column_stack([self.t_prev, self.q_prev])

    def gp_inputs(self) -> np.ndarray:
        """EAFM GP input x = [s; u] (paper eq. 3), shape (n, 1 + n_q + n_p)."""
        return np.hstack([self.s_prev, self.u])

    def subset(self, idx: np.ndarray) -> "DiagnosisData":
        """The rows ``idx`` (their backlash directions computed on the whole run are kept)."""
        idx = np.asarray(idx)
        return DiagnosisData(
            u=self.u[idx],
            q=self.q[idx],
            q_prev=self.q_prev[idx],
            t=self.t[idx],
            t_prev=self.t_prev[idx],
            time_s=None if self.time_s is None else self.time_s[idx],
            direction=self.direction[idx],
            source=self.source,
            seq=None if self.seq is None else self.seq[idx],
            line=None if self.line is None else self.line[idx],
        )

    def with_t(self, t: np.ndarray) -> "DiagnosisData":
        """A copy with other readings (same moves), e.g. to plant an effect in a test."""
        t = np.asarray(t, dtype=float).reshape(-1)
        if t.shape != self.t.shape:
            raise DataError(f"{self.source}: {t.size} readings for {self.n} moves")
        return DiagnosisData(self.u, self.q, self.q_prev, t, self.t_prev, self.time_s, self.direction, self.source,
                             self.seq, self.line)


def data_from_arrays(
    u: np.ndarray,
    q: np.ndarray,
    t: np.ndarray,
    *,
    q_prev: np.ndarray | None = None,
    t_prev: np.ndarray | None = None,
    time_s: np.ndarray | None = None,
    source: str = "<memory>",
    seq: np.ndarray | None = None,
    line: np.ndarray | None = None,
) -> DiagnosisData:
    """Build :class:`DiagnosisData` from arrays of one run in execution order.

    Parameters
    ----------
    u : ndarray, shape (n, n_p)
    q : ndarray, shape (n, n_q)
    t : ndarray, shape (n,)
    q_prev, t_prev : ndarray, optional
        Previous state; default the previous row (zero state before the first).
    time_s : ndarray (n,), optional
    source : str
    seq, line : ndarray (n,), optional
        The log's ``seq`` and the file's line numbers of the rows (for reports).
    """
    u = np.atleast_2d(np.asarray(u, dtype=float))
    q = np.atleast_2d(np.asarray(q, dtype=float))
    t = np.asarray(t, dtype=float).reshape(-1)
    n = t.size
    if u.shape[0] != n or q.shape[0] != n:
        raise DataError(f"{source}: u has {u.shape[0]} rows, q {q.shape[0]}, t {n}; they must match")
    if q_prev is None:
        q_prev = np.vstack([np.zeros((1, q.shape[1])), q[:-1]])
    if t_prev is None:
        t_prev = np.concatenate([[0.0], t[:-1]])
    q_prev = np.atleast_2d(np.asarray(q_prev, dtype=float))
    direction = directions_from_steps(q - q_prev, 1.0)  # physics: zero state approached "up"
    return DiagnosisData(
        u=u,
        q=q,
        q_prev=q_prev,
        t=t,
        t_prev=np.asarray(t_prev, dtype=float).reshape(-1),
        time_s=None if time_s is None else np.asarray(time_s, dtype=float).reshape(-1),
        direction=direction,
        source=source,
        seq=None if seq is None else np.asarray(seq, dtype=int),
        line=None if line is None else np.asarray(line, dtype=int),
    )


def data_from_log(log: MeasurementLog, stage: Stage) -> DiagnosisData:
    """Build :class:`DiagnosisData` from a validated measurement log.

    Raises
    ------
    DataError
        Too few rows (fewer than :data:`MIN_ROWS`).
    """
    if len(log) < MIN_ROWS:
        raise DataError(f"{log.path}: {len(log)} moves; a diagnosis needs at least {MIN_ROWS}")
    return data_from_arrays(
        log.u,
        log.q,
        log.t,
        q_prev=log.s_prev[:, 1:],
        t_prev=log.s_prev[:, 0],
        time_s=log.time_s,
        source=str(log.path),
        seq=log.seq,
        line=np.arange(len(log)) + 2,  # the reader keeps every row, in file order (header = line 1)
    )


def read_for_diagnosis(path, stage: Stage) -> tuple[DiagnosisData, np.ndarray, tuple]:
    """Read a measurement log for a diagnosis: rows no stage can have produced (a corrupt cell,
    :func:`microctl.measurement.log.implausible_rows`) are kept and marked, to be set aside as
    outliers and named by row (``run_diagnosis(set_aside=...)``), not refused.

    Returns
    -------
    data : DiagnosisData
    set_aside : ndarray of bool, shape (n,)
    implausible : tuple of ImplausibleRow
    """
    from microctl.measurement.log import read_log

    log = read_log(path, stage, plausibility="report")
    set_aside = np.zeros(len(log), dtype=bool)
    set_aside[[r.row for r in log.implausible]] = True
    return data_from_log(log, stage), set_aside, log.implausible
