"""Progress reporting on stderr for long work (hidden when not a terminal or ``--quiet``)."""

from __future__ import annotations

import sys
import time
from typing import TextIO


class Progress:
    """A one-line progress counter written to stderr.

    Parameters
    ----------
    total : int
        Number of steps.
    label : str
        What is being counted.
    quiet : bool
        Hide all output.
    stream : file, optional
        Where to write (default ``sys.stderr``); output is shown only when it is a terminal.
    """

    def __init__(self, total: int, label: str, *, quiet: bool = False, stream: TextIO | None = None):
        self.total = int(total)
        self.label = label
        self.stream = stream if stream is not None else sys.stderr
        isatty = getattr(self.stream, "isatty", lambda: False)
        self.enabled = (not quiet) and bool(isatty())
        self.count = 0
        self._t0 = time.perf_counter()

    def step(self, n: int = 1, info: str = "") -> None:
        """Advance by ``n`` steps and redraw the line."""
        self.count += n
        if self.enabled:
            elapsed = time.perf_counter() - self._t0
            self.stream.write(f"\r{self.label}: {self.count}/{self.total} ({elapsed:.1f} s) {info}   ")
            self.stream.flush()

    def close(self) -> None:
        """Finish the line."""
        if self.enabled:
            self.stream.write("\n")
            self.stream.flush()

    def __enter__(self) -> "Progress":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
