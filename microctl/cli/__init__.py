"""The ``microctl`` command line (contract: ``shared/spec/cli.md``, copied in docs/cli.md).

Each sub-command lives in its own module under :mod:`microctl.cli.commands` and exposes
``register(subparsers)``; this module discovers them, so adding a command never edits
this file. Exit status: 0 success, 2 usage or input error (one line on stderr, no
traceback), 1 any other failure (also an ``OSError`` from writing results, e.g. a full
disk, or running out of memory: one line, no traceback), 130 interrupted (Ctrl-C, at any
point once this module is imported: also while argparse, the command modules and their
NumPy/CasADi imports load, which takes most of a second). This module imports only ``sys``
and :mod:`microctl.errors` at import time, so that window starts a few milliseconds after
the interpreter.
"""

from __future__ import annotations

import sys
from typing import TYPE_CHECKING

from microctl.errors import INPUT_ERRORS, MicroctlError

if TYPE_CHECKING:  # pragma: no cover
    import argparse
    from typing import Sequence


def _parser_class() -> type:
    """ArgumentParser whose usage errors are one line and exit status 2 (argparse imported here)."""
    import argparse

    class _Parser(argparse.ArgumentParser):
        def error(self, message: str) -> None:  # noqa: D401 - argparse API
            self.exit(2, f"{self.prog}: error: {message}\n")

    return _Parser


def build_parser() -> argparse.ArgumentParser:
    """Build the top-level parser with every discovered sub-command."""
    from microctl._version import __version__

    _Parser = _parser_class()
    parser = _Parser(
        prog="microctl",
        description="Accurate, repeatable position control of piezo micromanipulators (EAFM).",
    )
    parser.add_argument("--version", action="version", version=f"microctl {__version__}")
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)
    import importlib
    import pkgutil

    import microctl.cli.commands as commands_pkg

    for info in sorted(pkgutil.iter_modules(commands_pkg.__path__), key=lambda m: m.name):
        if info.name.startswith("_"):
            continue
        module = importlib.import_module(f"microctl.cli.commands.{info.name}")
        module.register(subparsers)
    return parser


def _one_line(exc: BaseException) -> str:
    """The message on one line: line breaks that came with a quoted value are shown escaped."""
    return str(exc).replace("\r", "\\r").replace("\n", "\\n")


#: SIGINTs received during the current :func:`main` (a Ctrl-C a library swallowed, or one that
#: surfaced as another exception, e.g. ``ImportError: initialization failed`` from a compiled
#: module being loaded, still ends the command with 130).
_SIGINTS: list = []


def _on_sigint(signum, frame) -> None:  # noqa: ARG001 - signal handler API
    _SIGINTS.append(signum)
    raise KeyboardInterrupt


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command line; return the process exit status."""
    import signal

    _SIGINTS.clear()
    try:
        previous = signal.signal(signal.SIGINT, _on_sigint)
    except ValueError:  # not the main thread (e.g. a test runner's worker)
        previous = None
    try:
        rc = _main(argv)
    except KeyboardInterrupt:  # in a command, or while the command modules are still being imported
        rc = 130
    except BaseException:
        if not _SIGINTS:
            raise
        rc = 130  # the interrupt surfaced as another exception (an import failing half-way)
    finally:
        if argv is None:  # the process's entry point: a Ctrl-C now, after the work, must not end it by the signal
            signal.signal(signal.SIGINT, signal.SIG_IGN)
        elif previous is not None:
            signal.signal(signal.SIGINT, previous)
    if _SIGINTS or rc == 130:
        print("microctl: interrupted", file=sys.stderr)
        if argv is None:
            _exit_now(130)
        return 130
    return rc


def _exit_now(status: int) -> None:
    """Flush and end the process with ``status`` at once.

    CPython remembers a KeyboardInterrupt that ended code run from C (a compiled module's
    start-up) even when it was caught, and then ends the process by SIGINT instead of with
    the status ``main`` returned; ``os._exit`` keeps the documented 130.
    """
    import os

    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):
            pass
    os._exit(status)


def _main(argv: Sequence[str] | None) -> int:
    parser = build_parser()
    if _SIGINTS:  # a Ctrl-C while the command modules loaded, swallowed by an import: stop here
        raise KeyboardInterrupt
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help(sys.stderr)
        return 2
    try:
        return int(args.func(args) or 0)
    except INPUT_ERRORS as exc:
        print(f"microctl: error: {_one_line(exc)}", file=sys.stderr)
        return 2
    except MicroctlError as exc:
        print(f"microctl: error: {_one_line(exc)}", file=sys.stderr)
        return 1
    except BrokenPipeError:  # output piped into e.g. `head`
        import os

        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0
    except OSError as exc:  # the machine, not the input: a full disk, an I/O error while writing results
        where = f"{exc.filename}: " if exc.filename else ""
        print(f"microctl: error: {where}{exc.strerror or exc}", file=sys.stderr)
        return 1
    except MemoryError:
        print("microctl: error: out of memory", file=sys.stderr)
        return 1


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
