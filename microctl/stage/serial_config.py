"""The serial hardware section of a stage config (``backend.serial``; shared/spec/serial-protocol.md).

The drivers (PI GCS 2 subset), which (driver, axis) moves each actuator, and the gauge's line
protocol: frozen dataclasses and their YAML reader (used by :mod:`microctl.stage.config`).
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Any

from microctl.stage.geometry import Stage
from microctl.util.fields import FieldReader

#: Longest port timeout, on-target timeout or poll interval accepted, s (pyserial cannot wait
#: much longer than this on every platform, and a device slower than an hour is broken).
MAX_WAIT_S = 3600.0

#: Fastest baud rate accepted (real serial adapters stop well below it).
MAX_BAUDRATE = 100_000_000


@dataclass(frozen=True)
class SerialController:
    """One PZT servo driver (PI GCS 2 subset)."""

    name: str
    url: str
    baudrate: int = 115200
    timeout_s: float = 1.0


@dataclass(frozen=True)
class AxisMap:
    """Where an actuator is driven: (controller name, axis id)."""

    controller: str
    axis: str


@dataclass(frozen=True)
class Gauge:
    """The displacement gauge's line protocol."""

    url: str
    baudrate: int = 115200
    timeout_s: float = 1.0
    query: str = "MEAS?"
    eol: str = "\r\n"
    reply_pattern: str = r"^\s*\+?(-?\d+(?:\.\d*)?(?:[eE][-+]?\d+)?)\s*$"
    samples: int = 1
    zero_at_start: bool = False
    tare_samples: int = 20


@dataclass(frozen=True)
class SerialBackend:
    """Serial hardware (``backend.serial``; shared/spec/serial-protocol.md)."""

    controllers: tuple[SerialController, ...]
    axes: tuple[tuple[str, AxisMap], ...]
    gauge: Gauge
    on_target_timeout_s: float = 5.0
    poll_interval_s: float = 0.005
    retries: int = 2

    def axis_of(self, actuator: str) -> AxisMap:
        """The (controller, axis) an actuator is driven by."""
        return dict(self.axes)[actuator]


def parse_serial(ctx: FieldReader, raw: Any, stage: Stage) -> SerialBackend:
    """The ``backend.serial`` section (validated against the stage's actuators)."""
    p = "backend.serial"
    raw = ctx.mapping(
        raw,
        p,
        ["controllers", "axes", "gauge", "on_target_timeout_s", "poll_interval_s", "retries"],
        required=["controllers", "axes", "gauge"],
    )
    controllers = _parse_controllers(ctx, raw["controllers"], p)
    axes = _parse_axes(ctx, raw["axes"], p, stage, [c.name for c in controllers])
    gauge = _parse_gauge(ctx, raw["gauge"], p, stage)
    on_target_timeout_s = ctx.number(raw.get("on_target_timeout_s", 5.0), f"{p}.on_target_timeout_s",
                                     positive=True, hi=MAX_WAIT_S)
    poll_interval_s = ctx.number(raw.get("poll_interval_s", 0.005), f"{p}.poll_interval_s", positive=True,
                                 hi=on_target_timeout_s)
    return SerialBackend(
        controllers=tuple(controllers),
        axes=tuple(axes),
        gauge=gauge,
        on_target_timeout_s=on_target_timeout_s,
        poll_interval_s=poll_interval_s,
        retries=ctx.integer(raw.get("retries", 2), f"{p}.retries", lo=0, hi=100),
    )


def _parse_controllers(ctx: FieldReader, raw: Any, p: str) -> list[SerialController]:
    """``backend.serial.controllers``: the drivers, names unique."""
    if not isinstance(raw, list) or not raw:
        raise ctx.fail(f"{p}.controllers", "expected a non-empty list of drivers")
    controllers = []
    for i, c in enumerate(raw):
        cp = f"{p}.controllers[{i}]"
        c = ctx.mapping(c, cp, ["name", "url", "baudrate", "timeout_s"], ["name", "url"])
        ctrl = SerialController(
            name=ctx.string(c["name"], f"{cp}.name"),
            url=ctx.string(c["url"], f"{cp}.url"),
            baudrate=ctx.integer(c.get("baudrate", 115200), f"{cp}.baudrate", lo=1, hi=MAX_BAUDRATE),
            timeout_s=ctx.number(c.get("timeout_s", 1.0), f"{cp}.timeout_s", positive=True, hi=MAX_WAIT_S),
        )
        if any(ctrl.name == o.name for o in controllers):
            raise ctx.fail(f"{cp}.name", f"controller name '{ctrl.name}' is used twice")
        controllers.append(ctrl)
    return controllers


def _parse_axes(ctx: FieldReader, raw: Any, p: str, stage: Stage, names: list[str]) -> list[tuple[str, AxisMap]]:
    """``backend.serial.axes``: (controller, axis) of every actuator, no axis mapped twice."""
    axes_raw = ctx.mapping(raw, f"{p}.axes", stage.actuator_names, required=stage.actuator_names)
    axes = []
    used = set()
    for act in stage.actuator_names:
        ap = f"{p}.axes.{act}"
        m = ctx.mapping(axes_raw[act], ap, ["controller", "axis"], ["controller", "axis"])
        ctrl = ctx.string(m["controller"], f"{ap}.controller")
        if ctrl not in names:
            raise ctx.fail(f"{ap}.controller", f"'{ctrl}' is not a configured controller; valid: {', '.join(names)}")
        if isinstance(m["axis"], bool) or not isinstance(m["axis"], (str, int)):
            raise ctx.fail(f"{ap}.axis", f"expected an axis id such as '1' or 'A', got {m['axis']!r}")
        axis = str(m["axis"]).strip()
        if not axis or any(ch.isspace() for ch in axis):
            raise ctx.fail(f"{ap}.axis", f"{m['axis']!r} is not a valid axis id (no spaces)")
        ctx.ascii_text(axis, f"{ap}.axis", what="an axis id")
        if "=" in axis:
            raise ctx.fail(f"{ap}.axis", f"'{axis}' is not a valid axis id ('=' separates axis and value in replies)")
        if (ctrl, axis) in used:
            raise ctx.fail(f"{ap}.axis", f"axis {axis} of {ctrl} is mapped to two actuators")
        used.add((ctrl, axis))
        axes.append((act, AxisMap(controller=ctrl, axis=axis)))
    return axes


def _parse_gauge(ctx: FieldReader, raw: Any, p: str, stage: Stage) -> Gauge:
    """``backend.serial.gauge``: the gauge's line protocol (and whether the zero state can be tared)."""
    gp = f"{p}.gauge"
    g = ctx.mapping(
        raw, gp,
        ["url", "baudrate", "timeout_s", "query", "eol", "reply_pattern", "samples", "zero_at_start", "tare_samples"],
        ["url"],
    )
    gd = Gauge(url="")
    pattern = g.get("reply_pattern", gd.reply_pattern)
    try:
        compiled = re.compile(pattern)
    except (re.error, TypeError) as exc:
        raise ctx.fail(f"{gp}.reply_pattern", f"is not a valid regular expression: {exc}") from None
    if compiled.groups != 1:
        raise ctx.fail(f"{gp}.reply_pattern", f"must have exactly one capture group (the number), it has "
                       f"{compiled.groups}; e.g. {gd.reply_pattern!r}")
    query = ctx.ascii_text(g.get("query", gd.query), f"{gp}.query", what="the gauge query")
    eol = ctx.ascii_text(g.get("eol", gd.eol), f"{gp}.eol", what="the line ending", blank_ok=True, controls_ok=True)
    if not eol.endswith(("\n", "\r")):
        raise ctx.fail(f"{gp}.eol", f"{eol!r} must end with a line feed or carriage return, e.g. \"\\r\\n\"")
    gauge = Gauge(
        url=ctx.string(g["url"], f"{gp}.url"),
        baudrate=ctx.integer(g.get("baudrate", gd.baudrate), f"{gp}.baudrate", lo=1, hi=MAX_BAUDRATE),
        timeout_s=ctx.number(g.get("timeout_s", gd.timeout_s), f"{gp}.timeout_s", positive=True, hi=MAX_WAIT_S),
        query=query,
        eol=eol,
        reply_pattern=pattern,
        samples=ctx.integer(g.get("samples", gd.samples), f"{gp}.samples", lo=1, hi=10000),
        zero_at_start=ctx.boolean(g.get("zero_at_start", gd.zero_at_start), f"{gp}.zero_at_start"),
        tare_samples=ctx.integer(g.get("tare_samples", gd.tare_samples), f"{gp}.tare_samples", lo=1, hi=10000),
    )
    if gauge.zero_at_start:
        for i, a in enumerate(stage.actuators):
            if not a.range_um[0] <= 0.0 <= a.range_um[1]:
                raise ctx.fail(
                    f"{gp}.zero_at_start",
                    f"tares the gauge at the zero state q = 0, but actuator {a.name} (stage.actuators[{i}]) has "
                    f"range_um {list(a.range_um)}, which excludes 0; set zero_at_start: false or widen the range",
                )
    return gauge
