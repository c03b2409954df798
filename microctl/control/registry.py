"""Named registries of objective classes: the setting string (YAML, CLI) names a registered class.

An objective family (the r_e summaries of eq. 4, :mod:`microctl.control.noise_summaries`; the
sequence objectives, :mod:`microctl.control.sequence_objectives`) keeps its classes in one
:class:`Registry`. Adding one is a new class with a ``name`` decorated with
``@REGISTRY.register``; the settings field made by :meth:`Registry.setting` accepts every name
registered at validation time.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable, Generic, TypeVar

from microctl.errors import ConfigError
from microctl.util.fields import Rule

__all__ = ["Registry"]

T = TypeVar("T", bound=type)


@dataclass(frozen=True)
class _LiveChoiceRule(Rule):
    """A choice :class:`~microctl.util.fields.Rule` whose choices are read when checked."""

    names: Callable[[], tuple[str, ...]] = field(default=tuple)

    def _now(self) -> Rule:
        return Rule(kind="choice", choices=self.names(), none_ok=self.none_ok)

    def describe(self) -> str:
        return self._now().describe()

    def check(self, value: Any) -> Any:
        return self._now().check(value)


class Registry(Generic[T]):
    """Classes registered by their ``name`` attribute, in registration order.

    Parameters
    ----------
    what : str
        What the classes are (for messages), e.g. ``"r_e summary"``.
    """

    def __init__(self, what: str):
        self.what = what
        self._classes: dict[str, T] = {}

    def register(self, cls: T) -> T:
        """Add ``cls`` under ``cls.name`` (a class decorator); ValueError if the name is taken."""
        name = getattr(cls, "name", None)
        if not isinstance(name, str) or not name:
            raise ValueError(f"a {self.what} class needs a non-empty string attribute 'name', {cls.__name__} has none")
        if name in self._classes:
            raise ValueError(f"{self.what} {name!r} is already registered ({self._classes[name].__name__})")
        self._classes[name] = cls
        return cls

    def unregister(self, name: str) -> None:
        """Remove the class registered as ``name`` (KeyError if none)."""
        del self._classes[name]

    def names(self) -> tuple[str, ...]:
        """The registered names, in registration order."""
        return tuple(self._classes)

    def __contains__(self, name: object) -> bool:
        return name in self._classes

    def __getitem__(self, name: str) -> T:
        try:
            return self._classes[name]
        except KeyError:
            raise ConfigError(f"unknown {self.what} {name!r}; registered: {', '.join(self._classes)}") from None

    def setting(self, default: str) -> Any:
        """A settings field (:func:`~microctl.util.fields.setting`) whose value must be a registered name."""
        if default not in self._classes:
            raise ValueError(f"default {self.what} {default!r} is not registered")
        return field(default=default, metadata={"rule": _LiveChoiceRule(kind="choice", names=self.names)})
