"""Experiment YAML → frozen dataclasses, validated before any move is made.

An experiment file names the stage config (a path relative to the experiment file), the
seeds, the training (paper IV-A: 125 moves), the controllers compared and which experiments
to run (absolute movement IV-C, incremental movement IV-D). Every problem is a
:class:`~microctl.errors.ConfigError` naming the file and the field path
(``incremental.targets_um[2]``); unknown keys are rejected at every level. The stage config
is loaded (and so validated) here too, so that a bad field anywhere fails before the
backend is opened. See ``docs/experiments.md`` for the reference.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, replace
from functools import cache
from pathlib import Path
from typing import Any, Callable, Mapping

from microctl.control.controller import ControllerSettings
from microctl.control.refine import EPISODE_TARGETS, REFINE_STRATEGIES
from microctl.errors import ConfigError
import microctl.experiments.controllers as registry
from microctl.measurement.design import DEFAULT_DESIGN, DESIGNS, MAX_MOVES
from microctl.models.training import AUTO_SPARSE_ROWS, MAX_SPARSE_ROWS, ResidualModelSettings
from microctl.stage.config import StageConfig, load_stage_config, load_yaml
from microctl.util.packaged import missing_hint, resolve_config
from microctl.util.fields import (
    FieldReader,
    read_settings,
    same_setting,
    setting,
    validate_settings,
)

#: Controllers of an experiment file that does not list them (the registry's defaults:
#: :mod:`microctl.experiments.controllers` lists every controller an experiment can compare).
DEFAULT_CONTROLLERS = registry.default_names()


@dataclass(frozen=True)
class Seeds:
    """Seeds of every random choice (same file + same seeds → same results).

    Attributes
    ----------
    design : int
        Training move design.
    gp : int
        VHGPR restarts.
    training_stage : int
        Simulated stage during training (first round; refinement round r uses ``+ r``).
    absolute_points : int
        The 30 control signals of the absolute experiment.
    absolute_stage : int
        Simulated stage of absolute trial k: ``absolute_stage + k``.
    incremental_stage : int
        Simulated stage of incremental trial k: ``incremental_stage + k``, the same for every
        controller (common random numbers).
    refine_targets : int
        Targets of the refinement episodes.
    """

    design: int = 0
    gp: int = 0
    training_stage: int = 1
    absolute_points: int = 2
    absolute_stage: int = 100
    incremental_stage: int = 1000
    refine_targets: int = 3


@dataclass(frozen=True)
class Training:
    """Training of the residual VHGPR (paper IV-A, eq. 3).

    Attributes
    ----------
    moves : int
        Moves of the initial design (the paper: 125).
    design : str
        One of :data:`~microctl.measurement.design.DESIGNS` (default ``covering_still``).
    episode_moves : int
        Moves per episode of the ``face_episodes`` design (after its return to the zero state).
    noise_model, linear_trend, se, mean_shift, g_inputs, g_start, g_gp, restarts, max_iter, noise_sources
        The residual model (:class:`~microctl.models.training.ResidualModelSettings`; same defaults).
    refine_rounds : int
        Refinement rounds after the first fit (0: none): each runs incremental episodes,
        logs them as training moves and refits.
    refine_moves : int
        Moves per refinement round.
    refine_episode_targets : int
        Targets per refinement episode (each episode starts with a return to the zero state).
    refine_target_range_um : tuple of 2 float or None
        Range the refinement targets are drawn from (default: the AFM's reachable range);
        must lie inside it.
    refine_strategy : str
        ``uncertainty`` (default): at each refinement target, among the candidate optimal
        poses of the redundant set (local minima of the optimistic and of the cautious
        objective), execute the one whose predicted noise is least certain, so the model
        learns where the optimum might be rather than only where the controller already
        goes; ``on_policy``: the controller's own choice.
    """

    moves: int = setting(125, lo=5, hi=MAX_MOVES)
    design: str = setting(DEFAULT_DESIGN, choices=DESIGNS)
    episode_moves: int = setting(4, lo=1, hi=1000)
    noise_model: str = same_setting(ResidualModelSettings, "noise_model")
    linear_trend: bool = same_setting(ResidualModelSettings, "linear_trend")
    se: str = same_setting(ResidualModelSettings, "se")
    mean_shift: bool = same_setting(ResidualModelSettings, "mean_shift")
    g_inputs: str = same_setting(ResidualModelSettings, "g_inputs")
    g_start: str = same_setting(ResidualModelSettings, "g_start")
    g_gp: str = same_setting(ResidualModelSettings, "g_gp")
    restarts: int = same_setting(ResidualModelSettings, "restarts")
    max_iter: int | None = same_setting(ResidualModelSettings, "max_iter")
    noise_sources: tuple[str, ...] | None = same_setting(ResidualModelSettings, "noise_sources")
    refine_rounds: int = setting(0, lo=0, hi=20)
    refine_moves: int = setting(40, lo=1, hi=MAX_MOVES)
    refine_episode_targets: int = setting(EPISODE_TARGETS, lo=1, hi=1000)
    refine_target_range_um: tuple[float, float] | None = None
    refine_strategy: str = setting("uncertainty", choices=REFINE_STRATEGIES)

    def __post_init__(self) -> None:
        validate_settings(self, "training setting")
        self.model_settings(0)  # the residual model's own rules across fields (ConfigError)

    def model_settings(self, seed: int) -> ResidualModelSettings:
        """The residual model these settings describe, with the fit's seed."""
        return ResidualModelSettings(noise_model=self.noise_model, linear_trend=self.linear_trend, se=self.se,
                                     mean_shift=self.mean_shift, g_inputs=self.g_inputs, g_start=self.g_start,
                                     g_gp=self.g_gp, restarts=self.restarts,
                                     max_iter=self.max_iter, seed=seed, noise_sources=self.noise_sources)


@dataclass(frozen=True)
class Oracle:
    """Settings of the oracle controller (:mod:`microctl.control.oracle`).

    Attributes
    ----------
    grid : int
        Grid points per null-space axis of the redundant set.
    line_points : int
        Points on each "actuator still" line (where the variance has its kinks).
    zooms : int
        Grid refinements around the best candidate.
    newton_steps : int
        Newton steps moving candidates onto the true-mean surface.
    """

    grid: int = 31
    line_points: int = 61
    zooms: int = 2
    newton_steps: int = 6


@dataclass(frozen=True)
class Absolute:
    """The absolute movement experiment (paper IV-C).

    Attributes
    ----------
    enabled : bool
    points : int
        Control signals covering the workspace (the paper: 30).
    trials : int
        Trials per point (the paper: 2).
    """

    enabled: bool = True
    points: int = 30
    trials: int = 2


@dataclass(frozen=True)
class Incremental:
    """The incremental movement experiment (paper IV-D).

    Attributes
    ----------
    enabled : bool
    targets_um : tuple of float
        Reached in sequence from the zero state (the paper: 7, 14, 21, 28 µm).
    trials : int
        The paper: 10. Each trial starts by returning to the zero state.
    """

    enabled: bool = True
    targets_um: tuple[float, ...] = (7.0, 14.0, 21.0, 28.0)
    trials: int = 10


@dataclass(frozen=True)
class ExperimentConfig:
    """A whole experiment file, resolved.

    Attributes
    ----------
    source : str
        The experiment file (for messages).
    stage_path : Path
        The stage config, resolved against the experiment file's folder.
    stage_config : StageConfig
        The loaded (validated) stage config.
    emulate : bool
        Serve the stage in-process (:class:`~microctl.backends.emulator.Emulator`) and drive it through
        the serial backend (needs ``backend.serial`` in the stage config).
    controllers : tuple of str
        Controllers compared, registered in :mod:`microctl.experiments.controllers` (``afm`` and
        ``eafm`` required; default :data:`DEFAULT_CONTROLLERS`).
    seeds : Seeds
    training : Training
    controller : ControllerSettings
        Settings of the AFM and EAFM controllers.
    oracle : Oracle
    absolute : Absolute
    incremental : Incremental
    figures : bool
        Write PNG figures when matplotlib is available.
    seed_offset : int
        Added to every seed of the file (``microctl experiment --seed-offset``): the same
        experiment on another draw of every random choice.
    """

    source: str
    stage_path: Path
    stage_config: StageConfig
    emulate: bool = False
    controllers: tuple[str, ...] = DEFAULT_CONTROLLERS
    seeds: Seeds = field(default_factory=Seeds)
    training: Training = field(default_factory=Training)
    controller: ControllerSettings = field(default_factory=ControllerSettings)
    oracle: Oracle = field(default_factory=Oracle)
    absolute: Absolute = field(default_factory=Absolute)
    incremental: Incremental = field(default_factory=Incremental)
    figures: bool = True
    seed_offset: int = 0

    def with_seed_offset(self, offset: int) -> "ExperimentConfig":
        """The same experiment with every seed shifted by ``offset`` (>= 0)."""
        if isinstance(offset, bool) or int(offset) != offset or offset < 0:
            raise ConfigError(f"the seed offset must be a non-negative integer, got {offset!r}")
        seeds = Seeds(**{k: v + int(offset) for k, v in asdict(self.seeds).items()})
        return replace(self, seeds=seeds, seed_offset=self.seed_offset + int(offset))

    @property
    def simulated(self) -> bool:
        """Whether the stage is simulated in-process (a simulated backend or the emulator)."""
        return self.stage_config.backend.kind == "simulated" or self.emulate

    def to_dict(self) -> dict[str, Any]:
        """The resolved experiment as plain data (the YAML form, stage path absolute)."""
        tr = asdict(self.training)
        if tr["refine_target_range_um"] is not None:
            tr["refine_target_range_um"] = list(tr["refine_target_range_um"])
        if tr["noise_sources"] is not None:
            tr["noise_sources"] = list(tr["noise_sources"])
        inc = asdict(self.incremental)
        inc["targets_um"] = list(inc["targets_um"])
        return {
            "stage": str(self.stage_path),
            "emulate": self.emulate,
            "controllers": list(self.controllers),
            "seeds": asdict(self.seeds),
            "training": tr,
            "controller": asdict(self.controller),
            "oracle": asdict(self.oracle),
            "absolute": asdict(self.absolute),
            "incremental": inc,
            "figures": self.figures,
            "seed_offset": self.seed_offset,
        }


# --------------------------------------------------------------------------------------
# validation
# --------------------------------------------------------------------------------------


#: Largest value of each ``oracle`` setting (its work grows with grid², line_points, zooms).
ORACLE_MAX = {"grid": 201, "line_points": 1001, "zooms": 10, "newton_steps": 50}

#: Most moves an experiment section may ask for (points × trials, targets × trials).
MAX_EXPERIMENT_MOVES = 20_000


def _section(ck: FieldReader, raw: Mapping, name: str, cls: type, ints: dict, hi: dict | None = None,
             **kw) -> Any:
    """Parse a section whose fields are all integers (given as name -> minimum; ``hi``: name -> maximum)."""
    d = cls()
    hi = hi or {}
    sec = ck.mapping(raw.get(name), name, list(ints) + list(kw), none_ok=True)
    vals = {k: ck.integer(sec.get(k, getattr(d, k)), f"{name}.{k}", lo=lo, hi=hi.get(k)) for k, lo in ints.items()}
    for k, parse in kw.items():
        vals[k] = parse(sec.get(k, getattr(d, k)), f"{name}.{k}")
    return cls(**vals)


def parse_experiment_config(data: Any, source: str, base_dir: Path) -> ExperimentConfig:
    """Validate an already-parsed experiment document.

    Parameters
    ----------
    data : mapping
        The YAML document.
    source : str
        Name used in messages (the file).
    base_dir : Path
        Folder relative paths are resolved against (the experiment file's).

    Raises
    ------
    ConfigError
        Naming the file and the field path; also any error of the stage config it names.
    """
    ck = FieldReader(source)
    top = ck.mapping(
        data, "",
        ["stage", "emulate", "controllers", "seeds", "training", "controller", "oracle", "absolute",
         "incremental", "figures"],
        required=["stage"], none_ok=True,
    )
    stage_path, stage_config = _read_stage(ck, top["stage"], base_dir)
    emulate = ck.boolean(top.get("emulate", False), "emulate")
    controllers = _read_controllers(ck, top, stage_config, stage_path, emulate)
    seeds = _section(ck, top, "seeds", Seeds, {k: 0 for k in Seeds.__dataclass_fields__})

    @cache
    def reachable() -> tuple[float, float]:  # the AFM's reachable t range (two LPs), computed once
        from microctl.models.afm import AnalyticForwardModel

        return AnalyticForwardModel(stage_config.stage).t_range()

    tr_raw = top.get("training")
    rng = None
    if isinstance(tr_raw, Mapping) and tr_raw.get("refine_target_range_um") is not None:
        rng = ck.interval(tr_raw["refine_target_range_um"], "training.refine_target_range_um")
        _check_in_range(ck, reachable(), "training.refine_target_range_um", rng)
    training = read_settings(ck, tr_raw, "training", Training, refine_target_range_um=rng)
    rows = training.moves + training.refine_rounds * training.refine_moves
    if rows > MAX_SPARSE_ROWS:
        raise ck.fail("training", f"moves + refine_rounds × refine_moves = {rows} training rows; the residual model "
                      f"is trained on at most {MAX_SPARSE_ROWS} (the sparse GP above {AUTO_SPARSE_ROWS} rows)")
    controller = read_settings(ck, top.get("controller"), "controller", ControllerSettings)

    oracle = _section(ck, top, "oracle", Oracle, {"grid": 5, "line_points": 5, "zooms": 0, "newton_steps": 1},
                      hi=ORACLE_MAX)
    absolute, incremental = _read_movements(ck, top, reachable)

    return ExperimentConfig(
        source=source, stage_path=stage_path, stage_config=stage_config, emulate=emulate,
        controllers=controllers, seeds=seeds, training=training, controller=controller, oracle=oracle,
        absolute=absolute, incremental=incremental,
        figures=ck.boolean(top.get("figures", True), "figures"),
    )


def _read_stage(ck: FieldReader, stage_raw: Any, base_dir: Path) -> tuple[Path, StageConfig]:
    """The ``stage`` field: the stage config's path (resolved against ``base_dir``) and the loaded config."""
    if not isinstance(stage_raw, str) or not stage_raw.strip():
        raise ck.fail("stage", f"expected the path of a stage config, got {stage_raw!r}")
    stage_path = Path(stage_raw)
    if not stage_path.is_absolute():
        stage_path = (base_dir / stage_path).resolve()
    if stage_path.is_dir():
        raise ck.fail("stage", f"'{stage_raw}' is a directory ({stage_path}); give the path of a stage config file")
    if not stage_path.is_file():
        raise ck.fail("stage", f"stage config '{stage_raw}' not found (looked for {stage_path})")
    return stage_path, load_stage_config(stage_path)


def _read_controllers(ck: FieldReader, top: Mapping, stage_config: StageConfig, stage_path: Path,
                      emulate: bool) -> tuple[str, ...]:
    """The ``controllers`` list, checked against the registry (:mod:`microctl.experiments.controllers`):
    known names, none twice, the required ones present, the truth-needing ones only on a simulated
    (or emulated) stage; also checks ``emulate`` has serial devices to emulate."""
    known = registry.names()
    ctrl_raw = top.get("controllers", list(registry.default_names()))
    if not isinstance(ctrl_raw, list) or not ctrl_raw:
        raise ck.fail("controllers", f"expected a list of controllers from {', '.join(known)}, got {ctrl_raw!r}")
    controllers = tuple(ck.choice(c, f"controllers[{i}]", known) for i, c in enumerate(ctrl_raw))
    if len(set(controllers)) != len(controllers):
        raise ck.fail("controllers", f"lists a controller twice: {list(controllers)}")
    for need in registry.required_names():
        if need not in controllers:
            raise ck.fail("controllers", f"must include '{need}' (the paper compares AFM and EAFM)")
    backend = stage_config.backend
    if emulate and backend.serial is None:
        raise ck.fail("emulate", f"needs a stage config with backend.serial (the devices to emulate); "
                                 f"{stage_path} has none")
    simulated = backend.kind == "simulated" or emulate
    for name in known:
        if name in controllers and registry.entry(name).needs_truth and not simulated:
            raise ck.fail("controllers", f"'{name}' needs the simulator's true mean and variance: use a simulated "
                                         "stage (backend.kind: simulated) or emulate: true")
    return controllers


def _read_movements(ck: FieldReader, top: Mapping, reachable: Callable[[], tuple[float, float]]
                    ) -> tuple[Absolute, Incremental]:
    """The ``absolute`` and ``incremental`` sections (at least one enabled; every target reachable)."""
    ab = ck.mapping(top.get("absolute"), "absolute", ["enabled", "points", "trials"], none_ok=True)
    da = Absolute()
    absolute = Absolute(
        enabled=ck.boolean(ab.get("enabled", da.enabled), "absolute.enabled"),
        points=ck.integer(ab.get("points", da.points), "absolute.points", lo=2),
        trials=ck.integer(ab.get("trials", da.trials), "absolute.trials", lo=1),
    )

    inc = ck.mapping(top.get("incremental"), "incremental", ["enabled", "targets_um", "trials"], none_ok=True)
    di = Incremental()
    incremental = Incremental(
        enabled=ck.boolean(inc.get("enabled", di.enabled), "incremental.enabled"),
        targets_um=ck.vector(inc.get("targets_um", list(di.targets_um)), "incremental.targets_um"),
        trials=ck.integer(inc.get("trials", di.trials), "incremental.trials", lo=2),
    )
    for sec, n, what in (("absolute", absolute.points * absolute.trials, "points × trials"),
                         ("incremental", len(incremental.targets_um) * incremental.trials, "targets × trials")):
        if n > MAX_EXPERIMENT_MOVES:
            raise ck.fail(sec, f"{what} = {n} moves per controller; at most {MAX_EXPERIMENT_MOVES} are run")
    if not absolute.enabled and not incremental.enabled:
        raise ck.fail("incremental.enabled", "both experiments are disabled; enable absolute or incremental")
    if incremental.enabled:
        for i, t in enumerate(incremental.targets_um):  # every target reachable, checked before any move
            _check_in_range(ck, reachable(), f"incremental.targets_um[{i}]", (t,))
    return absolute, incremental


def _check_in_range(ck: FieldReader, reachable: tuple[float, float], path: str, values: tuple[float, ...]) -> None:
    """Tool poses inside the AFM's reachable range [lo, hi] (the bound printed in full precision)."""
    lo, hi = reachable
    for t in values:
        if not lo <= t <= hi:
            raise ck.fail(path, f"{t:g} µm is outside the stage's reachable range [{lo!r}, {hi!r}] µm")


def load_experiment_config(path: str | Path) -> ExperimentConfig:
    """Load and validate an experiment YAML file (and the stage config it names).

    Parameters
    ----------
    path : str or Path

    Returns
    -------
    ExperimentConfig

    Raises
    ------
    ConfigError
        Naming the file and the field path.
    """
    given = path
    path = resolve_config(path, "experiments")
    if not path.exists():
        raise ConfigError(f"{given}: cannot read: No such file or directory{missing_hint('experiments')}")
    data = load_yaml(path)
    if not isinstance(data, Mapping):
        raise ConfigError(f"{path}: expected a YAML mapping with at least 'stage', got {type(data).__name__}")
    if "backend" in data or isinstance(data.get("stage"), Mapping):
        raise ConfigError(f"{path}: this is a stage file (it has 'stage:' as a mapping or 'backend:'), not an "
                          "experiment file; give it to --config of collect/train/solve/diagnose, or name it in an "
                          "experiment file's 'stage:' (e.g. configs/experiments/paper.yaml)")
    return parse_experiment_config(data, str(path), path.resolve().parent)
