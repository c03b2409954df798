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
from typing import TYPE_CHECKING, Any

from microctl.errors import INPUT_ERRORS, MicroctlError
from microctl.util.signals import RECEIVED

if TYPE_CHECKING:  # pragma: no cover
    import argparse
    from typing import Sequence


def _parser_class() -> type:
    """ArgumentParser whose usage errors are one line and exit status 2 (argparse imported here)."""
    import argparse

    class _Parser(argparse.ArgumentParser):
        def __init__(self, *args, **kwargs) -> None:
            super().__init__(*args, **kwargs)
            # "-3,0,0,0,0" and "-20,-10" are values (--state, --targets, --start-q), not options
            import re

            self._negative_number_matcher = re.compile(NEGATIVE_VALUES)

        def error(self, message: str) -> None:  # noqa: D401 - argparse API
            self.exit(2, f"{self.prog}: error: {_hint(self, message)}\n")

    return _Parser


#: What argparse takes for a negative number (a value, not an option): also comma-separated lists.
NEGATIVE_VALUES = r"^-(\d|\.\d)[\d.eE+\-,]*$"


def _hint(parser: argparse.ArgumentParser, message: str) -> str:
    """``message`` with "did you mean" for a mistyped option (``--moves`` → ``-n``)."""
    import difflib

    if not message.startswith("unrecognized arguments:"):
        return message
    options = sorted({s for a in parser._actions for s in a.option_strings} - {"-h", "--help", "--version"})
    aliases = {"--moves": "-n", "--n": "-n", "--output": "-o/--out", "--target-um": "--target", "--cfg": "--config"}
    hints = []
    for word in message.split(":", 1)[1].split():
        name = word.split("=", 1)[0]
        if not name.startswith("-"):
            continue
        guess = aliases.get(name) if aliases.get(name, "").split("/")[0] in options else None
        guess = guess or next(iter(difflib.get_close_matches(name, options, n=1, cutoff=0.6)), None)
        if guess:
            hints.append(f"did you mean {guess} instead of {name}?")
    return message + ("; " + " ".join(hints) if hints else "") + f" (see {parser.prog} --help)"


def _deepest_parser(parser: argparse.ArgumentParser, args: argparse.Namespace) -> argparse.ArgumentParser:
    """The parser of the (sub-)sub-command ``args`` chose."""
    while True:
        subs = [a for a in parser._actions if hasattr(a, "choices") and isinstance(a.choices, dict) and a.choices]
        name = getattr(args, subs[0].dest, None) if subs else None
        if not subs or name not in subs[0].choices:
            return parser
        parser = subs[0].choices[name]


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


def _on_sigint(signum, frame) -> None:  # noqa: ARG001 - signal handler API
    """Record the SIGINT in :data:`microctl.util.signals.RECEIVED`, then raise KeyboardInterrupt.

    The record outlives the exception: a Ctrl-C a library swallowed, or one that surfaced as
    another exception (e.g. ``ImportError: initialization failed`` from a compiled module being
    loaded), still ends the command with 130, and the moving commands stop before their next
    move (:func:`microctl.util.signals.raise_if_interrupted`).
    """
    RECEIVED.append(signum)
    raise KeyboardInterrupt


def _on_unraisable(unraisable) -> None:
    """A Ctrl-C that landed in a callback Python cannot raise from (a weakref's or a finaliser
    during garbage collection) is delivered again, so the command stops in its own code, instead
    of being printed as "Exception ignored" and lost."""
    if isinstance(unraisable.exc_value, KeyboardInterrupt):
        import signal
        import threading

        # to the main thread (a blocking call there, a sleep or a serial read, is interrupted too),
        # a moment later: a signal handled before this hook returns would land in it and be lost
        timer = threading.Timer(0.05, signal.pthread_kill, args=(threading.main_thread().ident, signal.SIGINT))
        timer.daemon = True
        timer.start()
        return
    sys.__unraisablehook__(unraisable)


#: The thread-count variables of the BLAS libraries NumPy and CasADi load; a user's value wins.
BLAS_THREAD_VARIABLES = ("OPENBLAS_NUM_THREADS", "GOTO_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")


def one_blas_thread(environ: dict, modules: Any) -> bool:
    """Start the process's BLAS with one thread, unless the user chose a count or NumPy is loaded.

    microctl runs its numerical work on one BLAS thread (:mod:`microctl.util.blas`: faster on
    the small matrices it uses); a pool started with more threads only spins idle, and that
    CPU is charged to the process (a one-shot ``solve``: about half of its CPU). Must run
    before NumPy is imported (the pool is sized when the library loads). Returns whether it set
    ``OPENBLAS_NUM_THREADS``.
    """
    if "numpy" in modules or any(v in environ for v in BLAS_THREAD_VARIABLES):
        return False
    environ["OPENBLAS_NUM_THREADS"] = "1"
    return True


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command line; return the process exit status."""
    import signal

    if argv is None:  # the process's entry point (a library caller keeps its own BLAS)
        import os

        one_blas_thread(os.environ, sys.modules)
    RECEIVED.clear()
    try:
        previous = signal.signal(signal.SIGINT, _on_sigint)
    except ValueError:  # not the main thread (e.g. a test runner's worker)
        previous = None
    hook, sys.unraisablehook = sys.unraisablehook, (_on_unraisable if previous is not None else sys.unraisablehook)
    try:
        rc = _main(argv)
    except KeyboardInterrupt:  # in a command, or while the command modules are still being imported
        rc = 130
    except BaseException:
        if not RECEIVED:
            raise
        rc = 130  # the interrupt surfaced as another exception (an import failing half-way)
    finally:
        sys.unraisablehook = hook
        if argv is None:  # the process's entry point: a Ctrl-C now, after the work, must not end it by the signal
            signal.signal(signal.SIGINT, signal.SIG_IGN)
        elif previous is not None:
            signal.signal(signal.SIGINT, previous)
    interrupted = bool(RECEIVED) or rc == 130
    RECEIVED.clear()  # a library call after this command in the same process starts with none
    if interrupted:
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
    parser = build_parser(argv, lazy=True)
    if RECEIVED:  # a Ctrl-C while the command modules loaded, swallowed by an import: stop here
        raise KeyboardInterrupt
    args, extras = parser.parse_known_args(argv)
    if extras:  # reported by the sub-command's parser, which knows the options to suggest
        _deepest_parser(parser, args).error(f"unrecognized arguments: {' '.join(extras)}")
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
