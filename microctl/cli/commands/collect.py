"""``microctl collect``: designed training moves on the configured backend → measurement log."""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

from microctl.backends import make_backend
from microctl.backends.collect import run_collect
from microctl.cli.commands._common import add_quiet, add_seed, check_output_file, target_range
from microctl.control.refine import check_target_range, refinement_commands
from microctl.errors import ConfigError
from microctl.measurement.design import DEFAULT_DESIGN, DESIGNS, training_moves
from microctl.models.afm import AnalyticForwardModel
from microctl.models.eafm import EAFM
from microctl.stage.config import load_stage_config
from microctl.util.atomic import output_lock


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add the ``collect`` sub-command."""
    p = subparsers.add_parser(
        "collect",
        help="designed training moves on the configured backend, written as a measurement log",
        description="Run n training moves on the backend the stage config names, writing one log row per "
        "move. The default 'covering_still' design mixes space-filling poses, moves holding one or two "
        "actuators still and poses with actuators at their range limits (faces and edges of the workspace), "
        "and every 20th move sends the previous command again (it reads the noise floor; 'covering' is the "
        "same without them); "
        "'space_filling' is the paper's design (scrambled Sobol points in a state-spreading order). "
        "With --refine MODEL.npz the moves are chosen by that trained model instead: episodes from the zero "
        "state to random targets, each move the candidate optimal pose whose noise the model is least sure "
        "of (docs/experiments.md, Refinement); append them to the model's training log and train again.",
    )
    p.add_argument("--config", required=True, metavar="STAGE.yaml", help="stage config")
    p.add_argument("-n", type=int, default=125, help="number of moves (default 125, as in the paper)")
    add_seed(p, "seed of the move design, or of the refinement's targets (default 0)")
    p.add_argument("--design", choices=DESIGNS, default=None,
                   help=f"training design (default {DEFAULT_DESIGN}; see docs/experiments.md)")
    p.add_argument("--refine", metavar="MODEL.npz",
                   help="choose the moves with this trained model of the stage (not with --design)")
    p.add_argument("--target-range", metavar="LO,HI", type=target_range,
                   help="with --refine: the targets of its episodes, µm (default: every reading the stage can reach)")
    p.add_argument("-o", "--out", required=True, metavar="LOG.csv",
                   help="measurement log to write (an existing one is refused unless --force or --append)")
    grp = p.add_mutually_exclusive_group()
    grp.add_argument("--force", action="store_true",
                     help="replace an existing log (the old one stays whole until the new one is complete)")
    grp.add_argument("--append", action="store_true",
                     help="add the moves to an existing log of this stage (seq and time_s continue)")
    add_quiet(p)
    p.set_defaults(func=_run)


def _refinement(args: argparse.Namespace, afm: AnalyticForwardModel):
    """``(make_moves, note)``: ``make_moves(backend)`` gives the ``--refine`` moves (None without it)."""
    if args.refine is None:
        if args.target_range is not None:
            raise ConfigError("--target-range: only with --refine MODEL.npz (a design has no targets)")
        return None, ""
    if args.design is not None:
        raise ConfigError(f"--design {args.design} and --refine {args.refine}: choose one (a design, or the moves "
                          "a trained model chooses)")
    eafm = EAFM(afm, args.refine)  # refuses a model trained for another stage
    targets = check_target_range(eafm, args.target_range, "--target-range")

    def make_moves(backend):
        return refinement_commands(eafm, args.n, targets, args.seed, lambda: backend.state)

    return make_moves, f" chosen by {args.refine} (targets {targets[0]:g} to {targets[1]:g} µm)"


def _write_mode(args: argparse.Namespace) -> str:
    """How the log is opened: a new file, ``--force`` over an old one, ``--append`` to it."""
    exists = os.path.lexists(args.out)
    if args.append:
        if not exists:
            raise ConfigError(f"-o {args.out}: --append needs an existing log, and there is none; drop --append")
        if not Path(args.out).is_file():
            raise ConfigError(f"-o {args.out}: is not a regular file; --append needs a measurement log")
        return "append"
    if exists:
        if not args.force:
            raise ConfigError(f"-o {args.out}: the file exists; refusing to overwrite it (give --force to replace it, "
                              "--append to add the moves to it, or choose another file name)")
        return "replace" if Path(args.out).is_file() else "write"
    return "write"


def _run(args: argparse.Namespace) -> int:
    if args.n < 1:
        print(f"microctl: error: -n must be at least 1, got {args.n}", file=sys.stderr)
        return 2
    check_output_file(args.out, "-o", {"the stage config --config": args.config})
    config = load_stage_config(args.config)
    with output_lock(args.out, "-o"):  # a second collect to the same file is refused, not interleaved
        mode = _write_mode(args)
        afm = AnalyticForwardModel(config.stage)
        make_moves, chosen = _refinement(args, afm)
        if make_moves is None:
            moves = training_moves(afm, args.design or DEFAULT_DESIGN, args.n, args.seed)
        with make_backend(config) as backend:
            for note in backend.notes:
                if not args.quiet:
                    print(f"collect: {note}", file=sys.stderr)
            if make_moves is not None:
                moves = make_moves(backend)
            n = run_collect(backend, moves, args.out, quiet=args.quiet, mode=mode, total=args.n)
    print(f"collect: {n} moves{chosen} on the {config.backend.kind} backend written to {args.out}")  # the result: stdout
    return 0
