"""``microctl diagnose LOG.csv --config STAGE.yaml [--holdout LOG2.csv] --out DIR``.

Answers the four questions of docs/diagnosis.md (show, name, extend, gain) and
writes DIR/report.json, DIR/report.md, the figures and DIR/extended.yaml.
"""

from __future__ import annotations

import argparse
import sys

from microctl.cli.commands._common import add_quiet, add_seed, check_output_dir
from microctl.stage.config import load_stage_config


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add the ``diagnose`` command."""
    p = subparsers.add_parser("diagnose", help="find what the stage model gets wrong, name the cause, extend the model",
                              description="Find what the stage model gets wrong, name the physical cause, write the "
                              "extended model and measure the gain (docs/diagnosis.md).")
    p.add_argument("log", help="measurement log (CSV, docs/measurement-log.md)")
    p.add_argument("--config", required=True, help="stage YAML file the data is compared with")
    p.add_argument("--holdout", help="second measurement log for the held-out gain (default: 5-fold cross-validation)")
    p.add_argument("--out", required=True, help="output directory (created)")
    add_seed(p, "seed of the folds and GP fits (default 0)")
    p.add_argument("--no-gp", action="store_true", help="leave the GP variants out of the gain (faster)")
    add_quiet(p)
    p.set_defaults(func=_run)


#: What ``diagnose`` writes into ``--out`` (an input there under one of these names is refused).
OUTPUTS = ("report.json", "report.json.tmp", "report.md", "extended.yaml", "residuals.png", "causes.png", "gain.png")


def _run(args: argparse.Namespace) -> int:
    from microctl.diagnosis import data_from_log, run_diagnosis, write_outputs
    from microctl.diagnosis.data import read_for_diagnosis
    from microctl.measurement.log import read_log
    from microctl.util.progress import Progress

    cfg = load_stage_config(args.config)
    # rows no stage can have produced (a corrupt cell) are outliers to name, not a reason to stop
    data, set_aside, implausible = read_for_diagnosis(args.log, cfg.stage)
    if implausible and not args.quiet:
        for r in implausible:
            print(f"diagnose: note: {args.log}: row {r.row + 2}, {r.column}: {r.message}; set aside as an outlier",
                  file=sys.stderr)
    holdout = None
    if args.holdout:
        holdout = data_from_log(read_log(args.holdout, cfg.stage), cfg.stage)
    out = check_output_dir(args.out, "--out", {"the measurement log LOG.csv": args.log,
                                              "the stage config --config": args.config,
                                              "the held-out log --holdout": args.holdout}, OUTPUTS)
    with Progress(2 * 20 + 5, "diagnose (fits)", quiet=args.quiet) as prog:
        diag = run_diagnosis(cfg, data, holdout=holdout, seed=args.seed, gp=not args.no_gp,
                             progress=lambda info: prog.step(1, info), set_aside=set_aside)
    report = write_outputs(diag, out)
    if not args.quiet:
        from microctl.diagnosis.report import summary_lines

        for line in summary_lines(report):
            print(line)
        print(f"wrote {out / 'report.json'}, {out / 'report.md'}, {out / 'extended.yaml'}", file=sys.stdout)
    return 0
