"""``microctl solve``: the optimal control signal for one target (paper eq. 4) beside the AFM baseline."""

from __future__ import annotations

import argparse
import math
import sys

import numpy as np

from microctl.control.controller import (
    AFMController,
    ControllerSettings,
    OptimalController,
    with_baseline,
)
from microctl.control.memory import with_memory
from microctl.control.noise_summaries import R_E_SUMMARIES
from microctl.control.sequence_objectives import SEQUENCE_OBJECTIVES
from microctl.errors import ConfigError, UnreachableTargetError
from microctl.models.afm import (
    T_PLAUSIBLE_FACTOR,
    AnalyticForwardModel,
    plausible_t_bound_um,
)
from microctl.models.eafm import EAFM
from microctl.stage.config import load_stage_config
from microctl.util.io import print_json


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add the ``solve`` sub-command."""
    p = subparsers.add_parser(
        "solve",
        help="optimal control signal for one target, beside the AFM baseline",
        description="Minimise 1 - exp(-r_e(s, u)) subject to the EAFM-predicted tool pose = target and "
        "every actuator in range (paper eq. 4), from the given state; print u*, q*, the predicted pose "
        "mean and std, IPOPT status and solve time, and the AFM baseline's u and predicted std.",
    )
    p.add_argument("--config", required=True, metavar="STAGE.yaml", help="stage config")
    p.add_argument("--model", required=True, metavar="MODEL.npz", help="residual model from `microctl train`")
    which = p.add_mutually_exclusive_group(required=True)
    which.add_argument("--target", type=float, metavar="T_UM", help="target tool pose (µm)")
    which.add_argument("--targets", metavar="T1,T2,..",
                       help="a list of targets (µm) reached in sequence: the sequence-optimal commands (one NLP over "
                       "the whole list, minimising the cumulative r_e; docs/controller.md, Sequence control)")
    p.add_argument("--state", default=None, metavar="t,q1,..",
                   help="state s = [t; q] before the move, comma-separated µm (default: zero state)")
    d = ControllerSettings()
    p.add_argument("--r-e", default=d.r_e, choices=R_E_SUMMARIES.names(),
                   help=f"noise summary r_e of eq. 4 (default {d.r_e}: the upper quantile of the predicted noise "
                   "variance, cautious where the noise model is uncertain; see docs/controller.md)")
    p.add_argument("--kappa", type=float, default=d.kappa,
                   help=f"standard normal quantile of noise_quantile (default {d.kappa:g}: 95 %%)")
    p.add_argument("--sequence-objective", default=d.sequence_objective, choices=SEQUENCE_OBJECTIVES.names(),
                   help=f"with --targets: minimise the sum of the moves' r_e or the worst move's "
                   f"(default {d.sequence_objective})")
    p.add_argument("--json", action="store_true", help="print JSON on stdout")
    p.set_defaults(func=_run)


def parse_state(text: str | None, afm: AnalyticForwardModel) -> np.ndarray:
    """Parse ``--state`` (``t,q1,..``) into shape (n_s,); ConfigError naming the value.

    Each q must lie within its actuator's hardware ``limit_um`` (it may be outside ``range_um``:
    a stage can be left there) and |t| within the bound a measurement log has
    (:func:`~microctl.models.afm.plausible_t_bound_um`).
    """
    if text is None:
        return afm.zero_state()
    parts = [p.strip() for p in text.split(",")]
    names = ", ".join(afm.state_names)
    if len(parts) != afm.n_s:
        raise ConfigError(f"--state {text!r}: {len(parts)} value(s), expected {afm.n_s} ({names})")
    out = np.empty(afm.n_s)
    for k, (p, name) in enumerate(zip(parts, afm.state_names)):
        try:
            out[k] = float(p)
        except ValueError:
            raise ConfigError(f"--state {text!r}: {name} = {p!r} is not a number") from None
        if not math.isfinite(out[k]):
            raise ConfigError(f"--state {text!r}: {name} = {p!r} is not finite")
    for a, q in zip(afm.stage.actuators, out[1:]):
        lo, hi = a.limit_um
        if not lo <= q <= hi:
            raise ConfigError(f"--state {text!r}: {a.name} = {q:g} µm is beyond the actuator's hardware limit "
                              f"[{lo:g}, {hi:g}] µm (limit_um in the stage config); no stage can be there")
    t_max = plausible_t_bound_um(afm.stage)
    if abs(out[0]) > t_max:
        raise ConfigError(f"--state {text!r}: {afm.state_names[0]} = {out[0]:g} µm is implausible: the stage reaches "
                          f"at most |t| = {t_max / T_PLAUSIBLE_FACTOR:.6g} µm and states beyond {T_PLAUSIBLE_FACTOR:g} "
                          "times that are refused")
    return out


def parse_targets(text: str) -> list[float]:
    """Parse ``--targets`` (``t1,t2,..`` µm) into a list; ConfigError naming the bad value."""
    parts = [p.strip() for p in text.split(",")]
    out = []
    for k, p in enumerate(parts):
        try:
            v = float(p)
        except ValueError:
            raise ConfigError(f"--targets {text!r}: target {k + 1} = {p!r} is not a number") from None
        if not math.isfinite(v):
            raise ConfigError(f"--targets {text!r}: target {k + 1} = {p!r} is not finite")
        out.append(v)
    return out


def _run(args: argparse.Namespace) -> int:
    config = load_stage_config(args.config)
    afm = AnalyticForwardModel(config.stage)
    note = afm.dynamic_corrections_note()
    if note:
        print(f"solve: note: {note}", file=sys.stderr)
    state = parse_state(args.state, afm)
    targets = parse_targets(args.targets) if args.targets is not None else None
    if targets is None and not math.isfinite(args.target):
        raise ConfigError(f"--target {args.target!r} is not a finite number")
    eafm = EAFM(afm, args.model)
    if eafm.binding_note:
        print(f"solve: note: {eafm.binding_note}", file=sys.stderr)
    settings = ControllerSettings(r_e=args.r_e, kappa=args.kappa, sequence_objective=args.sequence_objective)
    base_ctrl = AFMController(afm, settings, reporter=eafm)
    _refuse_absurd_targets(afm, [args.target] if targets is None else targets)
    try:
        if targets is not None:
            return _run_sequence(args, afm, eafm, settings, base_ctrl, targets, state)
        if afm.memory.active:  # hysteresis corrections: the play states of a move from the zero state to q
            print("solve: note: stage.corrections has hysteresis; without the command history the play states "
                  "are those of one move from the zero state to the state's q", file=sys.stderr)
            res = with_baseline(eafm, with_memory(OptimalController(eafm, settings), afm).solve(args.target, state),
                                with_memory(base_ctrl, afm), settings.credible_level,
                                memory=afm.memory.step(None, np.asarray(state, dtype=float)[1:]))
        else:
            res = OptimalController(eafm, settings, baseline=base_ctrl).solve(args.target, state)
    except UnreachableTargetError as exc:  # one range, rounded as `stage show` rounds it
        raise UnreachableTargetError(_rounded(str(exc))) from None
    base = res.baseline
    if args.json:
        print_json(_step_dict(afm, eafm, settings, res, base))
        return 0
    _print_single(afm, settings, eafm, res, base, state)
    return 0


def _rounded(message: str) -> str:
    """``message`` with every number of more than 4 decimals rounded to 4 (as ``stage show`` prints)."""
    import re

    return re.sub(r"-?\d+\.\d{5,}(?:e[-+]?\d+)?", lambda m: f"{float(m.group(0)):.4f}", message)


def _refuse_absurd_targets(afm: AnalyticForwardModel, targets: list[float]) -> None:
    """UnreachableTargetError, before any solve, for a target beyond what a log of this stage may hold."""
    bound = plausible_t_bound_um(afm.stage)
    for t in targets:
        if abs(t) > bound:
            lo, hi = afm.t_range()
            raise UnreachableTargetError(
                f"target {t:g} µm is far outside what stage '{afm.stage.name}' reaches (the AFM: [{lo:.4f}, "
                f"{hi:.4f}] µm from the zero state; `microctl stage show`)")


def _step_dict(afm: AnalyticForwardModel, eafm: EAFM, settings: ControllerSettings, res, base) -> dict:
    """The JSON of one move: the EAFM command (eq. 4 or a sequence step) beside the AFM baseline."""
    cmp = res.vs_baseline
    dof = afm.dof
    state = res.state
    return {
        "target_um": res.target_um,
        "state": {n: float(v) for n, v in zip(afm.state_names, state)},
        "u": {n: float(v) for n, v in zip(dof, res.u)},
        "q_um": res.q.tolist(),
        "predicted_um": res.predicted_um,
        "predicted_std_um": res.predicted_std_um,
        "noise_std_um": res.noise_std_um,
        "noise_upper_std_um": res.noise_upper_std_um,
        "bias_std_um": res.bias_std_um,
        "hysteresis_um": res.hysteresis_um,
        "choice": res.choice,
        "objective": res.objective,
        "r_e": settings.r_e,
        "kappa": settings.kappa,
        "credibly_quieter_than_baseline": cmp.credible,
        "vs_baseline": cmp.to_dict(),
        "status": res.status,
        "success": res.success,
        "iterations": res.iterations,
        "solve_time_s": res.solve_time_s,
        "baseline": {
            "controller": "afm",
            "u": {n: float(v) for n, v in zip(dof, base.u)},
            "q_um": base.q.tolist(),
            "predicted_um": base.predicted_um,
            "predicted_std_um": base.predicted_std_um,
            "predicted_by": "eafm",
            "status": base.status,
        },
        "model": {"noise_model": eafm.model.noise_model},
    }


def _print_single(afm: AnalyticForwardModel, settings: ControllerSettings, eafm: EAFM, res, base,
                  state: np.ndarray) -> None:
    cmp = res.vs_baseline
    dof = afm.dof
    units = {"z": "µm"}
    where = ", ".join(f"{n} = {v:g}" for n, v in zip(afm.state_names, state))
    print(f"target {res.target_um:g} µm from the state {where} (µm; the tool pose and actuator positions "
          f"before the move)")
    print(f"{'':22s} {'EAFM (eq. 4)':>14s} {'AFM baseline':>14s}")
    for k, n in enumerate(dof):
        label = f"u_{n} ({units.get(n, 'mrad')})"
        print(f"{label:22s} {res.u[k]:14.6f} {base.u[k]:14.6f}")
    for k, n in enumerate(afm.actuator_names):
        print(f"{n + ' (µm)':22s} {res.q[k]:14.6f} {base.q[k]:14.6f}")
    print(f"{'EAFM predicted (µm)':22s} {res.predicted_um:14.6f} {base.predicted_um:14.6f}")
    print(f"{'EAFM pred. std (µm)':22s} {res.predicted_std_um:14.6f} {base.predicted_std_um:14.6f}")
    print(f"{'  of it, mean unc. (µm)':22s} {res.bias_std_um:14.6f} {'':>14s}  (std of the GP's mean correction "
          "at the command: the predicted bias uncertainty)")
    if res.hysteresis_um:
        print(f"{'  of it, hysteresis (µm)':22s} {res.hysteresis_um:14.6f} {base.hysteresis_um:14.6f}  (the loop's "
              "shift from the play states before the move: stage.corrections' hysteresis)")
    print("(both columns predicted by the EAFM: the AFM baseline's command reaches its AFM target, not "
          "necessarily the EAFM's)")
    verdict = ("credibly quieter than the AFM baseline's" if cmp.credible else
               "NOT credibly quieter than the AFM baseline's: the data do not show it to be more repeatable")
    print(f"noise at the EAFM command: std {res.noise_std_um:.4f} µm (upper {settings.kappa:g}-sigma "
          f"{res.noise_upper_std_um:.4f} µm); {verdict} (P = {cmp.prob_quieter:.3f}, level {cmp.level:g})")
    if res.choice:
        print(f"command: {res.choice}")
    print(f"IPOPT: {res.status}, {res.iterations} iterations, {res.n_starts} start(s), "
          f"{res.solve_time_s * 1e3:.1f} ms; r_e = {settings.r_e}; noise model {eafm.model.noise_model}")


def _run_sequence(args: argparse.Namespace, afm: AnalyticForwardModel, eafm: EAFM, settings: ControllerSettings,
                  base_ctrl: AFMController, targets: list[float], state: np.ndarray) -> int:
    """``--targets``: the sequence-optimal plan, each step beside the AFM baseline from the same state."""
    from microctl.control.sequence import SequenceController

    if afm.memory.active:  # hysteresis corrections: the play states run along the planned commands
        z = afm.memory.step(None, np.asarray(state, dtype=float)[1:])
        plan = with_memory(SequenceController(eafm, settings), afm).plan(targets, state, memory=z)
        base_ctrl = with_memory(base_ctrl, afm)
    else:
        z, plan = None, SequenceController(eafm, settings).plan(targets, state)
    steps = []
    for res in plan.steps:
        res = with_baseline(eafm, res, base_ctrl, settings.credible_level, memory=z)
        steps.append((res, res.baseline))
        z = None if z is None else afm.memory.step(z, res.q)
    out = {
        "targets_um": list(plan.targets_um),
        "state": {n: float(v) for n, v in zip(afm.state_names, state)},
        "sequence_objective": plan.sequence_objective,
        "r_e": settings.r_e,
        "kappa": settings.kappa,
        "r_e_um2": [float(v) for v in plan.r_e_um2],
        "total_r_e_um2": plan.total_r_e_um2,
        "worst_r_e_um2": plan.worst_r_e_um2,
        "status": plan.status,
        "success": plan.success,
        "iterations": plan.iterations,
        "n_starts": plan.n_starts,
        "solve_time_s": plan.solve_time_s,
        "model": {"noise_model": eafm.model.noise_model},
        "steps": [_step_dict(afm, eafm, settings, r, b) for r, b in steps],
    }
    if args.json:
        print_json(out)
        return 0
    where = ", ".join(f"{n} = {v:g}" for n, v in zip(afm.state_names, state))
    what = SEQUENCE_OBJECTIVES[plan.sequence_objective].description
    print(f"targets {', '.join(f'{t:g}' for t in targets)} µm in sequence from the state {where} (µm); "
          f"minimised: {what} (r_e = {settings.r_e})")
    head = (f"{'step':>4} {'target':>8} " + " ".join(f"{'u_' + n:>9}" for n in afm.dof) + " "
            + " ".join(f"{n:>7}" for n in afm.actuator_names)
            + f" {'pred (µm)':>10} {'pred std':>9} {'noise std':>9} {'r_e (µm²)':>10} {'AFM std':>8}  quieter?")
    print(head)
    for k, ((res, base), r) in enumerate(zip(steps, plan.r_e_um2)):
        print(f"{k + 1:>4} {res.target_um:>8g} " + " ".join(f"{v:>9.5f}" for v in res.u) + " "
              + " ".join(f"{v:>7.3f}" for v in res.q)
              + f" {res.predicted_um:>10.5f} {res.predicted_std_um:>9.5f} {res.noise_std_um:>9.5f} {r:>10.3g} "
              f"{base.predicted_std_um:>8.5f}  {'credibly' if res.vs_baseline.credible else 'NOT credibly'} "
              f"(P = {res.vs_baseline.prob_quieter:.3f})")
    print("(pred = the EAFM's predicted pose; AFM std = the EAFM's predicted std at the AFM baseline's command "
          "from the same state; quieter? = credibly quieter than that command)")
    print(f"cumulative r_e {plan.total_r_e_um2:.4g} µm², worst move {plan.worst_r_e_um2:.4g} µm²; IPOPT: "
          f"{plan.status}, {plan.iterations} iterations, {plan.n_starts} start(s), {plan.solve_time_s * 1e3:.1f} ms; "
          f"noise model {eafm.model.noise_model}")
    return 0
