"""Typed access to the fields of a parsed YAML document, with messages that name the file,
the field path (``stage.actuators[2].normal``) and what would be valid.

Shared by the stage config (:mod:`microctl.stage.config`) and the experiment config
(:mod:`microctl.experiments.config`); every method raises :class:`ConfigError`.

Settings dataclasses (controller, residual model) declare each field once with
:func:`setting` (default and :class:`Rule`); their ``__post_init__`` calls
:func:`validate_settings` and YAML sections are read with :func:`read_settings`, so a field's
default and its validation live in one place.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field, fields
from typing import Any, Iterable

import numpy as np

from microctl.errors import ConfigError

#: How far from 1 the length of a "unit" vector may be.
UNIT_TOLERANCE = 1e-6

#: Largest magnitude any number in a config file may have. No length, stiffness, time or
#: tolerance of a micromanipulator comes near it, and products of such numbers stay far
#: from overflowing a float (1e301 would overflow when squared).
MAX_MAGNITUDE = 1e9


class FieldReader:
    """Validating reader of one document.

    Parameters
    ----------
    source : str
        The file (or other name) used at the start of every message.
    """

    def __init__(self, source: str):
        self.source = source

    def fail(self, path: str, message: str) -> ConfigError:
        """The error for field ``path`` (to be raised by the caller)."""
        return ConfigError(f"{self.source}: {path}: {message}")

    def mapping(self, value: Any, path: str, allowed: Iterable[str], required: Iterable[str] = (), *,
                none_ok: bool = False) -> dict:
        """A mapping whose keys are all in ``allowed`` and include ``required``.

        ``none_ok``: an absent section (``None``) reads as an empty mapping.
        """
        allowed = list(allowed)
        if value is None and none_ok:
            value = {}
        if not isinstance(value, Mapping):
            raise self.fail(path, f"expected a mapping with keys {', '.join(allowed)}, got {type(value).__name__}")
        for key in value:
            if key not in allowed:
                raise self.fail(f"{path}.{key}" if path else str(key),
                                f"unknown key '{key}'; valid keys here: {', '.join(allowed)}")
        for key in required:
            if key not in value:
                raise self.fail(f"{path}.{key}" if path else str(key), "is required")
        return dict(value)

    def number(self, value: Any, path: str, *, positive: bool = False, nonneg: bool = False,
               lo: float | None = None, hi: float | None = None, max_abs: float = MAX_MAGNITUDE) -> float:
        """A finite number of magnitude at most ``max_abs`` (optionally > 0, >= 0, in [lo, hi])."""
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise self.fail(path, f"expected a number, got {value!r}")
        try:
            x = float(value)
        except OverflowError:  # an integer too large for a float
            raise self.fail(path, f"{value!r} is too large; the magnitude must be at most {max_abs:g}") from None
        if not math.isfinite(x):
            raise self.fail(path, f"expected a finite number, got {value!r}")
        if abs(x) > max_abs:
            raise self.fail(path, f"{value!r} is too large; the magnitude must be at most {max_abs:g}")
        if positive and x <= 0:
            raise self.fail(path, f"must be > 0, got {value!r}")
        if nonneg and x < 0:
            raise self.fail(path, f"must be >= 0, got {value!r}")
        if (lo is not None and x < lo) or (hi is not None and x > hi):
            rng = f">= {lo:g}" if hi is None else (f"<= {hi:g}" if lo is None else f"in [{lo:g}, {hi:g}]")
            raise self.fail(path, f"must be {rng}, got {value!r}")
        return x

    def integer(self, value: Any, path: str, *, lo: int | None = None, hi: int | None = None) -> int:
        """An integer (not a bool), optionally within [lo, hi]."""
        if isinstance(value, bool) or not isinstance(value, int):
            raise self.fail(path, f"expected an integer, got {value!r}")
        if (lo is not None and value < lo) or (hi is not None and value > hi):
            rng = f">= {lo}" if hi is None else (f"<= {hi}" if lo is None else f"in [{lo}, {hi}]")
            raise self.fail(path, f"must be an integer {rng}, got {value!r}")
        return int(value)

    def string(self, value: Any, path: str, *, blank_ok: bool = False) -> str:
        """A non-empty string (``blank_ok``: whitespace-only is fine, e.g. a line ending)."""
        if not isinstance(value, str) or value == "" or (not blank_ok and not value.strip()):
            raise self.fail(path, f"expected a non-empty string, got {value!r}")
        return value

    def ascii_text(self, value: Any, path: str, *, what: str, blank_ok: bool = False,
                   controls_ok: bool = False) -> str:
        """A non-empty string of ASCII characters (text sent to a device as ASCII bytes).

        ``controls_ok``: control characters (CR, LF, ...) are allowed, e.g. in a line ending;
        otherwise only printable ASCII (space to ``~``) is.
        """
        text = self.string(value, path, blank_ok=blank_ok)
        for i, ch in enumerate(text):
            code = ord(ch)
            if code > 126 or (code < 32 and not controls_ok) or code == 0:
                kind = "non-ASCII" if code > 127 else "control"
                raise self.fail(path, f"{text!r}: character {i + 1} ({ch!r}) is a {kind} character; {what} "
                                      "is sent to the device as ASCII, so use printable ASCII only")
        return text

    def boolean(self, value: Any, path: str) -> bool:
        """true or false."""
        if not isinstance(value, bool):
            raise self.fail(path, f"expected true or false, got {value!r}")
        return value

    def choice(self, value: Any, path: str, choices: Iterable[str]) -> str:
        """One of ``choices``."""
        choices = tuple(choices)
        if not isinstance(value, str) or value not in choices:
            raise self.fail(path, f"{value!r} is not one of {', '.join(choices)}")
        return value

    def vector(self, value: Any, path: str, n: int | None = None, *,
               max_abs: float = MAX_MAGNITUDE) -> tuple[float, ...]:
        """A list of ``n`` finite numbers of magnitude <= ``max_abs`` (any non-empty length when ``n`` is None)."""
        if not isinstance(value, (list, tuple)) or not value or (n is not None and len(value) != n):
            if n is None:
                raise self.fail(path, f"expected a non-empty list of numbers, got {value!r}")
            got = f"{len(value)} values" if isinstance(value, (list, tuple)) else repr(value)
            raise self.fail(path, f"expected a list of {n} numbers, got {got}")
        return tuple(self.number(v, f"{path}[{i}]", max_abs=max_abs) for i, v in enumerate(value))

    def unit_vector(self, value: Any, path: str) -> tuple[float, float, float]:
        """A 3-vector of length 1 (± :data:`UNIT_TOLERANCE`)."""
        v = self.vector(value, path, 3)
        norm = math.sqrt(sum(x * x for x in v))
        if norm == 0.0:
            raise self.fail(path, "is the zero vector; give a unit vector, e.g. [0, 0, 1]")
        if abs(norm - 1.0) > UNIT_TOLERANCE:
            raise self.fail(path, f"has length {norm:.6g}, must be a unit vector (length 1 ± {UNIT_TOLERANCE})")
        return v  # type: ignore[return-value]

    def interval(self, value: Any, path: str, *, max_abs: float = MAX_MAGNITUDE) -> tuple[float, float]:
        """[lo, hi] with lo < hi, both of magnitude <= ``max_abs``."""
        lo, hi = self.vector(value, path, 2, max_abs=max_abs)
        if lo >= hi:
            raise self.fail(path, f"lower bound {lo:g} must be below upper bound {hi:g}")
        return (lo, hi)


# --------------------------------------------------------------------------------------
# declarative settings: one rule per dataclass field, used by __post_init__ and the reader
# --------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Rule:
    """What a settings field accepts (kept in the dataclass field's metadata by :func:`setting`).

    Attributes
    ----------
    kind : str
        ``"bool"``, ``"int"``, ``"float"`` or ``"choice"`` (inferred from the default), or ``"names"``:
        a list of distinct names (non-empty strings without spaces), kept as a tuple; which names
        are valid is for the reader of the setting to check (they may depend on the stage).
    lo, hi : float or None
        Inclusive bounds (``lo_open``: lo excluded).
    choices : tuple of str
    none_ok : bool
        None is a valid value.
    """

    kind: str
    lo: float | None = None
    hi: float | None = None
    lo_open: bool = False
    choices: tuple[str, ...] = ()
    none_ok: bool = False

    def describe(self) -> str:
        """What is valid, as a phrase (for messages)."""
        if self.kind == "bool":
            text = "true or false"
        elif self.kind == "choice":
            text = f"one of {', '.join(self.choices)}"
        elif self.kind == "names":
            text = "a list of distinct names"
        else:
            noun = "an integer" if self.kind == "int" else "a number"
            if self.lo is None and self.hi is None:
                text = noun
            elif self.hi is None:
                text = f"{noun} {'>' if self.lo_open else '>='} {self.lo:g}"
            elif self.lo is None:
                text = f"{noun} <= {self.hi:g}"
            else:
                text = f"{noun} in {'(' if self.lo_open else '['}{self.lo:g}, {self.hi:g}]"
        return text + (" or null" if self.none_ok else "")

    def check(self, value: Any) -> Any:
        """The value converted to the field's type; ValueError (the reason) when invalid."""
        if value is None and self.none_ok:
            return None
        bad = ValueError(f"must be {self.describe()}, got {value!r}")
        if self.kind == "bool":
            if not isinstance(value, bool):
                raise bad
            return value
        if self.kind == "choice":
            if not isinstance(value, str) or value not in self.choices:
                raise bad
            return value
        if self.kind == "names":
            if (not isinstance(value, (list, tuple)) or len(set(value)) != len(value)
                    or not all(isinstance(v, str) and v and not any(c.isspace() for c in v) for v in value)):
                raise bad
            return tuple(value)
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise bad
        if self.kind == "int":
            if isinstance(value, float) and not value.is_integer():
                raise bad
            x: float = int(value)
        else:
            x = float(value)
            if not math.isfinite(x):
                raise bad
        if self.lo is not None and (x <= self.lo if self.lo_open else x < self.lo):
            raise bad
        if self.hi is not None and x > self.hi:
            raise bad
        return x


def check_moves(n: Any, minimum: int, name: str = "n", why: str = "") -> int:
    """``n`` as a number of moves of at least ``minimum`` (an int or NumPy integer, not a bool);
    ConfigError naming ``name`` (and ``why``, e.g. " (a model needs 5 to train on)") otherwise."""
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < minimum:
        raise ConfigError(f"{name}: expected a number of moves >= {minimum}{why}, got {n!r}")
    return int(n)


def setting(default: Any, *, lo: float | None = None, hi: float | None = None, lo_open: bool = False,
            choices: Iterable[str] = (), none_ok: bool = False, kind: str | None = None) -> Any:
    """A dataclass field with a validation :class:`Rule` (kind inferred from the default)."""
    if kind is None:
        kind = ("choice" if choices else "bool" if isinstance(default, bool) else "int" if isinstance(default, int)
                else "float")
    rule = Rule(kind=kind, lo=lo, hi=hi, lo_open=lo_open, choices=tuple(choices), none_ok=none_ok)
    return field(default=default, metadata={"rule": rule})


def _rules(cls: type) -> list[tuple[str, Rule]]:
    return [(f.name, f.metadata["rule"]) for f in fields(cls) if "rule" in f.metadata]


class SettingError(ConfigError):
    """A settings field breaks its rule: ``"<what> <field>: <reason>"``; ``field`` and ``reason``
    let a caller name the field its own way (a command-line option)."""

    def __init__(self, what: str, field_name: str, reason: str):
        super().__init__(f"{what} {field_name}: {reason}")
        self.field = field_name
        self.reason = reason


def validate_settings(obj: Any, what: str) -> None:
    """Check every :func:`setting` field of a dataclass instance (call from ``__post_init__``); a
    ``names`` field given as a list is stored as the tuple its rule returns.

    Raises
    ------
    SettingError
        ``"<what> <field>: must be ..., got ..."``.
    """
    for name, rule in _rules(type(obj)):
        try:
            value = rule.check(getattr(obj, name))
        except ValueError as exc:
            raise SettingError(what, name, str(exc)) from None
        if rule.kind == "names" and value is not None:  # a caller's list kept as the tuple it checked
            object.__setattr__(obj, name, value)


def read_settings(ck: FieldReader, raw: Any, path: str, cls: type, **fixed: Any) -> Any:
    """Build a settings dataclass from a YAML mapping: unknown keys rejected, every field checked
    against its rule with the file and field path in the message, absent fields at their default.

    ``fixed`` gives values the caller has read itself (their keys are allowed in the mapping
    and skipped here).
    """
    rules = dict(_rules(cls))
    sec = ck.mapping(raw, path, list(rules) + [k for k in fixed if k not in rules], none_ok=True)
    vals = dict(fixed)
    for name, value in sec.items():
        if name in fixed:
            continue
        try:
            vals[name] = rules[name].check(value)
        except ValueError as exc:
            raise ck.fail(f"{path}.{name}", str(exc)) from None
    try:
        return cls(**vals)
    except ConfigError as exc:  # a rule across fields (checked in __post_init__)
        raise ConfigError(f"{ck.source}: {path}: {exc}") from None


def same_setting(cls: type, name: str) -> Any:
    """A new field with the default and rule of ``cls``'s field ``name`` (one definition for both)."""
    f = next(f for f in fields(cls) if f.name == name)
    return field(default=f.default, metadata=f.metadata)
