"""Ctrl-C around moves: held while a move and its log row are written (one step that an interrupt
does not split), and not lost when its KeyboardInterrupt is.

The command line's SIGINT handler (:func:`microctl.cli.main`) records every SIGINT in
:data:`RECEIVED` before it raises KeyboardInterrupt. That KeyboardInterrupt can be lost on its way
out (raised inside compiled code, or in a callback Python cannot raise from): ``microctl move``
on a loaded machine once ran all 400 targets of a sequence after a Ctrl-C and only then exited
130 (tests/cli/test_move_serve.py). Before a command is sent, :func:`raise_if_interrupted` turns
a recorded Ctrl-C back into KeyboardInterrupt, so the stage stops at the next move instead of
running the rest of a sequence.
"""

from __future__ import annotations

import contextlib
import signal
import threading
from typing import Iterator

__all__ = ["interrupts_deferred", "raise_if_interrupted", "RECEIVED"]

#: SIGINTs the command line's handler received during the current command (cleared when a
#: command starts; empty for a library caller, whose own handler is left alone).
RECEIVED: list = []


def raise_if_interrupted() -> None:
    """Raise KeyboardInterrupt if a Ctrl-C was received in this command (its own KeyboardInterrupt
    may have been lost, see the module); call it before a command is sent to the stage."""
    if RECEIVED:
        raise KeyboardInterrupt


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
