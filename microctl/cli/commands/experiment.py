"""``microctl experiment``: the paper's absolute- and incremental-movement experiments (section IV)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from microctl.cli.commands._common import add_quiet, check_output_dir
from microctl.errors import ConfigError


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add the ``experiment`` sub-command."""
    p = subparsers.add_parser(
        "experiment",
        help="the absolute- and incremental-movement experiments (collect, train, run AFM and EAFM controllers, "
        "statistics, figures, report)",
        description="Run an experiment file: collect the training moves and fit the residual VHGPR (eq. 3), run the "
        "absolute-movement (IV-C) and incremental-movement (IV-D) experiments with the AFM, EAFM (and, on a "
        "simulated stage, oracle) controllers, and write results.json, report.md, config.yaml, the measurement "
        "logs, the model and figures into --out.",
    )
    p.add_argument("experiment", metavar="EXPERIMENT.yaml", help="experiment file (see docs/experiments.md)")
    p.add_argument("--out", metavar="DIR", default=None,
                   help="output folder (default: results/<experiment name> in the current folder); the files a "
                   "previous run wrote there (results.json, report.md, logs, model, figures) are removed first")
    p.add_argument("--seed-offset", type=int, default=0, metavar="K",
                   help="add K (>= 0) to every seed of the file: the same experiment on another draw of every "
                   "random choice (default 0)")
    add_quiet(p)
    p.set_defaults(func=_run)


#: What ``experiment`` writes into ``--out``: an input there under one of these names is refused,
#: and these files left by a previous run are removed before the run starts (nothing else is).
OUTPUTS = ("config.yaml", "training_log.csv", "absolute_log.csv", "incremental_log.csv", "model.npz",
           "results.json", "results.json.tmp", "report.md", "fig5_absolute.png", "fig6_incremental.png")


def clear_previous_run(out: Path) -> list[str]:
    """Remove the files of :data:`OUTPUTS` that a previous run left in ``out``.

    A run that writes fewer files (figures off, no matplotlib, an experiment disabled, an
    interrupted run that never writes results.json) must not leave the previous run's
    figures, logs or results beside its own. Other files in ``out`` are left alone.

    Parameters
    ----------
    out : Path
        The output folder (already checked by :func:`check_output_dir`).

    Returns
    -------
    list of str
        The names removed.

    Raises
    ------
    ConfigError
        One of the names is a folder (exit 2; nothing is removed).
    """
    found = [out / name for name in OUTPUTS if (out / name).exists() or (out / name).is_symlink()]
    for p in found:
        if p.is_dir() and not p.is_symlink():
            raise ConfigError(f"--out {out}: '{p.name}' is a folder, where the command writes a file; "
                              "remove it or choose another folder")
    for p in found:
        p.unlink()
    return [p.name for p in found]


def _run(args: argparse.Namespace) -> int:
    from microctl.experiments.config import load_experiment_config
    from microctl.experiments.runner import run_experiment

    cfg = load_experiment_config(args.experiment)  # everything validated before any move
    if args.seed_offset:
        cfg = cfg.with_seed_offset(args.seed_offset)
    out = Path(args.out) if args.out else Path("results") / Path(args.experiment).stem
    check_output_dir(out, "--out", {"the experiment file": args.experiment, "its stage config": cfg.stage_path},
                     OUTPUTS)
    removed = clear_previous_run(out)
    if removed and not args.quiet:
        print(f"experiment: removed the previous run's {', '.join(removed)} from {out}", file=sys.stderr)
    res = run_experiment(cfg, out, quiet=args.quiet)
    _print_summary(res, out)  # the result on stdout (progress and notes on stderr), also with --quiet
    return 0


def _print_summary(res: dict, out: Path) -> None:
    """The incremental table, the bars met and where the results are, on stdout."""
    inc = res.get("incremental")
    if inc is not None:
        from microctl.experiments.controllers import label as label_of  # as in report.md, the figures

        w = max(len("target (µm)"), *(len(label_of(n)) + len(" VSSE (µm²)") for n in inc["controllers"]))
        print(f"{'target (µm)':{w}s}" + "".join(f"{t:>9g}" for t in inc["targets_um"]))
        for name, c in inc["controllers"].items():
            label = label_of(name)
            print(f"{label + ' MSSE (µm)':{w}s}" + "".join(f"{v:9.3f}" for v in c["msse_um"]))
            print(f"{label + ' VSSE (µm²)':{w}s}" + "".join(f"{v:9.3f}" for v in c["vsse_um2"]))
    bars = res.get("bars", {})
    if bars:
        failed = [k for k, b in bars.items() if not b["passed"]]
        print(f"experiment: bars met {len(bars) - len(failed)}/{len(bars)}"
              + (f" (not met: {', '.join(failed)})" if failed else ""))
    print(f"experiment: results in {out} ({res['timings_s']['total']:.1f} s)")
