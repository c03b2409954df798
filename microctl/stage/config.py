"""Stage configuration: YAML → frozen dataclasses, validated at load.

A stage file has two top-level sections::

    stage:     # the geometry the analytic forward model (AFM) is built from (paper Table I)
    backend:   # which stage the commands drive: the simulated one or serial hardware

Every problem is a :class:`~microctl.errors.ConfigError` whose message names the file
and the field path (``stage.actuators[2].normal``) and says what would be valid; unknown
keys are rejected at every level. See ``docs/config.md`` for the full reference.

Units: lengths of the platform motion and actuators in µm, rotations in mrad, geometry
(contact points, tool point) in mm, so that mrad × mm = µm.
"""

from __future__ import annotations

import re
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Any, Mapping

import numpy as np
import yaml

from microctl.errors import ConfigError
from microctl.stage.causes import REGISTRY, Effects
from microctl.stage.geometry import TWIST_COMPONENTS, Actuator, Physics, Stage, Tool
from microctl.stage.kinematics import contact_map, inverse_kinematics_matrix
from microctl.stage.serial_config import (  # noqa: F401  (the serial section's settings, re-exported)
    MAX_BAUDRATE,
    MAX_WAIT_S,
    AxisMap,
    Gauge,
    SerialBackend,
    SerialController,
    parse_serial,
)
from microctl.util.fields import FieldReader
from microctl.util.packaged import missing_hint, resolve_config

#: Largest condition number accepted for the contact map H R^T J (eq. 10) and the
#: inverse-kinematics matrix K; beyond it the pose is not determined by the actuators.
MAX_CONDITION = 1e6

#: Smallest |n_i · d_i| accepted: a ball pushed more than ~84° away from its contact
#: normal needs ten times its stroke to move the platform (ill-conditioned eq. 10).
MIN_TRANSMISSION = 0.1

#: Largest magnitude of an actuator's ``range_um`` or ``limit_um``, µm. A piezo stroke is tens
#: to hundreds of µm; a bound beyond 10 mm is a unit mistake (nm typed as µm), not a stage.
MAX_STROKE_UM = 1e4

# --------------------------------------------------------------------------------------
# backend dataclasses (the stage geometry: microctl.stage.geometry)
# --------------------------------------------------------------------------------------


@dataclass(frozen=True)
class SimulatedBackend:
    """The simulated stage (``backend.simulated``).

    Attributes
    ----------
    seed : int
        Seed of every random draw; the same config and seed give the same data.
    gauge_noise_std_um : float
        Standard deviation of the gauge reading noise, µm.
    driver_accuracy_um : float
        Standard deviation of each driver's positioning error, µm (paper: 0.01 µm).
    move_time_s : float
        Simulated time a move takes to settle (drift accumulates with it), s.
    effects : Effects
        The physical defects the simulated stage has (the truth a diagnosis must find).
    """

    seed: int = 0
    gauge_noise_std_um: float = 0.05
    driver_accuracy_um: float = 0.01
    move_time_s: float = 1.0
    effects: Effects = field(default_factory=Effects)


#: The backend kinds a stage config can name (each has its class in
#: :data:`microctl.backends.base.BACKENDS`).
BACKEND_KINDS = ("simulated", "serial")


@dataclass(frozen=True)
class Backend:
    """Which stage the commands drive.

    Attributes
    ----------
    kind : str
        ``"simulated"`` or ``"serial"``.
    simulated : SimulatedBackend
        Simulator settings (also what ``microctl emulate`` serves).
    serial : SerialBackend or None
        Hardware settings; required when ``kind == "serial"``.
    """

    kind: str = "simulated"
    simulated: SimulatedBackend = field(default_factory=SimulatedBackend)
    serial: SerialBackend | None = None


@dataclass(frozen=True)
class StageConfig:
    """A whole stage file: the model and the backend.

    Attributes
    ----------
    stage : Stage
    backend : Backend
    source : str
        The file it was read from (for messages).
    """

    stage: Stage
    backend: Backend = field(default_factory=Backend)
    source: str = "<memory>"

    def to_dict(self) -> dict[str, Any]:
        """The YAML form of the whole file."""
        b = self.backend
        backend: dict[str, Any] = {"kind": b.kind}
        sim = b.simulated
        backend["simulated"] = {
            "seed": sim.seed,
            "gauge_noise_std_um": sim.gauge_noise_std_um,
            "driver_accuracy_um": sim.driver_accuracy_um,
            "move_time_s": sim.move_time_s,
        }
        if not sim.effects.is_empty():
            backend["simulated"]["effects"] = sim.effects.to_dict()
        if b.serial is not None:
            s = b.serial
            backend["serial"] = {
                "controllers": [asdict(c) for c in s.controllers],
                "axes": {name: asdict(m) for name, m in s.axes},
                "gauge": asdict(s.gauge),
                "on_target_timeout_s": s.on_target_timeout_s,
                "poll_interval_s": s.poll_interval_s,
                "retries": s.retries,
            }
        return {"stage": self.stage.to_dict(), "backend": backend}

    def dump_yaml(self) -> str:
        """YAML text that :func:`load_stage_config` reads back to an equal config."""
        return yaml.safe_dump(self.to_dict(), sort_keys=False)


# --------------------------------------------------------------------------------------
# validation helpers
# --------------------------------------------------------------------------------------


def _parse_effects(ctx: FieldReader, raw: Any, path: str, n_act: int) -> Effects:
    """Parse ``effects`` / ``corrections``: one key per cause of the registry (:mod:`microctl.stage.causes`).

    Per-actuator causes are lists (at most one entry per actuator), the others one mapping.
    """
    if raw is None:
        return Effects()
    raw = ctx.mapping(raw, path, list(REGISTRY))
    causes = []
    for name, cls in REGISTRY.items():
        if name not in raw or raw[name] is None:
            continue
        if not cls.per_actuator:
            causes.append(_parse_cause(ctx, cls, raw[name], f"{path}.{name}", n_act))
            continue
        entries = raw[name]
        if not isinstance(entries, list):
            raise ctx.fail(f"{path}.{name}", "expected a list of entries, one per actuator")
        seen: set[int] = set()
        for k, entry in enumerate(entries):
            c = _parse_cause(ctx, cls, entry, f"{path}.{name}[{k}]", n_act)
            if c.actuator in seen:
                raise ctx.fail(f"{path}.{name}[{k}].actuator", f"actuator {c.actuator} appears twice")
            seen.add(c.actuator)
            causes.append(c)
    return Effects.of(causes)


def _parse_cause(ctx: FieldReader, cls: type, raw: Any, path: str, n_act: int) -> Any:
    names = [f.name for f in fields(cls)]
    raw = ctx.mapping(raw, path, names, required=names)
    kwargs: dict[str, Any] = {}
    if cls.per_actuator:
        kwargs["actuator"] = ctx.integer(raw["actuator"], f"{path}.actuator", lo=1, hi=n_act)
    for p in cls.params:
        rule = {"positive": {"positive": True}, "nonneg": {"nonneg": True}}.get(p.rule or "", {})
        kwargs[p.name] = ctx.number(raw[p.name], f"{path}.{p.name}", **rule)
    return cls(**kwargs)


def _parse_stage(ctx: FieldReader, raw: Any) -> Stage:
    raw = ctx.mapping(
        raw, "stage", ["name", "dof", "actuators", "tool", "physics", "corrections"], required=["actuators", "tool"]
    )
    name = ctx.string(raw.get("name", "stage"), "stage.name")
    dof = _parse_dof(ctx, raw.get("dof", ["z", "rx", "ry"]))
    actuators = _parse_actuators(ctx, raw["actuators"], dof)
    tool = _parse_tool(ctx, raw["tool"], actuators, dof)
    physics = _parse_physics(ctx, raw.get("physics"), dof)

    # corrections: what a diagnosis found. Mean causes correct the AFM (static ones) or the
    # extended model (dynamic ones); noise causes (stick-slip) tell the residual model which
    # actuators scatter (microctl.models.training.noise_features_for)
    corrections = _parse_effects(ctx, raw.get("corrections"), "stage.corrections", len(actuators))
    stage = Stage(
        name=name,
        dof=tuple(dof),
        actuators=tuple(actuators),
        tool=tool,
        physics=physics,
        corrections=corrections,
    )
    _check_conditioning(ctx, stage)
    return stage


def _parse_dof(ctx: FieldReader, dof_raw: Any) -> list[str]:
    """``stage.dof``: hinge DoF (eq. 5), distinct twist components in twist order."""
    if not isinstance(dof_raw, list) or not dof_raw:
        raise ctx.fail("stage.dof", f"expected a non-empty list of twist components from {list(TWIST_COMPONENTS)}")
    dof = []
    for i, d in enumerate(dof_raw):
        if d not in TWIST_COMPONENTS:
            raise ctx.fail(f"stage.dof[{i}]", f"'{d}' is not a twist component; valid: {', '.join(TWIST_COMPONENTS)}")
        if d in dof:
            raise ctx.fail(f"stage.dof[{i}]", f"'{d}' appears twice")
        dof.append(d)
    dof.sort(key=TWIST_COMPONENTS.index)
    if tuple(dof) != tuple(dof_raw):
        raise ctx.fail("stage.dof", f"list the DoF in twist order, i.e. {dof}")
    return dof


def _parse_actuators(ctx: FieldReader, acts_raw: Any, dof: list[str]) -> list[Actuator]:
    """``stage.actuators``: at least one per DoF, ranges inside the hardware limits, names unique."""
    if not isinstance(acts_raw, list):
        raise ctx.fail("stage.actuators", "expected a list of actuators")
    if len(acts_raw) < len(dof):
        raise ctx.fail(
            "stage.actuators",
            f"{len(acts_raw)} actuators cannot determine {len(dof)} DoF; give at least {len(dof)}",
        )
    actuators = []
    for i, a in enumerate(acts_raw):
        p = f"stage.actuators[{i}]"
        a = ctx.mapping(a, p, ["name", "contact_mm", "normal", "direction", "range_um", "limit_um"], ["contact_mm"])
        act = Actuator(
            name=ctx.string(a.get("name", f"q{i + 1}"), f"{p}.name"),
            contact_mm=ctx.vector(a["contact_mm"], f"{p}.contact_mm", 3),  # type: ignore[arg-type]
            normal=ctx.unit_vector(a.get("normal", [0, 0, 1]), f"{p}.normal"),
            direction=ctx.unit_vector(a.get("direction", [0, 0, 1]), f"{p}.direction"),
            range_um=ctx.interval(a.get("range_um", [0, 32]), f"{p}.range_um", max_abs=MAX_STROKE_UM),
            limit_um=ctx.interval(a.get("limit_um", [0, 38]), f"{p}.limit_um", max_abs=MAX_STROKE_UM),
        )
        if act.range_um[0] < act.limit_um[0] or act.range_um[1] > act.limit_um[1]:
            raise ctx.fail(
                f"{p}.range_um",
                f"{list(act.range_um)} must lie inside the hardware limit {list(act.limit_um)}",
            )
        if any(act.name == b.name for b in actuators):
            raise ctx.fail(f"{p}.name", f"actuator name '{act.name}' is used twice")
        _check_column_name(ctx, act.name, f"{p}.name", dof)
        for j, b in enumerate(actuators):
            if np.allclose(act.contact_mm, b.contact_mm, atol=1e-9, rtol=0):
                raise ctx.fail(f"{p}.contact_mm", f"{list(act.contact_mm)} is the contact point of "
                               f"stage.actuators[{j}] ('{b.name}'); two balls cannot push at one point")
        actuators.append(act)
    return actuators


#: Names a measurement log uses for its own columns (docs/measurement-log.md; the experiment logs'
#: extra columns): an actuator or the tool may not take them.
RESERVED_COLUMN_NAMES = ("seq", "time_s", "trial", "target_um", "controller", "point")


def _check_column_name(ctx: FieldReader, name: str, field: str, dof: list[str]) -> None:
    """An actuator's or the tool's name becomes a log column: it must not be one the log already has."""
    reserved = set(RESERVED_COLUMN_NAMES) | {f"u_{d}" for d in dof}
    if name in reserved or name.endswith("_prev"):
        raise ctx.fail(field, f"'{name}' is a measurement-log column name ({', '.join(sorted(reserved))}, and "
                       "NAME_prev); choose another name")


def _parse_tool(ctx: FieldReader, raw: Any, actuators: list[Actuator], dof: list[str]) -> Tool:
    """``stage.tool``: the tool point and gauge direction (eq. 13), its name clashing with none."""
    t = ctx.mapping(raw, "stage.tool", ["name", "point_mm", "direction"], ["point_mm"])
    tool = Tool(
        name=ctx.string(t.get("name", "t"), "stage.tool.name"),
        point_mm=ctx.vector(t["point_mm"], "stage.tool.point_mm", 3),  # type: ignore[arg-type]
        direction=ctx.unit_vector(t.get("direction", [0, 0, 1]), "stage.tool.direction"),
    )
    if tool.name in {a.name for a in actuators} or tool.name in dof:
        raise ctx.fail("stage.tool.name", f"'{tool.name}' clashes with an actuator or DoF name")
    _check_column_name(ctx, tool.name, "stage.tool.name", dof)
    return tool


def _parse_physics(ctx: FieldReader, raw: Any, dof: list[str]) -> Physics:
    """``stage.physics``: contact stiffness, preload and flexure stiffness per DoF (all > 0)."""
    ph = ctx.mapping(
        raw,
        "stage.physics",
        ["contact_stiffness_n_per_um", "preload_n", "flexure_stiffness"],
        none_ok=True,
    )
    default = Physics()
    flex_default = dict(zip(("z", "rx", "ry"), default.flexure_stiffness))
    flex_raw = ph.get("flexure_stiffness", [flex_default.get(d, 1.0) for d in dof])
    physics = Physics(
        contact_stiffness_n_per_um=ctx.number(
            ph.get("contact_stiffness_n_per_um", default.contact_stiffness_n_per_um),
            "stage.physics.contact_stiffness_n_per_um",
            positive=True,
        ),
        preload_n=ctx.number(ph.get("preload_n", default.preload_n), "stage.physics.preload_n", positive=True),
        flexure_stiffness=ctx.vector(flex_raw, "stage.physics.flexure_stiffness", len(dof)),
    )
    for i, k in enumerate(physics.flexure_stiffness):
        if k <= 0:
            raise ctx.fail(f"stage.physics.flexure_stiffness[{i}]", f"must be > 0, got {k!r}")
    return physics


def _check_conditioning(ctx: FieldReader, stage: Stage) -> None:
    """Refuse geometries where H R^T J (eq. 10) or K (eq. 12) is singular or ill-conditioned."""

    hrj, _ = contact_map(stage)
    for i, a in enumerate(stage.actuators):
        nd = hrj[i, i]
        if abs(nd) < 1e-12:
            raise ctx.fail(
                f"stage.actuators[{i}].direction",
                "is perpendicular to the contact normal (n·d = 0): the ball cannot push the platform, so "
                "H R^T J (eq. 10) is singular; give a direction with a component along the normal",
            )
        if abs(nd) < MIN_TRANSMISSION:
            raise ctx.fail(
                f"stage.actuators[{i}].direction",
                f"makes H R^T J (eq. 10) ill-conditioned: n·d = {nd:.3g}, need |n·d| >= {MIN_TRANSMISSION} "
                "(direction within ~84° of the contact normal)",
            )
    cond = np.linalg.cond(hrj)
    if not np.isfinite(cond) or cond > MAX_CONDITION:
        raise ctx.fail(
            "stage.actuators",
            f"H R^T J (eq. 10) is ill-conditioned (condition number {cond:.3g} > {MAX_CONDITION:g}); "
            "tilt the directions closer to the contact normals",
        )
    K = inverse_kinematics_matrix(stage)
    sv = np.linalg.svd(K, compute_uv=False)
    if sv[-1] <= sv[0] / MAX_CONDITION:
        raise ctx.fail(
            "stage.actuators",
            f"the contact points do not determine the DoF {list(stage.dof)} (inverse kinematics K has "
            f"condition number {sv[0] / max(sv[-1], 1e-300):.3g}); place the contacts so that no platform "
            "motion leaves every contact height unchanged (e.g. not all on one line)",
        )


def _parse_backend(ctx: FieldReader, raw: Any, stage: Stage) -> Backend:
    if raw is None:
        return Backend()
    raw = ctx.mapping(raw, "backend", ["kind", "simulated", "serial"])
    kind = raw.get("kind", "simulated")
    if kind not in BACKEND_KINDS:
        raise ctx.fail("backend.kind", f"'{kind}' is not a backend; valid: {', '.join(BACKEND_KINDS)}")
    s = ctx.mapping(
        raw.get("simulated"),
        "backend.simulated",
        ["seed", "gauge_noise_std_um", "driver_accuracy_um", "move_time_s", "effects"],
        none_ok=True,
    )
    d = SimulatedBackend()
    sim = SimulatedBackend(
        seed=ctx.integer(s.get("seed", d.seed), "backend.simulated.seed", lo=0),
        gauge_noise_std_um=ctx.number(
            s.get("gauge_noise_std_um", d.gauge_noise_std_um), "backend.simulated.gauge_noise_std_um", nonneg=True
        ),
        driver_accuracy_um=ctx.number(
            s.get("driver_accuracy_um", d.driver_accuracy_um), "backend.simulated.driver_accuracy_um", nonneg=True
        ),
        move_time_s=ctx.number(s.get("move_time_s", d.move_time_s), "backend.simulated.move_time_s", positive=True),
        effects=_parse_effects(ctx, s.get("effects"), "backend.simulated.effects", stage.n_act),
    )
    serial = None
    if raw.get("serial") is not None:
        serial = parse_serial(ctx, raw["serial"], stage)
    if kind == "serial" and serial is None:
        raise ctx.fail("backend.serial", "is required when backend.kind is 'serial'")
    return Backend(kind=kind, simulated=sim, serial=serial)


# --------------------------------------------------------------------------------------
# public loaders
# --------------------------------------------------------------------------------------


def parse_stage_config(data: Any, source: str = "<memory>") -> StageConfig:
    """Validate an already-parsed YAML document.

    Parameters
    ----------
    data : mapping
        The document, with keys ``stage`` and optionally ``backend``.
    source : str
        Name used in error messages.

    Raises
    ------
    ConfigError
        On any invalid or unknown field.
    """
    ctx = FieldReader(source)
    if not isinstance(data, Mapping):
        raise ConfigError(f"{source}: expected a YAML mapping with a 'stage' section, got {type(data).__name__}")
    top = ctx.mapping(data, "<top>", ["stage", "backend"], required=["stage"])
    stage = _parse_stage(ctx, top["stage"])
    backend = _parse_backend(ctx, top.get("backend"), stage)
    return StageConfig(stage=stage, backend=backend, source=source)


class _StrictLoader(yaml.SafeLoader):
    """``yaml.SafeLoader`` that refuses duplicate keys and reads ``1e-3`` as a number.

    YAML 1.1 (PyYAML) silently keeps the last of two equal keys in a mapping and reads a
    float without a dot (``1e-3``) as text; a config must not lose a field that way.
    """

    def construct_mapping(self, node: yaml.MappingNode, deep: bool = False) -> dict:
        seen: dict[Any, yaml.Node] = {}
        for key_node, _ in node.value:
            if key_node.tag == "tag:yaml.org,2002:merge":
                continue
            key = self.construct_object(key_node, deep=True)
            try:
                first = seen.get(key)
            except TypeError:  # an unhashable key: the base class says so
                break
            if first is not None:
                raise yaml.constructor.ConstructorError(
                    problem=f"duplicate key {key!r} (first at line {first.start_mark.line + 1}); "
                            "a key may appear once per mapping",
                    problem_mark=key_node.start_mark,
                )
            seen[key] = key_node
        return super().construct_mapping(node, deep=deep)


_StrictLoader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"^[-+]?(?:[0-9]+(?:\.[0-9]*)?|\.[0-9]+)[eE][-+]?[0-9]+$"),
    list("-+0123456789."),
)


if getattr(yaml, "__with_libyaml__", False):
    class _StrictCLoader(yaml.cyaml.CParser, _StrictLoader):  # type: ignore[misc]
        """:class:`_StrictLoader` on libyaml's parser (the same constructor and resolvers, marks
        with line and column): parsing a stage file takes a fraction of the pure-Python parser's
        time, which is part of a one-shot command's start-up."""

        def __init__(self, stream: str):
            yaml.cyaml.CParser.__init__(self, stream)
            yaml.constructor.SafeConstructor.__init__(self)
            yaml.resolver.Resolver.__init__(self)

    _LOADER: type = _StrictCLoader
else:  # PyYAML built without libyaml
    _LOADER = _StrictLoader


#: Most values (scalars, lists, mappings) a YAML document may expand to through its aliases.
MAX_YAML_VALUES = 1_000_000


def _expanded_size(obj: Any, memo: dict) -> int:
    """How many values ``obj`` holds with every alias expanded (shared objects counted per use)."""
    if not isinstance(obj, (list, dict)):
        return 1
    key = id(obj)
    if key not in memo:
        memo[key] = 0  # a cycle (a recursive alias) counts once
        children = obj.values() if isinstance(obj, dict) else obj
        memo[key] = 1 + sum(_expanded_size(c, memo) for c in children)
    return memo[key]


def load_yaml(path: str | Path) -> Any:
    """Read a UTF-8 YAML file (a leading BOM is fine), turning every problem into :class:`ConfigError`.

    Refused, each with the file and, where it applies, the line and column: an unreadable
    file or a directory, a FIFO or device, bytes that are not UTF-8, invalid YAML, a key given
    twice in one mapping, nesting too deep to read, aliases that expand to more than
    :data:`MAX_YAML_VALUES` values.
    """
    path = Path(path)
    if path.exists() and not path.is_dir() and not path.is_file():  # a FIFO or a device would block or never end
        raise ConfigError(f"{path}: is not a regular file (a FIFO, socket or device); give a YAML file")
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read: {exc.strerror or exc}") from None
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        line = raw.count(b"\n", 0, exc.start) + 1
        column = exc.start - (raw.rfind(b"\n", 0, exc.start) + 1) + 1
        raise ConfigError(
            f"{path}: not UTF-8 text: byte 0x{raw[exc.start]:02x} at line {line}, column {column} cannot be "
            "decoded; save the file as UTF-8"
        ) from None
    try:
        doc = yaml.load(text, Loader=_LOADER)  # noqa: S506 - a SafeLoader subclass
        size = _expanded_size(doc, {})
        if size > MAX_YAML_VALUES:
            raise ConfigError(f"{path}: the YAML expands to {size:.3g} values through its aliases (*name); at most "
                              f"{MAX_YAML_VALUES} are read (an alias bomb?); write the values out")
        return doc
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark is not None else ""
        problem = getattr(exc, "problem", None) or str(exc).splitlines()[0]
        raise ConfigError(f"{path}: invalid YAML{where}: {problem}") from None
    except RecursionError:
        raise ConfigError(f"{path}: invalid YAML: nested too deeply to read") from None


def load_stage_config(path: str | Path) -> StageConfig:
    """Load and validate a stage YAML file.

    Parameters
    ----------
    path : str or Path
        The file, e.g. ``configs/stage/table1.yaml``, or the short name of a packaged stage
        config (``table1``; :func:`microctl.util.packaged.resolve_config`).

    Returns
    -------
    StageConfig

    Raises
    ------
    ConfigError
        Naming the file and the field path.
    """
    resolved = resolve_config(path, "stage")
    if not resolved.exists():
        raise ConfigError(f"{path}: cannot read: No such file or directory{missing_hint('stage')}")
    data = load_yaml(resolved)
    if isinstance(data, Mapping) and isinstance(data.get("stage"), str) and "backend" not in data:
        raise ConfigError(f"{path}: this is an experiment file (its 'stage:' names the stage file "
                          f"'{data['stage']}'), not a stage file; run it with `microctl experiment {path}`, or give "
                          "--config the stage file it names")
    return parse_stage_config(data, source=str(path))

