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


def _command_word(argv: Sequence[str] | None) -> str | None:
    """The sub-command named on the command line (the first word that is not an option), or None."""
    args = sys.argv[1:] if argv is None else list(argv)
    for a in args:
        if a == "--":
            return None
        if not a.startswith("-"):
            return a
    return None


def _command_modules() -> list[str]:
    """Names of the command modules (``cli/commands/*.py`` not starting with ``_``), found without importing them."""
    import pkgutil

    import microctl.cli.commands as commands_pkg

    return sorted(m.name for m in pkgutil.iter_modules(commands_pkg.__path__) if not m.name.startswith("_"))


def build_parser(argv: Sequence[str] | None = None, *, lazy: bool = False) -> argparse.ArgumentParser:
    """Build the top-level parser with the discovered sub-commands.

    Parameters
    ----------
    argv : sequence of str, optional
        The command line (default ``sys.argv[1:]``); only used when ``lazy``.
    lazy : bool
        Import only what this command line needs: the one command module it names (a module is
        named like its command), none for a bare ``--version``, all of them otherwise (help,
        an unknown command: argparse lists them all). A command module imports NumPy,
        CasADi and the model code, so importing all of them costs most of a second.
    """
    from microctl._version import __version__

    _Parser = _parser_class()
    parser = _Parser(
        prog="microctl",
        description="Accurate, repeatable position control of piezo micromanipulators (EAFM).",
    )
    parser.add_argument("--version", action="version", version=f"microctl {__version__}")
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)
    import importlib

    names = _command_modules()
    if lazy:
        word = _command_word(argv)
        args = sys.argv[1:] if argv is None else list(argv)
        if word in names:
            names = [word]
        elif word is None and "--version" in args and not {"-h", "--help"} & set(args):
            names = []
    for name in names:
        module = importlib.import_module(f"microctl.cli.commands.{name}")
        module.register(subparsers)
    return parser


def _one_line(exc: BaseException) -> str:
    """The message on one line: line breaks that came with a quoted value are shown escaped."""
    return str(exc).replace("\r", "\\r").replace("\n", "\\n")


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command line; return the process exit status."""
    try:
        return _main(argv)
    except KeyboardInterrupt:  # in a command, or while the command modules are still being imported
        print("microctl: interrupted", file=sys.stderr)
        return 130


def _main(argv: Sequence[str] | None) -> int:
    parser = build_parser(argv, lazy=True)
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
