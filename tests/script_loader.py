"""Load a file of scripts/ as a module (the scripts are not a package), for the tests of their code."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def load_script(name: str, alias: str | None = None):
    """``scripts/<name>.py`` as a module registered as ``_script_<alias or name>``."""
    spec = importlib.util.spec_from_file_location(f"_script_{alias or name}", ROOT / "scripts" / f"{name}.py")
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod
    spec.loader.exec_module(mod)
    return mod
