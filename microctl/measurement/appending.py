"""Appending executed moves to an existing measurement log (``microctl move``, :mod:`microctl.api`)."""

from __future__ import annotations

import csv
import io
from collections.abc import Sequence
from pathlib import Path

from microctl.errors import DataError
from microctl.measurement.log import _ENVIRONMENT_ERRNOS, LogWriteError, MeasurementLogWriter, log_columns, read_log
from microctl.stage.geometry import Stage

__all__ = ["append_log_writer"]


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
    # the caller numbers the rows (seq) and continues the clock itself, so no offsets here
    writer.mode, writer._seq0, writer._time0, writer._tmp = "append", 0, 0.0, None
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
