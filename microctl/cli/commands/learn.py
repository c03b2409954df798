"""``microctl learn``: a designed log, then refinement rounds, training between (:func:`microctl.api.learn`)."""

from __future__ import annotations

import argparse
import os
import sys
import time

from microctl.cli.commands._common import add_quiet, add_seed, check_output_file, int_at_least, target_range
from microctl.control.refine import REFINE_SHARE, ROUND_MOVES, check_target_range, learning_rounds
from microctl.errors import ConfigError
from microctl.measurement.design import DEFAULT_DESIGN, DESIGNS
from microctl.util.atomic import output_lock

#: Moves of a learning run unless ``-n`` says otherwise (120 designed, 2 refinement rounds).
DEFAULT_MOVES = 200


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add the ``learn`` sub-command."""
    p = subparsers.add_parser(
        "learn",
        help="learn a stage: designed moves, then refinement rounds chosen by the model, training between",
        description=f"Run n moves on the backend the stage config names and train the residual model on them, "
        f"in rounds: the first moves are a design ('collect'), a model is trained on them ('train'), then "
        f"{int(REFINE_SHARE * 100)} % of the moves, in rounds of {ROUND_MOVES}, are chosen by the model where it "
        "is least sure of the optimum ('collect --refine --append'), each round followed by training on "
        "everything. Every move goes to the log as it is made; the model file is written after every fit. "
        "The bench measures this against collect + train on the same number of moves (docs/experiments.md, "
        "Refinement).",
    )
    p.add_argument("--config", required=True, metavar="STAGE.yaml", help="stage config")
    p.add_argument("-n", type=int_at_least(5, "at least 5 (a model needs 5 moves to train on)", 20_000),
                   default=DEFAULT_MOVES,
                   help=f"moves in all (default {DEFAULT_MOVES}; below {int(ROUND_MOVES / REFINE_SHARE)} there is "
                   "no refinement round)")
    add_seed(p, "seed of the design and of the refinement targets (default 0)")
    p.add_argument("--design", choices=DESIGNS, default=DEFAULT_DESIGN,
                   help=f"design of the first moves (default {DEFAULT_DESIGN})")
    p.add_argument("--target-range", metavar="LO,HI", type=target_range,
                   help="targets of the refinement episodes, µm: the range you will work in (default: every "
                   "reading the stage can reach)")
    p.add_argument("--log", required=True, metavar="LOG.csv",
                   help="measurement log to write (an existing one is refused unless --force)")
    p.add_argument("-o", "--out", required=True, metavar="MODEL.npz", help="model file to write")
    p.add_argument("--force", action="store_true",
                   help="replace an existing log (the old one stays whole until the designed moves are written)")
    add_quiet(p)
    p.set_defaults(func=_run)


def _run(args: argparse.Namespace) -> int:
    from microctl import api
    from microctl.cli.commands.train import describe_noise
    from microctl.models.training import noise_summary

    check_output_file(args.log, "--log", {"the stage config --config": args.config})
    check_output_file(args.out, "-o", {"the stage config --config": args.config, "the measurement log --log": args.log})
    if os.path.lexists(args.log) and not args.force:
        raise ConfigError(f"--log {args.log}: the file exists; refusing to overwrite it (give --force to replace it, "
                          "or choose another file name; to add moves to a log use 'collect --refine --append')")
    stage = api.load_stage(args.config)
    targets = check_target_range(stage.afm, args.target_range, "--target-range")  # before any move
    rounds = learning_rounds(args.n)
    designed = f"{args.n - rounds * ROUND_MOVES} designed"
    t0 = time.perf_counter()

    def say(text: str) -> None:
        if not args.quiet:
            print(text, file=sys.stderr)

    with output_lock(args.log, "--log"):
        with stage.open_backend() as backend:
            for note in backend.notes:
                say(f"learn: {note}")
            say(f"learn: {designed} moves, then {rounds} refinement round(s) of "
                f"{ROUND_MOVES}")
            model = api.learn(stage, args.n, args.log, out=args.out, seed=args.seed, design=args.design,
                              target_range_um=targets, backend=backend, replace_log=args.force,
                              quiet=args.quiet, say=say)
    # the result on stdout (progress goes to stderr): shown also with --quiet
    print(f"learn: {args.n} moves ({designed} + {rounds} refinement round(s) of "
          f"{ROUND_MOVES}) on the {stage.config.backend.kind} backend written to {args.log}; model for stage "
          f"'{stage.name}' written to {args.out} ({time.perf_counter() - t0:.1f} s)")
    print(f"learn: {describe_noise(noise_summary(model, stage.afm))}")
    return 0
