"""The configs shipped with the package, and the short names that reach them.

The repository's ``configs/stage/*.yaml`` and ``configs/experiments/*.yaml`` are installed with
the package (``microctl/configs``), so a command works from any folder, also after a plain
``pip install``:

* a path that exists is used as given;
* a short name (``sim_paper``, ``sim_paper.yaml``) names a packaged config of the kind the
  option expects (a stage config for ``--config``, an experiment for ``experiment``);
* a missing relative path that starts with ``configs/`` (as the README writes them) is read
  from the packaged copy, so the README's commands run verbatim outside the clone.
"""

from __future__ import annotations

from pathlib import Path

__all__ = ["PACKAGED_CONFIGS", "KINDS", "packaged_names", "resolve_config"]

#: Where the shipped configs are installed.
PACKAGED_CONFIGS = Path(__file__).resolve().parents[1] / "configs"

#: The folders of :data:`PACKAGED_CONFIGS`: what each kind of config is called in messages.
KINDS = {"stage": "stage config", "experiments": "experiment config"}


def packaged_names(kind: str) -> list[str]:
    """Short names of the packaged configs of one kind (``"stage"`` or ``"experiments"``)."""
    return sorted(p.stem for p in (PACKAGED_CONFIGS / kind).glob("*.yaml"))


def resolve_config(path: str | Path, kind: str) -> Path:
    """The file a config argument names (see the module docstring); unchanged if none fits.

    Parameters
    ----------
    path : str or Path
        What the user gave.
    kind : {"stage", "experiments"}
        Which packaged folder a short name refers to.

    Returns
    -------
    Path
        The path to read (the reader reports a missing file, naming :func:`packaged_names`).
    """
    given = Path(path)
    if given.exists() or given.is_absolute():
        return given
    text = str(path)
    if "/" not in text and "\\" not in text:
        name = text if text.endswith((".yaml", ".yml")) else f"{text}.yaml"
        candidate = PACKAGED_CONFIGS / kind / name
        return candidate if candidate.is_file() else given
    parts = given.parts
    if len(parts) >= 3 and parts[0] == "configs" and parts[1] in KINDS:
        candidate = PACKAGED_CONFIGS.joinpath(*parts[1:])
        if candidate.is_file():
            return candidate
    return given


def missing_hint(kind: str) -> str:
    """``; packaged stage configs: a, b (give one by name, e.g. --config a)`` for a not-found message."""
    names = packaged_names(kind)
    if not names:
        return ""
    return f"; the packaged {KINDS[kind]}s, usable by name from any folder: {', '.join(names)}"
