"""``microctl train``: fit the heteroscedastic GP to the AFM residual of a measurement log (eq. 3)."""

from __future__ import annotations

import argparse
import sys
import time

from microctl.afm import AnalyticForwardModel
from microctl.commands._common import add_quiet, add_seed, check_output_file
from microctl.config import load_stage_config
from microctl.errors import ConfigError
from microctl.measurement_log import read_log
from microctl.training import residual_dataset, train_residual_model

#: Fewest log rows a residual fit accepts.
MIN_ROWS = 5


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add the ``train`` sub-command."""
    p = subparsers.add_parser(
        "train",
        help="fit the heteroscedastic GP to the AFM residual of a measurement log",
        description="Fit the VHGPR to y = t' - AFM t(u) with x = [s_prev; u] (paper eq. 3) from a "
        "measurement log; the model file records the stage geometry and is refused for another.",
    )
    p.add_argument("log", metavar="LOG.csv", help="measurement log")
    p.add_argument("--config", required=True, metavar="STAGE.yaml", help="stage config")
    p.add_argument("-o", "--out", required=True, metavar="MODEL.npz", help="model file to write")
    p.add_argument("--restarts", type=int, default=2, metavar="N", help="optimisation runs (default 2)")
    add_seed(p, "seed of the restarts (default 0)")
    add_quiet(p)
    p.set_defaults(func=_run)


def _run(args: argparse.Namespace) -> int:
    if args.restarts < 1:
        raise ConfigError(f"--restarts must be at least 1, got {args.restarts}")
    check_output_file(args.out, "-o", {"the measurement log LOG.csv": args.log, "the stage config --config": args.config})
    config = load_stage_config(args.config)
    afm = AnalyticForwardModel(config.stage)
    log = read_log(args.log, config.stage, min_rows=MIN_ROWS)
    data = residual_dataset(log, afm)
    note = afm.dynamic_corrections_note()
    if note:
        print(f"train: note: {note}", file=sys.stderr)
    t0 = time.perf_counter()
    if not args.quiet and sys.stderr.isatty():
        print(f"train: fitting the VHGPR to {len(data.y)} residuals ({args.restarts} run(s))...", file=sys.stderr)
    model = train_residual_model(data, afm, n_restarts=args.restarts, seed=args.seed)
    model.save(args.out)
    if not args.quiet:
        print(f"train: {len(data.y)} rows, MV bound {model.bound:.4g}, {time.perf_counter() - t0:.1f} s; "
              f"model for stage '{config.stage.name}' written to {args.out}", file=sys.stderr)
    return 0
