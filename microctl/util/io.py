"""Plain-data I/O shared by the library and the command line: JSON of NumPy results.

Results (``results.json``, ``report.json``, ``solve --json``) are built from NumPy arrays and
scalars; :func:`to_jsonable` turns them into plain JSON types (non-finite floats become
``null``), :func:`write_json` writes a file atomically and :func:`print_json` prints on
stdout. The library (``microctl.experiments``, ``microctl.diagnosis``) and the command
modules (``microctl.cli.commands``) all use these, so the library never imports the CLI package.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["to_jsonable", "print_json", "write_json"]


def to_jsonable(obj: Any) -> Any:
    """Convert NumPy scalars/arrays (recursively) into plain JSON types.

    Parameters
    ----------
    obj : any
        Dicts (keys become ``str``), lists, tuples, NumPy arrays and scalars, plain values.

    Returns
    -------
    any
        The same structure with lists, Python scalars and ``None`` for non-finite floats.
    """
    if isinstance(obj, dict):
        return {str(k): to_jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [to_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return to_jsonable(obj.tolist())
    if isinstance(obj, np.generic):
        return to_jsonable(obj.item())
    if isinstance(obj, float) and not np.isfinite(obj):
        return None
    return obj


def print_json(obj: Any) -> None:
    """Print ``obj`` as indented JSON on stdout (through :func:`to_jsonable`)."""
    json.dump(to_jsonable(obj), sys.stdout, indent=2)
    sys.stdout.write("\n")


def write_json(path: str | Path, obj: Any) -> None:
    """Write ``obj`` as indented JSON to ``path`` (atomically: temp file then rename).

    Parameters
    ----------
    path : path
        The file to write; a hidden temporary file beside it is used on the way
        (:func:`microctl.util.atomic.atomic_write`).
    obj : any
        Converted with :func:`to_jsonable`.

    Raises
    ------
    OSError
        The machine failed (a full disk): the temp file is removed and ``path`` is left as it
        was (the command line reports it in one line, exit status 1).
    """
    from microctl.util.atomic import write_text_atomic

    write_text_atomic(path, json.dumps(to_jsonable(obj), indent=2) + "\n")
