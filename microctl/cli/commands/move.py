"""``microctl move``: solve, command the drivers, read the gauge, log the move (a thin layer over :mod:`microctl.api`)."""

from __future__ import annotations

import argparse
import json
import math
import sys

from microctl.cli.commands._common import add_quiet, int_at_least
from microctl.errors import ConfigError


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add the ``move`` sub-command."""
    p = subparsers.add_parser(
        "move",
        help="move the stage to targets: solve, command the drivers, read the gauge, append to a log",
        description="For each target in order: the optimal control signal (eq. 4) from the stage's state (the "
        "backend's: the simulator starts at the zero state, the serial backend reads where the stage stands at "
        "connect), sent to the drivers; the gauge is read and the move appended to the measurement log (the "
        "format `collect` writes, so the log trains). Prints target, prediction ± predicted std and the measured "
        "pose. Targets the stage cannot reach are refused before anything moves; no command outside the "
        "configured ranges is ever sent. Ctrl-C stops after the current move, whose row is written.",
    )
    p.add_argument("--config", required=True, metavar="STAGE.yaml", help="stage config (its backend is driven)")
    p.add_argument("--model", required=True, metavar="MODEL.npz", help="residual model from `microctl train`")
    which = p.add_mutually_exclusive_group(required=True)
    which.add_argument("--target", type=float, metavar="T_UM", help="target tool pose (µm)")
    which.add_argument("--targets", metavar="T1,T2,..", help="targets (µm), moved to one after the other")
    p.add_argument("--log", required=True, metavar="LOG.csv",
                   help="measurement log the moves are appended to (created if missing)")
    p.add_argument("--r-e", default=None, metavar="R", help="noise summary r_e of eq. 4 (default: as `solve`)")
    p.add_argument("--kappa", type=float, default=None, help="standard normal quantile of noise_quantile")
    p.add_argument("--learn", action="store_true",
                   help="fold the moves into the model: every --refit-every moves, refit on the whole log and "
                   "continue with the new model, written as a new version MODEL.vK.npz beside --model (recorded "
                   "in MODEL.versions.jsonl with the log rows it was trained on)")
    p.add_argument("--update", action="store_true",
                   help="with --learn: also fold each move into the model at once, without a refit (in memory, "
                   "hyperparameters fixed; the next refit supersedes it)")
    p.add_argument("--refit-every", type=int_at_least(1, "at least 1"), default=50, metavar="N",
                   help="moves between refits with --learn (default 50)")
    p.add_argument("--json", action="store_true", help="print one JSON object per move on stdout (JSON lines)")
    add_quiet(p)
    p.set_defaults(func=_run)


def parse_targets(text: str, flag: str = "--targets") -> list[float]:
    """``t1,t2,..`` (µm) as a list of finite floats; ConfigError naming the bad value."""
    out = []
    for k, part in enumerate(text.split(",")):
        try:
            v = float(part.strip())
        except ValueError:
            raise ConfigError(f"{flag} {text!r}: target {k + 1} = {part.strip()!r} is not a number") from None
        if not math.isfinite(v):
            raise ConfigError(f"{flag} {text!r}: target {k + 1} = {part.strip()!r} is not finite")
        out.append(v)
    return out


def controller_settings(args: argparse.Namespace):
    """``ControllerSettings`` from ``--r-e`` / ``--kappa`` (None: the defaults); ConfigError naming the option."""
    from microctl.control.settings import ControllerSettings
    from microctl.util.fields import SettingError

    kw = {k: v for k, v in (("r_e", args.r_e), ("kappa", args.kappa)) if v is not None}
    try:
        return ControllerSettings(**kw)
    except SettingError as exc:
        raise ConfigError(f"--{exc.field.replace('_', '-')}: {exc.reason}") from None


def _run(args: argparse.Namespace) -> int:
    from microctl import api
    from microctl.errors import UnreachableTargetError
    from microctl.util.io import to_jsonable

    if args.update and not args.learn:
        raise ConfigError("--update needs --learn (it folds the moves into the model the learner keeps)")
    targets = parse_targets(args.targets) if args.targets is not None else [args.target]
    if args.target is not None and not math.isfinite(args.target):
        raise ConfigError(f"--target {args.target!r} is not a finite number")
    stage = api.load_stage(args.config)
    ctl = api.Controller(stage, args.model, controller_settings(args))
    with api.Operator(ctl, stage.open_backend(), log=args.log) as op:
        learner = (api.Learner(op, args.model, every=args.refit_every, update=args.update)
                   if args.learn else None)
        for note in op.backend.notes:
            if not args.quiet:
                print(f"move: {note}", file=sys.stderr)
        lo, hi = ctl.reachable_interval(op.state)
        bad = [t for t in targets if not lo <= t <= hi]
        if bad:  # before anything moves
            raise UnreachableTargetError(f"target {bad[0]:g} µm is unreachable from the stage's state "
                                         f"{op.state.round(6).tolist()}: the EAFM reaches [{lo:.6g}, {hi:.6g}] µm; "
                                         "nothing was moved")
        if not args.json:
            print(f"{'seq':>5} {'target µm':>10} {'predicted µm':>13} {'± std µm':>9} {'measured µm':>12} "
                  f"{'error µm':>9}")
        for t in targets:
            rec = op.move(t)
            if args.json:
                print(json.dumps(to_jsonable(rec.to_dict(stage))))
            else:
                print(f"{rec.seq:>5} {rec.target_um:>10.4f} {rec.predicted_um:>13.4f} {rec.predicted_std_um:>9.4f} "
                      f"{rec.measured_um:>12.4f} {rec.error_um:>9.4f}")
            sys.stdout.flush()
            new = learner.after_move(rec) if learner is not None else None
            if new is not None and not args.quiet:
                print(f"move: refit on the log's {ctl.n_train} moves; continuing with {new}", file=sys.stderr)
        if not args.quiet:
            print(f"move: {op.moves} move(s) on the {stage.config.backend.kind} backend appended to {op.log_path}",
                  file=sys.stderr)
    return 0
