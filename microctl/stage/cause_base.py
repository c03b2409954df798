"""The cause vocabulary's registry and base classes (front: :mod:`microctl.stage.causes`).

:data:`REGISTRY` maps a cause name to its class; :func:`register` adds a :class:`Cause` subclass.
A cause has :class:`Param` parameters and may declare stage-physics :class:`Nuisance` values
fitted with it; :meth:`Cause.apply` changes the :class:`StageParts` (the physical numbers of the
stage). The concrete causes, :class:`~microctl.stage.causes.Effects` and
:func:`~microctl.stage.causes.stage_parts` are in :mod:`microctl.stage.causes`.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields, replace
from typing import Any, ClassVar, Iterable, Sequence

import numpy as np

from microctl.stage.sensor import Sensor

#: A :class:`microctl.stage.geometry.Stage`. Not imported: the geometry imports the causes (a
#: stage carries an :class:`~microctl.stage.causes.Effects`), and the causes read only its
#: actuators, tool and physics.
StageLike = Any

#: Kinds of cause, see the module docstring.
KINDS = ("static", "dynamic", "noise")

#: Mean kinds (corrections of the predicted reading).
MEAN_KINDS = ("static", "dynamic")


@dataclass(frozen=True)
class Param:
    """One parameter of a cause.

    Attributes
    ----------
    name : str
        Config and report name (units in the name where they apply: ``dx_mm``).
    unit : str
        Unit for reports and figure axes (``"1"`` for a ratio).
    healthy : float
        Value of a healthy stage (the start of a fit).
    rule : str or None
        Config validity: ``"positive"`` (> 0), ``"nonneg"`` (>= 0) or None (any finite number).
    fit_lo, fit_hi : float
        Range a diagnosis searches (physically plausible, wider than any planted value).
    """

    name: str
    unit: str
    healthy: float
    rule: str | None
    fit_lo: float
    fit_hi: float


@dataclass(frozen=True)
class Nuisance:
    """A number of the stage physics that a cause's prediction depends on and that the config
    may have wrong (fitted with the cause, reported, not a cause itself).

    Attributes
    ----------
    name : str
        Report name with unit (``preload_compression_um``).
    unit : str
    lo, hi : float
        Search range.
    factors : tuple of float
        Starting values of a grid search, as multiples of the config's value.
    """

    name: str
    unit: str
    lo: float
    hi: float
    factors: tuple[float, ...] = (1.0,)

    def value(self, stage: StageLike) -> float:
        """The config's value."""
        raise NotImplementedError

    def apply(self, stage: StageLike, value: float) -> StageLike:
        """``stage`` with this number set to ``value``."""
        raise NotImplementedError


@dataclass(frozen=True)
class _PreloadCompression(Nuisance):
    """Preload compression c = preload / contact stiffness: how far a lowered ball can sit before
    it unloads. A stage preloaded differently from its config has another c; its contact stiffness
    and flexure are kept (c changes the preload)."""

    def value(self, stage):
        return preload_compression_um(stage)

    def apply(self, stage, value):
        ph = stage.physics
        return replace(stage, physics=replace(ph, preload_n=float(value) * ph.contact_stiffness_n_per_um))


#: The preload compression as a nuisance of ``contact_loss``.
PRELOAD_COMPRESSION = _PreloadCompression("preload_compression_um", "µm", 0.5, 60.0, (0.5, 1.0, 2.0, 4.0))


#: name -> cause class, in vocabulary order (filled by :func:`register`).
REGISTRY: dict[str, type["Cause"]] = {}


def register(cls: type["Cause"]) -> type["Cause"]:
    """Class decorator: add a cause to :data:`REGISTRY` (checks its declaration)."""
    if cls.kind not in KINDS:
        raise TypeError(f"{cls.__name__}.kind must be one of {KINDS}, got {cls.kind!r}")
    names = [f.name for f in fields(cls)]
    want = (["actuator"] if cls.per_actuator else []) + [p.name for p in cls.params]
    if names != want:
        raise TypeError(f"{cls.__name__}: fields {names} must be {want} (actuator first if per-actuator)")
    if cls.name in REGISTRY:
        raise TypeError(f"cause {cls.name!r} registered twice")
    REGISTRY[cls.name] = cls
    return cls


@dataclass
class StageParts:
    """The physical numbers of a stage that causes change (built by :func:`stage_parts`).

    Attributes
    ----------
    contacts_mm : ndarray, shape (n_q, 3)
        Contact point c_i of each ball on the platform (eq. 6).
    tool_mm : ndarray, shape (3,)
        Tool point t0 (eq. 13).
    gain : ndarray, shape (n_q,)
        Ball motion per µm of command along the actuator direction (1 when healthy).
    gap_um : ndarray, shape (n_q,)
        How far each ball sits low (lost preload), µm.
    lag_um : ndarray, shape (n_q,)
        Backlash: how far each actuator ends short of its command in its last direction, µm.
    friction_std_per_um : ndarray, shape (n_q,)
        Stick-slip scatter per µm an actuator moves.
    hysteresis_half_um : ndarray, shape (n_q,)
        Half-width h_i of each actuator's major hysteresis loop, µm (0 without hysteresis).
    hysteresis_range_um : ndarray, shape (n_q,)
        Largest play threshold R_i of each actuator's hysteresis, µm
        (:mod:`microctl.stage.hysteresis`).
    sensor : Sensor
        The gauge transfer (scale, quadratic term, drift).
    """

    contacts_mm: np.ndarray
    tool_mm: np.ndarray
    gain: np.ndarray
    gap_um: np.ndarray
    lag_um: np.ndarray
    friction_std_per_um: np.ndarray
    hysteresis_half_um: np.ndarray
    hysteresis_range_um: np.ndarray
    sensor: Sensor = field(default_factory=Sensor)


@dataclass(frozen=True)
class Cause:
    """Base class of a cause (subclasses are frozen dataclasses: the config entry).

    Class attributes
    ----------------
    name : str
        Vocabulary name (report.json, config key).
    kind : str
        One of :data:`KINDS`.
    per_actuator : bool
        Whether the cause belongs to one actuator (first field ``actuator``, 1-based).
    params : tuple of Param
        The other fields, in order.
    meaning : str
        Physical meaning (the spec's table).
    needs : tuple of str
        Data a diagnosis needs to see the cause (``"time_s"`` for drift).
    nuisance : tuple of Nuisance
        Stage-physics numbers fitted with the cause (its prediction depends on them strongly
        and the config may have them wrong).
    lifts_balls : bool
        Whether the cause may lift a ball off (``contact_loss``). The spec defines every other
        cause on a well-preloaded stage where no ball lifts off, so a fit of other causes whose
        prediction lifts a ball is not that cause (a diagnosis discards it).
    """

    name: ClassVar[str] = ""
    kind: ClassVar[str] = "static"
    per_actuator: ClassVar[bool] = False
    params: ClassVar[tuple[Param, ...]] = ()
    meaning: ClassVar[str] = ""
    needs: ClassVar[tuple[str, ...]] = ()
    nuisance: ClassVar[tuple[Nuisance, ...]] = ()
    lifts_balls: ClassVar[bool] = False

    # ---- values ------------------------------------------------------------------------
    @classmethod
    def make(cls, actuator: int | None, theta: Sequence[float]) -> "Cause":
        """The entry for parameters ``theta`` (in :attr:`params` order) on ``actuator``."""
        vals = [float(x) for x in theta]
        return cls(actuator, *vals) if cls.per_actuator else cls(*vals)  # type: ignore[call-arg]

    def theta(self) -> tuple[float, ...]:
        """The parameter values in :attr:`params` order."""
        return tuple(float(getattr(self, p.name)) for p in self.params)

    @property
    def key(self) -> str:
        """``name`` or ``name[actuator]``."""
        return f"{self.name}[{self.actuator}]" if self.per_actuator else self.name  # type: ignore[attr-defined]

    def report_params(self) -> dict[str, Any]:
        """Report form ``{"actuator": i, param: value, ...}``."""
        out: dict[str, Any] = {"actuator": int(self.actuator)} if self.per_actuator else {}  # type: ignore[attr-defined]
        out.update({p.name: float(getattr(self, p.name)) for p in self.params})
        return out

    # ---- physics -------------------------------------------------------------------------
    def apply(self, parts: StageParts) -> None:
        """Change the stage physics ``parts`` in place (the cause's physical meaning)."""
        raise NotImplementedError

    # ---- diagnosis -----------------------------------------------------------------------
    @classmethod
    def fit_bounds(cls, stage: StageLike) -> tuple[tuple[float, ...], tuple[float, ...]]:
        """Search range of the parameters for ``stage`` (lower, upper)."""
        return tuple(p.fit_lo for p in cls.params), tuple(p.fit_hi for p in cls.params)

    @classmethod
    def healthy(cls) -> tuple[float, ...]:
        """Parameters of a healthy stage (the start of a fit)."""
        return tuple(p.healthy for p in cls.params)

    @classmethod
    def start_grid(cls, stage: StageLike) -> tuple[tuple[float, ...], ...]:
        """Starting points a fit tries when not warm-started (the best one is used): parameters
        followed by the :attr:`nuisance` values."""
        return (cls.healthy() + tuple(n.value(stage) for n in cls.nuisance),)

    # ---- planting ------------------------------------------------------------------------
    @classmethod
    def draw(cls, rng: np.random.Generator, actuator: int | None, *, compression_um: float) -> "Cause":
        """A realistic planted value (tests, scripts): see each cause's docstring for the range.

        Parameters
        ----------
        rng : numpy Generator
        actuator : int or None
            1-based actuator for a per-actuator cause.
        compression_um : float
            Total contact compression the planted stage's preload makes up
            (:func:`preload_compression_um`), for causes sized relative to it.
        """
        raise NotImplementedError


def preload_compression_um(stage: StageLike) -> float:
    """Total contact compression the preload makes up, µm (preload / contact stiffness).

    With the default physics (100 N, 20 N/µm) 5 µm; each of four balls carries a quarter.
    A ball lowered by less than about this still carries load; lowered by more it lifts off
    over part of the workspace (``contact_loss``).
    """
    return stage.physics.preload_n / stage.physics.contact_stiffness_n_per_um


def nuisances(causes: Iterable[Any] | None = None) -> tuple[Nuisance, ...]:
    """Every nuisance the ``causes`` (anything with a ``nuisance`` tuple: cause classes, fit
    specs; default every registered cause) declare, each once, in order."""
    out: list[Nuisance] = []
    for c in REGISTRY.values() if causes is None else causes:
        out += [n for n in c.nuisance if n not in out]
    return tuple(out)
