"""Holding Ctrl-C while a move and its log row are written (one step that an interrupt does not split)."""

from __future__ import annotations

import contextlib
import signal
import threading
from typing import Iterator

__all__ = ["interrupts_deferred"]


@contextlib.contextmanager
def interrupts_deferred() -> Iterator[None]:
    """Hold Ctrl-C (SIGINT) until the block ends, so a move is never executed without its log row.

    In the main thread only (elsewhere signals are not delivered to Python anyway). A SIGINT in
    the block is re-raised as KeyboardInterrupt when it ends, through the handler that was set.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    got: list[tuple] = []
    old = signal.signal(signal.SIGINT, lambda *a: got.append(a))
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, old)
        if got:
            if callable(old):
                old(*got[0])
            elif old != signal.SIG_IGN:
                raise KeyboardInterrupt
