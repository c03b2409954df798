"""Output files that are never torn: write to a temporary name, fsync, rename; and writer locks.

Every file a command writes (model files, predictions, ``results.json``, ``report.md``,
figures, ``extended.yaml``, a log written over an existing one) goes through
:func:`atomic_write`: the content is written to a hidden temporary file in the same folder
(``.NAME.<random>.tmp``), flushed and fsynced, then renamed over ``NAME`` with
:func:`os.replace`, which is atomic on POSIX. A process killed at any instant therefore
leaves either the old file or the new one, never a torn or missing one (at worst a stray
temporary file beside it).

:func:`output_lock` serialises writers of one file (e.g. two ``collect -o same.csv``): it
takes an exclusive, non-blocking ``fcntl.flock`` on the hidden lock file ``.NAME.lock`` in the
same folder and refuses with :class:`OutputBusyError` when another process holds it.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from pathlib import Path
from typing import IO, Iterator

from microctl.errors import ConfigError

__all__ = ["atomic_write", "write_text_atomic", "write_bytes_atomic", "output_lock", "OutputBusyError", "save_figure",
           "fsync_dir"]


class OutputBusyError(ConfigError):
    """Another process is writing the same output file (a usage error: exit status 2)."""


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def fsync_dir(folder: str | Path) -> None:
    """Fsync a folder so a rename in it survives a power cut (best effort)."""
    try:
        fd = os.open(str(folder), os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


@contextlib.contextmanager
def atomic_write(path: str | Path, mode: str = "w", *, encoding: str | None = "utf-8") -> Iterator[IO]:
    """Open a temporary file beside ``path``; on success fsync it and rename it to ``path``.

    Parameters
    ----------
    path : path
        The file to (over)write.
    mode : {"w", "wb"}
        Text or binary.
    encoding : str, optional
        For text mode.

    Yields
    ------
    file object
        Write the whole content to it. If the block raises (or the process is interrupted),
        the temporary file is removed and ``path`` keeps its old content.
    """
    if mode not in ("w", "wb"):
        raise ValueError(f"mode must be 'w' or 'wb', got {mode!r}")
    path = Path(path)
    if path.is_char_device() or path.is_block_device():  # /dev/null, /dev/full: write, never replace
        with open(path, mode, encoding=None if "b" in mode else encoding) as fh:
            yield fh
        return
    folder = path.parent if str(path.parent) else Path(".")
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=folder)
    try:
        os.fchmod(fd, 0o666 & ~_umask())
        with os.fdopen(fd, mode, encoding=None if "b" in mode else encoding) as fh:
            yield fh
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise
    fsync_dir(folder)


def write_text_atomic(path: str | Path, text: str) -> None:
    """Write ``text`` to ``path`` atomically (:func:`atomic_write`)."""
    with atomic_write(path, "w") as fh:
        fh.write(text)


def write_bytes_atomic(path: str | Path, data: bytes) -> None:
    """Write ``data`` to ``path`` atomically (:func:`atomic_write`)."""
    with atomic_write(path, "wb") as fh:
        fh.write(data)


@contextlib.contextmanager
def output_lock(path: str | Path, flag: str = "-o") -> Iterator[Path]:
    """Hold an exclusive lock on writing ``path`` (``.NAME.lock`` beside it, ``fcntl.flock``).

    Parameters
    ----------
    path : path
        The output file.
    flag : str
        The option that named it, for the message.

    Raises
    ------
    OutputBusyError
        Another process holds the lock (it is writing the same file).
    """
    import fcntl

    path = Path(path)
    if path.is_char_device() or path.is_block_device():  # /dev/null: no lock file beside it in /dev
        yield path
        return
    folder = path.parent if str(path.parent) else Path(".")
    lock = folder / f".{path.name}.lock"
    try:
        fd = os.open(str(lock), os.O_RDWR | os.O_CREAT, 0o666)
    except OSError as exc:
        raise ConfigError(f"{flag} {path}: cannot create the lock file {lock}: {exc.strerror or exc}") from None
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise OutputBusyError(
                f"{flag} {path}: another microctl process is writing this file (lock {lock} is held); "
                "wait for it to finish or choose another file name") from None
        yield path
    finally:
        os.close(fd)


def save_figure(fig, path: str | Path, dpi: int) -> None:
    """``fig.savefig`` to ``path`` atomically (the format from the suffix, PNG by default)."""
    fmt = Path(path).suffix.lstrip(".") or "png"
    with atomic_write(path, "wb") as fh:
        fig.savefig(fh, format=fmt, dpi=dpi)
