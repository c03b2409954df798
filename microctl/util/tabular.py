"""Reading numeric CSV tables with errors that name the file, the row and the column.

Rows are counted as the file's line numbers (the header is line 1), so an error points
at the line a user would open in an editor.

Numbers are read strictly: optional sign, digits with an optional decimal point, optional
exponent (``-1.5``, ``.5``, ``2e-3``). Python's ``float()`` is more lenient (``1_0.5`` is 10.5
to it, and it reads non-ASCII digits); such text is refused, not guessed at. Files are read
as UTF-8; a leading byte-order mark (as spreadsheet programs write) is skipped.
"""

from __future__ import annotations

import csv
import io
import math
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from microctl.errors import DataError

#: A decimal number as a CSV field may hold it (ASCII only, no ``_`` separators).
NUMBER_PATTERN = re.compile(r"[+-]?(?:[0-9]+(?:\.[0-9]*)?|\.[0-9]+)(?:[eE][+-]?[0-9]+)?")

_NON_FINITE = {"nan", "+nan", "-nan", "inf", "+inf", "-inf", "infinity", "+infinity", "-infinity"}


def parse_number(text: str, path: Path | str, line: int, column: str) -> float:
    """One CSV field as a finite float, else a DataError naming file, row (line) and column.

    Accepted: :data:`NUMBER_PATTERN` (surrounding spaces are ignored).
    """
    text = text.strip()
    where = f"{path}: row {line}, column '{column}'"
    if NUMBER_PATTERN.fullmatch(text) is None:
        if text.lower() in _NON_FINITE:
            raise DataError(f"{where}: value '{text}' is not finite")
        raise DataError(f"{where}: {text!r} is not a number (expected e.g. 12, -0.5 or 1.5e-3; "
                        "no '_', ',' or other separators)")
    value = float(text)
    if not math.isfinite(value):
        raise DataError(f"{where}: value '{text}' is not finite (beyond the float range)")
    return value


@dataclass(frozen=True)
class Table:
    """A CSV file read as text, with its header.

    Attributes
    ----------
    path : Path
        The file read.
    header : tuple of str
        Column names, in file order.
    rows : tuple of tuple of str
        The data rows as text; ``rows[k]`` is on line ``k + 2`` of the file.
    """

    path: Path
    header: tuple[str, ...]
    rows: tuple[tuple[str, ...], ...]

    def has(self, column: str) -> bool:
        """Whether the table has ``column``."""
        return column in self.header

    def numeric(self, column: str) -> np.ndarray:
        """Column ``column`` as a float array, shape (n_rows,).

        Raises
        ------
        DataError
            If the column is missing or a value is not a finite number.
        """
        if column not in self.header:
            raise DataError(
                f"{self.path}: missing required column '{column}' (columns present: {', '.join(self.header)})"
            )
        j = self.header.index(column)
        return np.array([parse_number(row[j], self.path, k + 2, column) for k, row in enumerate(self.rows)])

    def numeric_columns(self, columns: Sequence[str]) -> np.ndarray:
        """Several columns as a float array, shape (n_rows, len(columns))."""
        if not columns:
            return np.empty((len(self.rows), 0))
        return np.column_stack([self.numeric(c) for c in columns])


def _refuse_other_formats(path: Path, text: str) -> None:
    """DataError for a JSON or YAML file given where a CSV table is expected."""
    head = text.lstrip()[:1]
    lines = [ln for ln in text.splitlines()[:50] if ln.strip() and not ln.lstrip().startswith("#")]
    first = lines[0].strip() if lines else ""
    if head in ("{", "["):
        raise DataError(f"{path}: this is JSON (it starts with '{head}'), not a CSV table; expected a header row "
                        "of column names, then one comma-separated row per line")
    if first.startswith("---") or (":" in first and "," not in first and first.rstrip().endswith(":")):
        raise DataError(f"{path}: this looks like YAML ('{first[:40]}'), not a CSV table; a stage or experiment "
                        "file goes to --config or `microctl experiment`")


def read_table(path: str | Path, *, min_rows: int = 1) -> Table:
    """Read a comma-separated file with a header row.

    Parameters
    ----------
    path : str or Path
        The CSV file.
    min_rows : int
        Fewest data rows accepted.

    Raises
    ------
    DataError
        Unreadable file, empty file, duplicate column names, ragged rows, too few rows.
    """
    path = Path(path)
    if path.exists() and not path.is_dir() and not path.is_file():  # a FIFO or device: reading would block
        raise DataError(f"{path}: is not a regular file (a FIFO, socket or device); give a CSV file")
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise DataError(f"{path}: cannot read: {exc.strerror or exc}") from None
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        line = raw.count(b"\n", 0, exc.start) + 1
        raise DataError(
            f"{path}: not a text CSV file: byte 0x{raw[exc.start]:02x} on line {line} is not UTF-8"
        ) from None
    _refuse_other_formats(path, text)
    reader = csv.reader(io.StringIO(text, newline=""))
    try:
        try:
            header = tuple(h.strip() for h in next(reader))
        except StopIteration:
            raise DataError(f"{path}: the file is empty (expected a header row)") from None
        rows = []
        for line_no, row in enumerate(reader, start=2):
            if not row or all(not c.strip() for c in row):
                raise DataError(f"{path}: row {line_no} is empty (blank lines are not allowed)")
            if len(row) != len(header):
                raise DataError(
                    f"{path}: row {line_no} has {len(row)} fields, the header has {len(header)}"
                )
            rows.append(tuple(row))
    except csv.Error as exc:
        raise DataError(f"{path}: line {reader.line_num}: not a valid CSV line: {exc}") from None
    seen = set()
    for name in header:
        if name in seen:
            raise DataError(f"{path}: column '{name}' appears twice in the header")
        seen.add(name)
    if len(rows) < min_rows:
        raise DataError(f"{path}: {len(rows)} data rows, at least {min_rows} needed")
    return Table(path=path, header=header, rows=tuple(rows))
