"""``microctl collect``: designed training moves on the configured backend → measurement log."""

from __future__ import annotations

import argparse
import sys

from microctl.backends import make_backend
from microctl.backends.collect import run_collect
from microctl.cli.commands._common import add_quiet, add_seed, check_output_file
from microctl.measurement.design import DEFAULT_DESIGN, DESIGNS, training_moves
from microctl.models.afm import AnalyticForwardModel
from microctl.stage.config import load_stage_config


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add the ``collect`` sub-command."""
    p = subparsers.add_parser(
        "collect",
        help="designed training moves on the configured backend, written as a measurement log",
        description="Run n training moves on the backend the stage config names, writing one log row per "
        "move. The default 'covering' design mixes space-filling poses, moves holding one or two actuators "
        "still and poses with actuators at their range limits (faces and edges of the workspace); "
        "'space_filling' is the paper's design (scrambled Sobol points in a state-spreading order).",
    )
    p.add_argument("--config", required=True, metavar="STAGE.yaml", help="stage config")
    p.add_argument("-n", type=int, default=125, help="number of moves (default 125, as in the paper)")
    add_seed(p, "seed of the move design (default 0)")
    p.add_argument("--design", choices=DESIGNS, default=DEFAULT_DESIGN,
                   help=f"training design (default {DEFAULT_DESIGN}; see docs/experiments.md)")
    p.add_argument("-o", "--out", required=True, metavar="LOG.csv", help="measurement log to write")
    add_quiet(p)
    p.set_defaults(func=_run)


def _run(args: argparse.Namespace) -> int:
    if args.n < 1:
        print(f"microctl: error: -n must be at least 1, got {args.n}", file=sys.stderr)
        return 2
    check_output_file(args.out, "-o", {"the stage config --config": args.config})
    config = load_stage_config(args.config)
    afm = AnalyticForwardModel(config.stage)
    moves = training_moves(afm, args.design, args.n, args.seed)
    with make_backend(config) as backend:
        for note in backend.notes:
            if not args.quiet:
                print(f"collect: {note}", file=sys.stderr)
        n = run_collect(backend, moves, args.out, quiet=args.quiet)
    if not args.quiet:
        print(f"collect: {n} moves on the {config.backend.kind} backend written to {args.out}", file=sys.stderr)
    return 0
