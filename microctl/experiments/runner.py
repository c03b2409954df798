"""Run an experiment: training, absolute movement (IV-C), incremental movement (IV-D).

Every move of every phase goes through :class:`MoveRecorder`, which writes one measurement-log
row (``shared/spec/measurement-log.md``) per completed move, flushed at once, with the extra
columns ``trial``, ``target_um``, ``controller`` (and ``point`` for the absolute experiment).
An interrupted run (Ctrl-C, a backend error) therefore leaves valid logs of every completed
move; :func:`run_experiment` says so in the error it raises.

Common random numbers (simulated backend): every incremental trial k opens a fresh simulated
stage with seed ``seeds.incremental_stage + k`` for *each* controller, so all controllers meet
the same noise draws move for move (a simulated move draws a fixed number of normals), and
differences between controllers come from the controllers, not from the noise. Absolute trial
k likewise uses ``seeds.absolute_stage + k``. Through the serial backend (hardware or the
emulator) the stage cannot be reseeded: one stage serves the whole run.
"""

from __future__ import annotations

import contextlib
import math
import sys
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Callable, Iterator

import numpy as np

from microctl.backends import make_backend
from microctl.backends.base import StageBackend
from microctl.control.controller import ControlResult, OptimalController
from microctl.control.context import ByDirection
from microctl.control.memory import with_memory
from microctl.control.refine import check_target_range, refinement_moves
from microctl.errors import BackendError, SolveError
import microctl.experiments.controllers as registry
from microctl.experiments.config import ExperimentConfig
from microctl.measurement.design import space_filling_moves, training_moves
from microctl.measurement.log import Measurement, MeasurementLogWriter, read_log
from microctl.models import direction
from microctl.models.afm import AnalyticForwardModel
from microctl.models.eafm import EAFM
from microctl.models.floor_check import with_floor_check
from microctl.models.outlier_screen import describe_screen
from microctl.models.training import (
    noise_summary,
    residual_dataset,
    train_residual_model,
)
from microctl.stage.config import StageConfig
from microctl.util.progress import Progress
from microctl.util.signals import raise_if_interrupted

__all__ = ["MoveRecorder", "ExperimentInterrupted", "run_experiment", "BackendFactory"]

#: ``factory(stage_config, seed) -> StageBackend``; seed None = the config's own.
BackendFactory = Callable[[StageConfig, "int | None"], StageBackend]

LOG_NAMES = {"training": "training_log.csv", "absolute": "absolute_log.csv", "incremental": "incremental_log.csv"}


class ExperimentInterrupted(BackendError):
    """A run stopped by a backend error; the message lists the logs and their rows."""


def default_backend_factory(config: StageConfig, seed: int | None) -> StageBackend:
    """Open the configured backend; the simulated stage is reseeded with ``seed``."""
    if config.backend.kind == "simulated" and seed is not None:
        return make_backend(config, seed=int(seed))
    return make_backend(config)


class MoveRecorder:
    """Executes moves and logs each one as a measurement-log row, written and flushed at once.

    Parameters
    ----------
    path : Path
        The log file (created).
    config : StageConfig
        Gives the column names.
    extra_columns : tuple of str
        Extra columns written after ``t``.

    Attributes
    ----------
    rows : int
        Completed (logged) moves.
    """

    def __init__(self, path: Path, config: StageConfig, extra_columns: tuple[str, ...]):
        self.path = Path(path)
        self.writer = MeasurementLogWriter(self.path, config.stage, extra_columns=extra_columns)
        self._clock_offset_s = 0.0
        self._last_time_s = 0.0
        self._last_backend: StageBackend | None = None  # held, so its id cannot be reused

    @property
    def rows(self) -> int:
        return self.writer.rows

    def move(self, backend: StageBackend, u: np.ndarray, **extra: Any) -> tuple[Measurement, np.ndarray]:
        """Execute ``u`` (shape (n_p,)) and log it.

        ``time_s`` keeps increasing across trials: a backend not seen in the previous move is a
        fresh stage whose clock restarted at 0, so the time run so far is added to it; the shared
        serial backend keeps its own clock running and gets nothing added.

        Returns
        -------
        m : Measurement
        s_prev : ndarray, shape (n_s,)
            The state before the move.
        """
        if backend is not self._last_backend:
            if self._last_backend is not None:  # a fresh stage: its clock restarted at 0
                self._clock_offset_s += self._last_time_s
            self._last_backend = backend
            self._last_time_s = 0.0
        s_prev = backend.state
        raise_if_interrupted()  # a Ctrl-C whose KeyboardInterrupt was lost (microctl.util.signals): stop here
        m = backend.move(u)
        self._last_time_s = m.time_s
        logged = replace(m, time_s=m.time_s + self._clock_offset_s)
        self.writer.write(logged, s_prev, extra=extra)
        return m, s_prev

    def close(self) -> None:
        self.writer.close()


@dataclass
class _Run:
    """Mutable state of one run (logs, timings, the stage in use)."""

    cfg: ExperimentConfig
    out: Path
    stage_config: StageConfig
    factory: BackendFactory
    quiet: bool
    afm: AnalyticForwardModel
    recorders: dict[str, MoveRecorder] = field(default_factory=dict)
    timings_s: dict[str, float] = field(default_factory=dict)
    shared_backend: StageBackend | None = None
    emulator: Any = None

    def say(self, text: str) -> None:
        if not self.quiet:
            print(text, file=sys.stderr)

    @contextlib.contextmanager
    def backend(self, seed: int | None) -> Iterator[StageBackend]:
        """A stage for one trial: fresh and reseeded when simulated, else the shared one."""
        if self.stage_config.backend.kind == "simulated":
            with self.factory(self.stage_config, seed) as b:
                yield b
        else:
            if self.shared_backend is None:
                self.shared_backend = self.factory(self.stage_config, None)
            yield self.shared_backend

    def truth(self, backend: StageBackend):
        """The simulated stage behind ``backend`` (for the oracle and true means), or None."""
        if self.emulator is not None:
            return self.emulator.stage
        return backend if hasattr(backend, "true_mean") else None

    def recorder(self, phase: str, extra: tuple[str, ...]) -> MoveRecorder:
        rec = MoveRecorder(self.out / LOG_NAMES[phase], self.stage_config, extra)
        self.recorders[phase] = rec
        return rec

    def log_summary(self) -> str:
        return ", ".join(f"{r.path.name}: {r.rows} rows" for r in self.recorders.values()) or "no log written"


# --------------------------------------------------------------------------------------
# phases
# --------------------------------------------------------------------------------------


def _train(run: _Run) -> tuple[EAFM, dict]:
    """Collect the training moves, fit the residual VHGPR (eq. 3), then refinement rounds if asked
    (:mod:`microctl.control.refine`), each followed by a fit on everything."""
    cfg, afm, tr = run.cfg, run.afm, run.cfg.training
    t0 = time.perf_counter()
    rec = run.recorder("training", ("trial", "target_um", "controller"))
    moves = training_moves(afm, tr.design, tr.moves, cfg.seeds.design, tr.episode_moves)
    with run.backend(cfg.seeds.training_stage) as b, Progress(len(moves), "training moves", quiet=run.quiet) as pr:
        for u in moves:
            m, _ = rec.move(b, u, trial=0, controller="design")
            pr.step(info=f"t = {m.t_um:.3f} µm")
    info: dict[str, Any] = {"design": tr.design, "moves": int(len(moves)), "rounds": [],
                            "refine_strategy": tr.refine_strategy, "explored_moves": 0}
    eafm = _fit(run, info, 0)
    if tr.refine_rounds:
        targets = check_target_range(eafm, tr.refine_target_range_um, "training.refine_target_range_um")
        rng = np.random.default_rng(cfg.seeds.refine_targets)
        for r in range(1, tr.refine_rounds + 1):
            controllers = ByDirection(eafm, lambda e: OptimalController(e, cfg.controller))
            with run.backend(cfg.seeds.training_stage + r) as b, \
                    Progress(tr.refine_moves, f"refinement round {r}", quiet=run.quiet) as pr:
                for mv in refinement_moves(controllers, tr.refine_moves, targets, rng, lambda: b.state,
                                           episode_targets=tr.refine_episode_targets, strategy=tr.refine_strategy):
                    rec.move(b, mv.u, trial=r, target_um=mv.target_um, controller=mv.label)
                    info["explored_moves"] += mv.label == "explore"
                    pr.step()
            eafm = _fit(run, info, r)
    run.timings_s["training"] = time.perf_counter() - t0
    return eafm, info


def _fit(run: _Run, info: dict, round_: int) -> EAFM:
    tr = run.cfg.training
    rec = run.recorders["training"]
    log = read_log(rec.path, run.stage_config.stage, min_rows=5)  # the writer flushed every row
    data = residual_dataset(log, run.afm)
    t0 = time.perf_counter()
    run.say(f"experiment: fitting the VHGPR to {len(data.y)} residuals (round {round_})")
    model = train_residual_model(data, run.afm, tr.model_settings(seed=run.cfg.seeds.gp + round_))
    # a floor the mean correction passes through (microctl.models.floor_check), as `microctl train` checks it
    model, floor = with_floor_check(model, data)
    model.save(run.out / "model.npz")
    info["rounds"].append({"round": round_, "rows": int(len(data.y)), "bound": float(model.bound),
                           "fit_time_s": time.perf_counter() - t0,
                           "f_log_lengthscales": np.asarray(model.f_log_lengthscales).tolist(),
                           "g_log_lengthscales": np.asarray(model.g_log_lengthscales).tolist(),
                           "se_selection": model.info.get("se_selection"),
                           "noise": noise_summary(model, run.afm),
                           "floor_check": model.info.get("floor_check")})
    if floor is not None:
        run.say(f"experiment: round {round_}: warning: {floor.describe()}")
    info["rows"] = int(len(data.y))
    screened = describe_screen((model.info.get("noise_selection") or {}).get("screened"), log.seq)
    if screened:  # the corrupt-reading screen (microctl.models.outlier_screen); the log keeps the rows
        run.say(f"experiment: round {round_}: training_log.csv: {screened}; results.json lists them")
    return EAFM(run.afm, model)


def _absolute(run: _Run, eafm: EAFM) -> dict:
    """IV-C: 30 signals, each from the zero state (u0, u1, u0, u2, ...), ``trials`` trials."""
    cfg, afm = run.cfg, run.afm
    t0 = time.perf_counter()
    rec = run.recorder("absolute", ("trial", "target_um", "controller", "point"))
    U = space_filling_moves(afm, cfg.absolute.points, seed=cfg.seeds.absolute_points)
    n, T = len(U), cfg.absolute.trials
    meas = np.full((T, n), np.nan)
    afm_pred = np.asarray(afm.t_of(U), dtype=float)
    loop = _absolute_loop_shifts(afm, U)  # hysteresis corrections: the loop along u0, u1, u0, u2, ...
    afm_pred = afm_pred + loop
    eafm_mean = np.full((T, n), np.nan)
    eafm_std = np.full((T, n), np.nan)
    eafm_bias_std = np.full((T, n), np.nan)  # f's std: the predicted uncertainty of the mean itself
    true_mean = np.full((T, n), np.nan)
    true_std = np.full((T, n), np.nan)
    zero = np.zeros(afm.n_p)
    with Progress(n * T, "absolute movement", quiet=run.quiet) as pr:
        for k in range(T):
            with run.backend(cfg.seeds.absolute_stage + k) as b:
                truth = run.truth(b)
                last = direction.at_commands(b.state[1:])
                for i, u in enumerate(U):
                    q_before = b.state[1:]
                    rec.move(b, zero, trial=k, point=-1, controller="none")
                    s = b.state
                    last = direction.after_move(last, q_before, s[1:])
                    p = eafm.with_direction(last).predict(s, u)  # the direction: a model with reversals
                    eafm_mean[k, i], eafm_std[k, i] = float(p.t_mean[0]) + loop[i], math.sqrt(float(p.t_var[0]))
                    eafm_bias_std[k, i] = math.sqrt(max(float(p.f_var[0]), 0.0))
                    if truth is not None:
                        true_mean[k, i] = float(truth.true_mean(s, u))
                        true_std[k, i] = math.sqrt(float(truth.true_var(s, u)))
                    m, _ = rec.move(b, u, trial=k, point=i, controller="none")
                    last = direction.after_move(last, s[1:], b.state[1:])
                    meas[k, i] = m.t_um
                    pr.step()
    run.timings_s["absolute"] = time.perf_counter() - t0
    return {"u": U, "measured_um": meas, "afm_um": afm_pred, "eafm_mean_um": eafm_mean,
            "eafm_std_um": eafm_std, "eafm_bias_std_um": eafm_bias_std, "true_mean_um": true_mean, "true_std_um": true_std}


def _absolute_loop_shifts(afm, U: np.ndarray) -> np.ndarray:
    """The hysteresis loop's reading shift at each absolute point (0 without hysteresis corrections).

    Every trial runs the same commands from a fresh stage (the zero state, then each point with a
    return to zero before it), so the play states before point i, and its shift, are the same in
    every trial."""
    mem = afm.memory
    if not mem.active:
        return np.zeros(len(U))
    z, out, zero_q = mem.zero(), np.empty(len(U)), np.zeros(afm.n_q)
    for i, u in enumerate(U):
        z = mem.step(z, zero_q)
        out[i] = mem.shift_at(z, afm.K @ u)
        z = mem.step(z, afm.K @ u)
    return out


def _controllers(run: _Run, eafm: EAFM) -> dict:
    """The configured controllers, built by their registry entries (:mod:`microctl.experiments.controllers`)."""
    return {name: registry.entry(name).build(run, eafm) for name in run.cfg.controllers}


def _incremental(run: _Run, eafm: EAFM) -> dict:
    """IV-D: targets in sequence from the zero state, ``trials`` trials per controller."""
    cfg, afm = run.cfg, run.afm
    t0 = time.perf_counter()
    rec = run.recorder("incremental", ("trial", "target_um", "controller"))
    targets = list(cfg.incremental.targets_um)
    T, J = cfg.incremental.trials, len(targets)
    ctrls = _controllers(run, eafm)
    res: dict[str, Any] = {}
    with Progress(len(ctrls) * T * J, "incremental movement", quiet=run.quiet) as pr:
        for name, ctrl0 in ctrls.items():
            spec = registry.entry(name)
            # a model that reads the actuators' last directions: a controller per direction, for the
            # move-by-move ones and a re-planning sequence controller (each re-plan from the directions
            # the commands sent give, so every executed move is planned with its own)
            by_dir = None if spec.needs_truth or (spec.sequence and not spec.replan) or not eafm.uses_direction \
                else ByDirection(eafm, lambda e, n=name: registry.entry(n).build(run, e))
            r = {key: np.full((T, J), np.nan) for key in
                 ("reached_um", "predicted_um", "predicted_std_um", "true_mean_um", "true_std_um", "solve_time_s",
                  "prob_quieter_than_afm", "credibly_quieter_than_afm")}
            r["q_um"] = np.full((T, J, afm.n_q), np.nan)
            r["status"] = [[""] * J for _ in range(T)]
            r["choice"] = [[""] * J for _ in range(T)]  # which pose the least-motion rule returned, and why
            r["fallbacks"] = 0
            carries = afm.memory.active and not spec.needs_truth
            for k in range(T):
                # the same stage seed for every controller: common random numbers
                with run.backend(cfg.seeds.incremental_stage + k) as b:
                    truth = run.truth(b)
                    if spec.needs_truth:
                        ctrl0.bind(truth)
                    rec.move(b, np.zeros(afm.n_p), trial=k, target_um=0.0, controller=name)  # the zero state
                    prev_u = None
                    plan: Any = None
                    # hysteresis corrections: the play states, stepped with every command sent
                    memory = afm.memory.step(None, b.state[1:]) if carries else None
                    last = direction.at_commands(b.state[1:])
                    for j, target in enumerate(targets):
                        s = b.state
                        ctrl = ctrl0 if by_dir is None else by_dir(last)
                        if spec.sequence:
                            sol, plan = _sequence_step(ctrl, spec.replan, targets[j:], s, plan, run, r,
                                                       fallback=ctrls["afm"], memory=memory)
                        else:
                            sol = _solve(ctrl, target, s, prev_u, run, r, fallback=ctrls["afm"], memory=memory)
                        if truth is not None:
                            r["true_mean_um"][k, j] = float(truth.true_mean(s, sol.u))
                            r["true_std_um"][k, j] = math.sqrt(float(truth.true_var(s, sol.u)))
                        m, _ = rec.move(b, sol.u, trial=k, target_um=target, controller=name)
                        r["reached_um"][k, j] = m.t_um
                        if memory is not None:
                            memory = afm.memory.step(memory, b.state[1:])
                        last = direction.after_move(last, s[1:], b.state[1:])
                        r["predicted_um"][k, j] = sol.predicted_um
                        r["predicted_std_um"][k, j] = sol.predicted_std_um
                        r["solve_time_s"][k, j] = sol.solve_time_s
                        r["q_um"][k, j] = sol.q
                        r["status"][k][j] = sol.status
                        r["choice"][k][j] = sol.choice
                        if sol.vs_baseline is not None:
                            r["prob_quieter_than_afm"][k, j] = sol.vs_baseline.prob_quieter
                            r["credibly_quieter_than_afm"][k, j] = float(sol.vs_baseline.credible)
                        prev_u = sol.u
                        pr.step(info=f"{name} trial {k + 1} target {target:g} µm")
            res[name] = r
    run.timings_s["incremental"] = time.perf_counter() - t0
    return {"targets_um": targets, "trials": T, "controllers": res}


def _solve(ctrl, target: float, s: np.ndarray, prev_u, run: _Run, r: dict, fallback,
           memory: np.ndarray | None = None) -> ControlResult:
    """Solve with a warm start; on failure retry cold, then fall back to the AFM command (counted).

    With ``memory`` (the hysteresis play states before the move) both controllers meet the
    target with the loop (:class:`~microctl.control.memory.MemoryCompensated`)."""
    kw = {} if memory is None else {"memory": memory}
    if memory is not None:
        ctrl, fallback = with_memory(ctrl, run.afm), with_memory(fallback, run.afm)
    for u_init in (prev_u, None):
        try:
            return ctrl.solve(float(target), s, u_init=u_init, **kw)
        except SolveError as exc:
            err = exc
    r["fallbacks"] += 1
    run.say(f"experiment: {ctrl.name} could not solve {target:g} µm ({err}); the AFM command was used")
    return fallback.solve(float(target), s, **kw)


def _sequence_step(ctrl, replan: bool, rest: list[float], s: np.ndarray, plan: Any, run: _Run, r: dict,
                   fallback, memory: np.ndarray | None = None) -> tuple[ControlResult, Any]:
    """The next move of a sequence controller over the remaining targets ``rest``, from the state s.

    A re-planning controller (``replan``, e.g. ``eafm_sequence``) plans the whole list at the first move and re-plans the remaining targets
    after every executed move from the measured state, warm-started with the previous plan
    without its executed move (receding horizon): the EAFM's mean and noise depend on the
    measured t_prev (x = [s; u], eq. 3), so each executed command is then on the EAFM-mean
    surface from the state it is executed from, as the move-by-move controllers' are.
    One that does not (e.g. ``oracle_sequence``) plans once and executes its plan: the truth depends on the previous
    state only through q, which the commands fix, so a re-plan would return the same moves.
    Returns the move and what the next call needs (the plan). A failed plan is retried cold,
    then the AFM command is used for this move (counted as a fallback) and the next move plans
    afresh. With ``memory`` (the hysteresis play states before the move) the plans and the
    fallback meet the targets with the loop (:class:`~microctl.control.memory.MemoryCompensated`).
    """
    kw = {} if memory is None else {"memory": memory}
    if memory is not None:
        ctrl, fallback = with_memory(ctrl, run.afm), with_memory(fallback, run.afm)
    if not replan:
        if not plan:
            try:
                plan = ctrl.plan(rest, s, **kw).steps
            except SolveError as exc:
                r["fallbacks"] += 1
                run.say(f"experiment: {ctrl.name} could not plan {rest} µm ({exc}); the AFM command was used")
                return fallback.solve(float(rest[0]), s, **kw), None
            return plan[0], plan[1:]
        return replace(plan[0], solve_time_s=0.0), plan[1:]  # planned at an earlier move
    err: Exception | None = None
    warm = [plan.u[1:]] if plan is not None and len(plan.steps) > 1 else []
    for u_init in (*warm, None):
        try:
            new = ctrl.plan(rest, s, u_init=u_init, **kw)
            return new.steps[0], new
        except SolveError as exc:
            err = exc
    r["fallbacks"] += 1
    run.say(f"experiment: {ctrl.name} could not plan {rest} µm ({err}); the AFM command was used")
    return fallback.solve(float(rest[0]), s, **kw), None


# --------------------------------------------------------------------------------------
# the run
# --------------------------------------------------------------------------------------


def _emulated_config(cfg: ExperimentConfig):
    """Start the in-process emulator and point the serial devices at it."""
    from microctl.backends.emulator import Emulator

    sc = cfg.stage_config
    emu = Emulator(sc, seed=cfg.seeds.training_stage)
    emu.start()
    return emu, emu.pointed_at()


def run_experiment(cfg: ExperimentConfig, out: str | Path, *, quiet: bool = False,
                   backend_factory: BackendFactory | None = None) -> dict:
    """Run the whole experiment and write its outputs into ``out``.

    Parameters
    ----------
    cfg : ExperimentConfig
        Validated (:func:`~microctl.experiments.config.load_experiment_config`).
    out : path
        Output folder (created).
    quiet : bool
        Hide progress and notes on stderr.
    backend_factory : callable, optional
        ``factory(stage_config, seed) -> StageBackend`` (default: :func:`default_backend_factory`).

    Returns
    -------
    dict
        The content of ``results.json``.

    Raises
    ------
    ExperimentInterrupted
        A backend error stopped the run; the logs keep every completed move (the message
        lists them). KeyboardInterrupt is re-raised after the same note on stderr.
    """
    from microctl.experiments import figures, report

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    t_start = time.perf_counter()
    afm = AnalyticForwardModel(cfg.stage_config.stage)
    run = _Run(cfg=cfg, out=out, stage_config=cfg.stage_config, factory=backend_factory or default_backend_factory,
               quiet=quiet, afm=afm)
    report.write_config(out / "config.yaml", cfg)
    try:
        if cfg.emulate:
            run.emulator, run.stage_config = _emulated_config(cfg)
        eafm, train_info = _train(run)
        absolute = _absolute(run, eafm) if cfg.absolute.enabled else None
        incremental = _incremental(run, eafm) if cfg.incremental.enabled else None
    except BackendError as exc:
        raise ExperimentInterrupted(
            f"experiment stopped by a backend error: {exc}; the logs in {out} keep every completed move "
            f"({run.log_summary()})") from None
    except KeyboardInterrupt:
        print(f"microctl: experiment interrupted; the logs in {out} keep every completed move "
              f"({run.log_summary()})", file=sys.stderr)
        raise
    finally:
        for rec in run.recorders.values():
            rec.close()
        if run.shared_backend is not None:
            run.shared_backend.close()
        if run.emulator is not None:
            run.emulator.stop()
    run.timings_s["total"] = time.perf_counter() - t_start
    results = report.build_results(cfg, train_info, absolute, incremental, run.timings_s,
                                   {k: v.path.name for k, v in run.recorders.items()})
    figs = figures.write_figures(out, results, title=f"{Path(cfg.source).name}: ") if cfg.figures else []
    results["figures"] = figs
    report.write_outputs(out, cfg, results)
    return results
