"""``microctl diagnose LOG.csv --config STAGE.yaml [--holdout LOG2.csv] --out DIR``.

Answers the four questions of shared/spec/diagnosis.md (show, name, extend, gain) and
writes DIR/report.json, DIR/report.md, the figures and DIR/extended.yaml.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from microctl.commands._common import add_quiet
from microctl.config import load_stage_config
from microctl.errors import DataError


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add the ``diagnose`` command."""
    p = subparsers.add_parser("diagnose", help="find what the stage model gets wrong, name the cause, extend the model")
    p.add_argument("log", help="measurement log (CSV, shared/spec/measurement-log.md)")
    p.add_argument("--config", required=True, help="stage YAML file the data is compared with")
    p.add_argument("--holdout", help="second measurement log for the held-out gain (default: 5-fold cross-validation)")
    p.add_argument("--out", required=True, help="output directory (created)")
    p.add_argument("--seed", type=int, default=0, help="seed of the folds and GP fits (default 0)")
    p.add_argument("--no-gp", action="store_true", help="leave the GP variants out of the gain (faster)")
    add_quiet(p)
    p.set_defaults(func=_run)


def _run(args: argparse.Namespace) -> int:
    from microctl.diagnosis import data_from_log, run_diagnosis, write_outputs
    from microctl.measurement_log import read_log
    from microctl.progress import Progress

    cfg = load_stage_config(args.config)
    data = data_from_log(read_log(args.log, cfg.stage), cfg.stage)
    holdout = None
    if args.holdout:
        holdout = data_from_log(read_log(args.holdout, cfg.stage), cfg.stage)
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise DataError(f"{out}: --out must be a directory, a file is in the way")
    with Progress(2 * 20 + 5, "diagnose (fits)", quiet=args.quiet) as prog:
        diag = run_diagnosis(cfg, data, holdout=holdout, seed=args.seed, gp=not args.no_gp,
                             progress=lambda info: prog.step(1, info))
    report = write_outputs(diag, out)
    if not args.quiet:
        from microctl.diagnosis.report import summary_lines

        for line in summary_lines(report):
            print(line)
        print(f"wrote {out / 'report.json'}, {out / 'report.md'}, {out / 'extended.yaml'}", file=sys.stdout)
    return 0
