"""Helpers shared by the sub-command modules."""

from __future__ import annotations

import argparse
import os
import tempfile
from pathlib import Path
from typing import Iterable, Mapping

from microctl.errors import ConfigError


def add_quiet(parser: argparse.ArgumentParser) -> None:
    """Add ``--quiet`` (hide progress on stderr)."""
    parser.add_argument("--quiet", action="store_true", help="hide progress on stderr")


def int_at_least(minimum: int, rule: str, maximum: int | None = None):
    """An argparse type: an integer >= ``minimum`` (and <= ``maximum``); ``rule`` says what is valid."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"'{text}' is not an integer") from None
        if value < minimum:
            raise argparse.ArgumentTypeError(f"must be {rule}, got {value}")
        if maximum is not None and value > maximum:
            raise argparse.ArgumentTypeError(f"must be at most {maximum}, got {value}")
        return value

    return parse


#: Largest ``--seed`` (what every seeded setting accepts: a signed 64-bit integer).
MAX_SEED = 2**63 - 1

#: argparse type of ``--seed``: a non-negative integer (what NumPy's generators take), at most :data:`MAX_SEED`.
seed = int_at_least(0, "a non-negative integer", MAX_SEED)


def add_seed(parser: argparse.ArgumentParser, help_text: str) -> None:
    """Add ``--seed S`` (a non-negative integer, default 0)."""
    parser.add_argument("--seed", type=seed, default=0, metavar="S", help=help_text)


def target_range(text: str) -> tuple[float, float]:
    """argparse type of ``--target-range``: two numbers LO,HI (µm)."""
    parts = text.split(",")
    try:
        if len(parts) != 2:
            raise ValueError
        return float(parts[0]), float(parts[1])
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected LO,HI (two numbers in µm, e.g. 0,30), got '{text}'") from None


def _same_file(a: Path, b: Path) -> bool:
    try:
        if a.exists() and b.exists():
            return os.path.samefile(a, b)
    except OSError:
        pass
    return a.resolve() == b.resolve()


def _is_fifo_or_socket(path: Path) -> bool:
    import stat

    try:
        mode = path.stat().st_mode
    except OSError:
        return False
    return stat.S_ISFIFO(mode) or stat.S_ISSOCK(mode)


def check_output_file(path: str | Path, flag: str, inputs: Mapping[str, str | Path | None]) -> Path:
    """Refuse an output file that is an input, a directory or in a missing folder (ConfigError, exit 2).

    Parameters
    ----------
    path : path
        The file the command will write.
    flag : str
        The option that named it (``-o``), for the message.
    inputs : mapping
        What each input is called (``"the stage config --config"``) → its path (None: not given).
    """
    path = Path(path)
    for what, src in inputs.items():
        if src is not None and _same_file(path, Path(src)):
            raise ConfigError(f"{flag} {path}: is {what}; refusing to overwrite an input, choose another file name")
    if path.is_dir():
        raise ConfigError(f"{flag} {path}: is a directory, expected a file name to write")
    if _is_fifo_or_socket(path):
        raise ConfigError(f"{flag} {path}: is a FIFO or socket (writing would wait forever); give a file name")
    parent = path.parent if str(path.parent) else Path(".")
    if not parent.is_dir():
        raise ConfigError(f"{flag} {path}: the folder '{parent}' does not exist")
    return path


def check_output_dir(path: str | Path, flag: str, inputs: Mapping[str, str | Path | None],
                     writes: Iterable[str]) -> Path:
    """Create (if needed) and test an output folder before any work (ConfigError, exit 2).

    Refused: a path that is a file, a folder that cannot be created or written to, and a
    folder holding an input under a name the command writes (``writes``), which would be
    overwritten.
    """
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise ConfigError(f"{flag} {path}: is a file; give a folder (it is created if missing)")
    writes = set(writes)
    for what, src in inputs.items():
        if src is None:
            continue
        src = Path(src)
        if src.name in writes and _same_file(src.parent, path):
            raise ConfigError(f"{flag} {path}: the command writes {src.name} there, which is {what}; refusing to "
                              "overwrite an input, choose another folder")
    try:
        path.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryFile(dir=path):
            pass
    except OSError as exc:
        raise ConfigError(f"{flag} {path}: cannot write there: {exc.strerror or exc}") from None
    return path
