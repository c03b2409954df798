"""The cause vocabulary (shared/spec/diagnosis.md): one class per physical cause, one registry.

A *cause* is a physical defect of the stage with a name, parameters (units, validity rule,
healthy value, the range a diagnosis searches) and a kind:

- ``static`` — a mean cause the AFM graph can apply (geometry, actuator gain, gauge transfer);
- ``dynamic`` — a mean cause that needs the state (backlash, hysteresis), the contact physics
  (contact loss) or time (drift): the AFM graph leaves it to the GP, the extended model applies it;
- ``noise`` — scatter (stick-slip friction), not a correction of the mean.

Each cause is a frozen dataclass whose fields are the config entry (``ActuatorGain(actuator=3,
gain=0.93)``) and whose :meth:`Cause.apply` says how it changes the stage physics
(:class:`StageParts`: contact points, tool point, gains, gaps, lags, friction, the gauge
:class:`~microctl.stage.sensor.Sensor`). Everything that knows about causes iterates
:data:`REGISTRY`:

- the config parser of ``backend.simulated.effects`` and ``stage.corrections``
  (:mod:`microctl.stage.config`) and its YAML form (``extended.yaml``);
- :class:`Effects`, a set of causes, whose fields are generated from the registry;
- the stage physics: :func:`stage_parts` applies each cause to the CAD numbers, used by the AFM
  (static kinds), the contact physics and therefore the simulated stage, its oracle and the
  extended model (all kinds);
- the diagnosis candidates (:mod:`microctl.diagnosis.causes`) and its noise causes;
- planting in tests and scripts (:meth:`Cause.draw`).

Adding a cause is one subclass decorated with :func:`register`, plus its tests.

The registry, :class:`Cause`, :class:`Param`, :class:`Nuisance` and :class:`StageParts` live in
:mod:`microctl.stage.cause_base`; this module holds the concrete causes, :class:`Effects` and
:func:`stage_parts`, and re-exports the rest (import from here).
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields, make_dataclass, replace
from typing import Any, ClassVar, Iterator, Sequence

import numpy as np

__all__ = [
    "REGISTRY",
    "KINDS",
    "Param",
    "Nuisance",
    "PRELOAD_COMPRESSION",
    "nuisances",
    "Cause",
    "register",
    "StageParts",
    "stage_parts",
    "Effects",
    "preload_compression_um",
    "ActuatorGain",
    "ContactOffset",
    "ToolOffset",
    "SensorScale",
    "SensorNonlinearity",
    "ContactLoss",
    "Backlash",
    "Hysteresis",
    "HYSTERESIS_RANGE_GRID_UM",
    "Drift",
    "ActuatorFriction",
    "MEAN_KINDS",
    "StageLike",
]

from microctl.stage.cause_base import (  # the registry and base classes (re-exported: this is the front)
    KINDS,
    MEAN_KINDS,
    PRELOAD_COMPRESSION,
    REGISTRY,
    Cause,
    Nuisance,
    Param,
    StageLike,
    StageParts,
    nuisances,
    preload_compression_um,
    register,
)


def _sign(rng: np.random.Generator) -> float:
    return 1.0 if rng.random() < 0.5 else -1.0


def _offset(rng: np.random.Generator) -> tuple[float, float]:
    r, ang = rng.uniform(0.5, 2.0), rng.uniform(0.0, 2.0 * np.pi)
    return float(r * np.cos(ang)), float(r * np.sin(ang))


_OFFSET_MM = 20.0  # offsets searched within ±20 mm (the contacts are 15 mm from the centre)


@register
@dataclass(frozen=True)
class ActuatorGain(Cause):
    """Actuator ``actuator`` moves ``gain`` × its command (planted: 1 ± U(0.03, 0.10))."""

    actuator: int
    gain: float

    name: ClassVar[str] = "actuator_gain"
    kind: ClassVar[str] = "static"
    per_actuator: ClassVar[bool] = True
    params: ClassVar[tuple[Param, ...]] = (Param("gain", "1", 1.0, "positive", 0.2, 5.0),)
    meaning: ClassVar[str] = "actuator i moves gain × its command"

    def apply(self, parts: StageParts) -> None:
        parts.gain[self.actuator - 1] = self.gain

    @classmethod
    def draw(cls, rng, actuator, *, compression_um):
        return cls(actuator, 1.0 + _sign(rng) * rng.uniform(0.03, 0.10))


@register
@dataclass(frozen=True)
class ContactOffset(Cause):
    """Ball ``actuator`` touches the platform (dx_mm, dy_mm) away from its CAD contact point
    (planted: |d| ∈ U(0.5, 2) mm at a random angle)."""

    actuator: int
    dx_mm: float
    dy_mm: float

    name: ClassVar[str] = "contact_offset"
    kind: ClassVar[str] = "static"
    per_actuator: ClassVar[bool] = True
    params: ClassVar[tuple[Param, ...]] = (
        Param("dx_mm", "mm", 0.0, None, -_OFFSET_MM, _OFFSET_MM),
        Param("dy_mm", "mm", 0.0, None, -_OFFSET_MM, _OFFSET_MM),
    )
    meaning: ClassVar[str] = "ball i touches the platform away from its CAD contact point"

    def apply(self, parts: StageParts) -> None:
        parts.contacts_mm[self.actuator - 1, :2] += (self.dx_mm, self.dy_mm)

    @classmethod
    def draw(cls, rng, actuator, *, compression_um):
        return cls(actuator, *_offset(rng))


@register
@dataclass(frozen=True)
class ToolOffset(Cause):
    """The measured point is (dx_mm, dy_mm) away from its CAD position t0 (planted as
    :class:`ContactOffset`)."""

    dx_mm: float
    dy_mm: float

    name: ClassVar[str] = "tool_offset"
    kind: ClassVar[str] = "static"
    params: ClassVar[tuple[Param, ...]] = ContactOffset.params
    meaning: ClassVar[str] = "the measured point is away from its CAD position t0"

    def apply(self, parts: StageParts) -> None:
        parts.tool_mm[:2] += (self.dx_mm, self.dy_mm)

    @classmethod
    def draw(cls, rng, actuator, *, compression_um):
        return cls(*_offset(rng))


@register
@dataclass(frozen=True)
class SensorScale(Cause):
    """The gauge reads ``scale`` × the true displacement (planted: 1 ± U(0.02, 0.06))."""

    scale: float

    name: ClassVar[str] = "sensor_scale"
    kind: ClassVar[str] = "static"
    params: ClassVar[tuple[Param, ...]] = (Param("scale", "1", 1.0, "positive", 0.2, 5.0),)
    meaning: ClassVar[str] = "the gauge reads scale × the true displacement"

    def apply(self, parts: StageParts) -> None:
        parts.sensor = replace(parts.sensor, scale=self.scale)

    @classmethod
    def draw(cls, rng, actuator, *, compression_um):
        return cls(1.0 + _sign(rng) * rng.uniform(0.02, 0.06))


@register
@dataclass(frozen=True)
class SensorNonlinearity(Cause):
    """The gauge adds ``quad_per_um`` × d² to a displacement d (planted: ±U(1e-3, 3e-3) /µm)."""

    quad_per_um: float

    name: ClassVar[str] = "sensor_nonlinearity"
    kind: ClassVar[str] = "static"
    params: ClassVar[tuple[Param, ...]] = (Param("quad_per_um", "1/µm", 0.0, None, -0.1, 0.1),)
    meaning: ClassVar[str] = "the gauge adds quad_per_um × d²"

    def apply(self, parts: StageParts) -> None:
        parts.sensor = replace(parts.sensor, quad_per_um=self.quad_per_um)

    @classmethod
    def draw(cls, rng, actuator, *, compression_um):
        return cls(_sign(rng) * rng.uniform(1e-3, 3e-3))


#: Starting gaps of a ``contact_loss`` fit, as offsets (µm) from the stage's preload compression
#: c: below c a lowered ball still carries load and the prediction hardly depends on the gap
#: (zero gradient), so a fit starts from the best of these gaps c + g instead of from 0.
GAP_GRID_OFFSETS_UM = (-3.0, -1.0, 0.0, 1.0, 2.0, 3.0, 5.0, 7.0, 10.0, 15.0, 21.0, 28.0)

#: Widest gap beyond the preload compression a ``contact_loss`` fit searches, µm.
GAP_SEARCH_UM = 35.0


@register
@dataclass(frozen=True)
class ContactLoss(Cause):
    """Ball ``actuator`` sits ``gap_um`` low (lost preload): it carries no load until the platform
    comes down onto it (planted: the stage's preload compression + U(2, 7) µm, so that the ball
    lifts off over part of the workspace)."""

    actuator: int
    gap_um: float

    name: ClassVar[str] = "contact_loss"
    kind: ClassVar[str] = "dynamic"
    per_actuator: ClassVar[bool] = True
    params: ClassVar[tuple[Param, ...]] = (Param("gap_um", "µm", 0.0, "nonneg", 0.0, np.inf),)
    meaning: ClassVar[str] = ("ball i sits gap_um low (lost preload): it carries no load until the platform "
                              "comes down onto it, and the platform rests on the other balls")
    # where the ball unloads depends on the gap *relative to* the preload compression, which a
    # stage preloaded differently from its config does not share: fitted with the gap
    nuisance: ClassVar[tuple[Nuisance, ...]] = (PRELOAD_COMPRESSION,)
    lifts_balls: ClassVar[bool] = True

    def apply(self, parts: StageParts) -> None:
        parts.gap_um[self.actuator - 1] = self.gap_um

    @classmethod
    def fit_bounds(cls, stage):
        return (0.0,), (PRELOAD_COMPRESSION.hi + GAP_SEARCH_UM,)

    @classmethod
    def start_grid(cls, stage):
        c0 = preload_compression_um(stage)
        return tuple((max(0.0, c + g), c) for c in (f * c0 for f in PRELOAD_COMPRESSION.factors)
                     for g in GAP_GRID_OFFSETS_UM)

    @classmethod
    def draw(cls, rng, actuator, *, compression_um):
        return cls(actuator, compression_um + rng.uniform(2.0, 7.0))


@register
@dataclass(frozen=True)
class Backlash(Cause):
    """Actuator ``actuator`` ends ``lag_um`` short of its command in the direction it last moved
    (planted: U(0.1, 0.4) µm)."""

    actuator: int
    lag_um: float

    name: ClassVar[str] = "backlash"
    kind: ClassVar[str] = "dynamic"
    per_actuator: ClassVar[bool] = True
    params: ClassVar[tuple[Param, ...]] = (Param("lag_um", "µm", 0.0, "nonneg", 0.0, 5.0),)
    meaning: ClassVar[str] = "actuator i ends lag_um short of its command in the direction it last moved"

    def apply(self, parts: StageParts) -> None:
        parts.lag_um[self.actuator - 1] = self.lag_um

    @classmethod
    def healthy(cls):
        # the fit starts just off the bound: at lag 0 the gradient of a one-sided fit is degenerate
        return (0.05,)

    @classmethod
    def draw(cls, rng, actuator, *, compression_um):
        return cls(actuator, rng.uniform(0.1, 0.4))


#: Largest play thresholds R (µm) a ``hysteresis`` fit starts from (the loop's width in command
#: travel is poorly identified from a start far from it: a fit tries each and keeps the best).
HYSTERESIS_RANGE_GRID_UM = (1.0, 3.0, 9.0)


@register
@dataclass(frozen=True)
class Hysteresis(Cause):
    """Rate-independent piezo hysteresis of actuator ``actuator``: a Prandtl-Ishlinskii sum of
    play operators (:mod:`microctl.stage.hysteresis`) whose major loop has half-width
    ``half_width_um`` and whose largest play threshold is ``range_um`` (planted: h ~ U(0.15, 0.4)
    µm, R ~ U(2, 8) µm).

    After a move longer than 2 R the actuator ends h short of its command in the direction it
    moved, as with ``backlash`` of lag h (the limit R -> 0); after a shorter reversal it is
    part-way round its loop, by an amount set by how far it went and by the moves before (the
    loop's memory), which ``backlash`` cannot express. This cause extends the vocabulary of
    ``shared/spec/diagnosis.md`` (documented in ``docs/diagnosis.md``).
    """

    actuator: int
    half_width_um: float
    range_um: float

    name: ClassVar[str] = "hysteresis"
    kind: ClassVar[str] = "dynamic"
    per_actuator: ClassVar[bool] = True
    params: ClassVar[tuple[Param, ...]] = (
        Param("half_width_um", "µm", 0.05, "nonneg", 0.0, 2.0),
        Param("range_um", "µm", 4.0, "positive", 0.5, 16.0),
    )
    meaning: ClassVar[str] = ("actuator i lags its command round a hysteresis loop of half-width half_width_um "
                              "that closes over range_um of reversal")

    def apply(self, parts: StageParts) -> None:
        parts.hysteresis_half_um[self.actuator - 1] = self.half_width_um
        parts.hysteresis_range_um[self.actuator - 1] = self.range_um

    @classmethod
    def start_grid(cls, stage):
        return tuple((0.2, R) for R in HYSTERESIS_RANGE_GRID_UM)

    @classmethod
    def draw(cls, rng, actuator, *, compression_um):
        return cls(actuator, rng.uniform(0.15, 0.4), rng.uniform(2.0, 8.0))


@register
@dataclass(frozen=True)
class Drift(Cause):
    """The reading creeps by ``rate_um_per_s`` per second (planted: ±U(3e-3, 8e-3) µm/s)."""

    rate_um_per_s: float

    name: ClassVar[str] = "drift"
    kind: ClassVar[str] = "dynamic"
    params: ClassVar[tuple[Param, ...]] = (Param("rate_um_per_s", "µm/s", 0.0, None, -1.0, 1.0),)
    meaning: ClassVar[str] = "the reading creeps linearly with time"
    needs: ClassVar[tuple[str, ...]] = ("time_s",)

    def apply(self, parts: StageParts) -> None:
        parts.sensor = replace(parts.sensor, drift_um_per_s=self.rate_um_per_s)

    @classmethod
    def draw(cls, rng, actuator, *, compression_um):
        return cls(_sign(rng) * rng.uniform(3e-3, 8e-3))


@register
@dataclass(frozen=True)
class ActuatorFriction(Cause):
    """Stick-slip at ball ``actuator``: scatter std = ``std_per_um`` × abs(Δq_i) (planted:
    U(0.02, 0.06) per µm)."""

    actuator: int
    std_per_um: float

    name: ClassVar[str] = "actuator_friction"
    kind: ClassVar[str] = "noise"
    per_actuator: ClassVar[bool] = True
    params: ClassVar[tuple[Param, ...]] = (Param("std_per_um", "1", 0.0, "nonneg", 0.0, np.inf),)
    meaning: ClassVar[str] = "stick-slip at ball i: scatter grows with how far actuator i moved"

    def apply(self, parts: StageParts) -> None:
        parts.friction_std_per_um[self.actuator - 1] = self.std_per_um

    @classmethod
    def draw(cls, rng, actuator, *, compression_um):
        return cls(actuator, rng.uniform(0.02, 0.06))


# ---- a set of causes ------------------------------------------------------------------------


def _effects_is_empty(self) -> bool:
    """Whether no cause is set."""
    return all(not getattr(self, f.name) for f in fields(self))


def _effects_items(self, kinds: Sequence[str] = KINDS) -> Iterator[Cause]:
    """Every cause entry set, in vocabulary order (optionally only some kinds)."""
    for name, cls in REGISTRY.items():
        if cls.kind not in kinds:
            continue
        v = getattr(self, name)
        if v is None:
            continue
        yield from (v if cls.per_actuator else (v,))


def _effects_to_dict(self) -> dict[str, Any]:
    """The YAML form (only the causes that are set)."""
    out: dict[str, Any] = {}
    for name, cls in REGISTRY.items():
        v = getattr(self, name)
        if not v:
            continue
        if cls.per_actuator:
            out[name] = [{f.name: getattr(c, f.name) for f in fields(c)} for c in v]
        else:
            out[name] = {f.name: getattr(v, f.name) for f in fields(v)}
    return out


def _effects_with(self, *causes: Cause):
    """A copy with ``causes`` added, each replacing the same cause (on the same actuator)."""
    kw = {f.name: getattr(self, f.name) for f in fields(self)}
    for c in causes:
        if c.per_actuator:
            kept = [e for e in kw[c.name] if e.actuator != c.actuator]
            kw[c.name] = tuple(sorted([*kept, c], key=lambda e: e.actuator))
        else:
            kw[c.name] = c
    return type(self)(**kw)


def _effects_from_items(cls, causes: Sequence[Cause]):
    """An Effects holding ``causes``."""
    return cls().with_(*causes)


Effects = make_dataclass(
    "Effects",
    [(name, tuple if c.per_actuator else Any, field(default=() if c.per_actuator else None))
     for name, c in REGISTRY.items()],
    frozen=True,
    namespace={
        "__doc__": (
            "A set of physical causes (simulator truth, model corrections), one field per cause of\n"
            "    :data:`REGISTRY` (generated from it): per-actuator causes are tuples sorted by actuator\n"
            "    (at most one entry each), the others the entry or None.\n"
        ),
        "__module__": __name__,
        "is_empty": _effects_is_empty,
        "items": _effects_items,
        "to_dict": _effects_to_dict,
        "with_": _effects_with,
        "of": classmethod(_effects_from_items),
    },
)


def stage_parts(stage: StageLike, effects: Any | None = None, kinds: Sequence[str] = KINDS) -> StageParts:
    """The physical numbers of ``stage`` with ``effects`` applied (each cause's :meth:`Cause.apply`).

    Parameters
    ----------
    stage : Stage
        CAD geometry.
    effects : Effects, optional
        Causes to apply (default none).
    kinds : sequence of str
        Apply only the causes of these kinds (the AFM applies ``static`` ones).

    Returns
    -------
    StageParts
    """
    n = len(stage.actuators)
    parts = StageParts(
        contacts_mm=np.array([a.contact_mm for a in stage.actuators], dtype=float).reshape(n, 3),
        tool_mm=np.array(stage.tool.point_mm, dtype=float),
        gain=np.ones(n),
        gap_um=np.zeros(n),
        lag_um=np.zeros(n),
        friction_std_per_um=np.zeros(n),
        hysteresis_half_um=np.zeros(n),
        hysteresis_range_um=np.zeros(n),
    )
    if effects is not None:
        for cause in effects.items(kinds):
            cause.apply(parts)
    return parts
