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
    _check_enough_plausible(args, cfg, set_aside, implausible)
    from microctl.measurement.scale import check_spread
    from microctl.models.afm import AnalyticForwardModel

    keep = ~set_aside
    check_spread(args.log, data.t[keep], data.u[keep], AnalyticForwardModel(cfg.stage))  # mm, nm, another stage
    if implausible and not args.quiet:
        for r in implausible[:NOTES_SHOWN]:
            print(f"diagnose: note: {args.log}: row {r.row + 2}, {r.column}: {r.message}; set aside as an outlier",
                  file=sys.stderr)
        if len(implausible) > NOTES_SHOWN:
            print(f"diagnose: note: {args.log}: {len(implausible) - NOTES_SHOWN} more rows set aside as outliers "
                  "(report.md lists them)", file=sys.stderr)
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
        figures = [out / name for name in report.get("figures", {}).get("files", [])]
        print("wrote " + ", ".join(str(p) for p in [out / "report.json", out / "report.md", out / "extended.yaml",
                                                    *figures]))
    return 0


#: How many implausible rows ``diagnose`` names one by one on stderr.
NOTES_SHOWN = 5


def _check_enough_plausible(args: argparse.Namespace, cfg, set_aside, implausible) -> None:
    """Refuse (DataError, exit 2) a log with fewer plausible rows than a diagnosis needs.

    Such a log is not of this stage: another geometry, or readings in other units.
    """
    from microctl.diagnosis.data import MIN_ROWS
    from microctl.errors import DataError

    kept = int(len(set_aside) - set_aside.sum())
    if kept >= MIN_ROWS:
        return
    first = implausible[0] if implausible else None
    example = f" (e.g. row {first.row + 2}, {first.column}: {first.message})" if first is not None else ""
    raise DataError(
        f"{args.log}: {len(implausible)} of {len(set_aside)} rows are implausible for the stage '{cfg.stage.name}' of "
        f"{args.config}{example}; {kept} remain and a diagnosis needs at least {MIN_ROWS}: is it a log of another "
        "stage, or in other units (t and q in µm)?")
