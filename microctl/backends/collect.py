"""Execute training moves on a backend and write them as a measurement log.

The moves come from a training design (:mod:`microctl.measurement.design`: ``covering_still`` by default,
``space_filling`` for the paper's IV-A design), or one at a time from a trained model
(:mod:`microctl.control.refine`); :func:`run_collect` executes them one by one, logging each
completed move at once, so that a failure keeps every completed move.
"""

from __future__ import annotations

from pathlib import Path
from typing import Iterable

import numpy as np

from microctl.backends.base import StageBackend
from microctl.errors import BackendError
from microctl.measurement.design import space_filling_moves, training_moves  # noqa: F401  (re-exported)
from microctl.measurement.log import MeasurementLogWriter
from microctl.util.progress import Progress

__all__ = ["run_collect", "execute_moves", "training_moves", "space_filling_moves"]


def execute_moves(backend: StageBackend, moves: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Execute moves on a backend and keep the log's arrays in memory (no file; for benchmarks).

    Returns
    -------
    s_prev : ndarray, shape (n, n_s)
        State before each move.
    u : ndarray, shape (n, n_p)
    t : ndarray, shape (n,)
        Gauge reading after each move (µm).
    """
    s_prev, t = [], []
    for u in np.atleast_2d(moves):
        s_prev.append(backend.state)
        t.append(backend.move(u).t_um)
    return np.array(s_prev), np.atleast_2d(moves).astype(float), np.array(t)


def run_collect(
    backend: StageBackend,
    moves: np.ndarray | Iterable[np.ndarray],
    out: str | Path,
    *,
    quiet: bool = False,
    mode: str = "write",
    total: int | None = None,
) -> int:
    """Execute moves on a backend, writing the measurement log row by row.

    Parameters
    ----------
    backend : StageBackend
    moves : ndarray, shape (n, n_p), or iterable of ndarray, shape (n_p,)
        The commands; an iterable is read one move at a time, each after the previous one was
        executed (a generator may read the backend's state).
    out : path
        The log file (overwritten).
    quiet : bool
        Hide progress on stderr.
    mode : {"write", "replace", "append"}
        How the log is opened (:data:`microctl.measurement.log.WRITE_MODES`).
    total : int, optional
        How many moves an iterable gives (for the progress and the messages); an array's length.

    Returns
    -------
    int
        Number of completed moves (all of them).

    Raises
    ------
    BackendError
        From a failed move; the log keeps every move completed before it, and the message
        says how many.
    """
    if isinstance(moves, (np.ndarray, list, tuple)):
        moves = np.atleast_2d(np.asarray(moves, dtype=float))
        total = len(moves)
    n = 0
    with MeasurementLogWriter(out, backend.stage, mode=mode) as log, Progress(total or 0, "collect", quiet=quiet) as prog:
        for k, u in enumerate(moves):
            s_prev = backend.state
            try:
                m = backend.move(u)
            except BackendError as exc:
                raise BackendError(
                    f"move {k + 1} of {total if total is not None else '?'} failed: {exc}; {out} keeps the {k} completed moves"
                    + (" (after its earlier rows)" if mode == "append" else "")
                ) from None
            log.write(m, s_prev, seq=k)
            n = k + 1
            prog.step(info=f"t = {m.t_um:.3f} µm")
    return n
