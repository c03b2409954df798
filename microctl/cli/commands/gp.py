"""``microctl gp fit`` and ``microctl gp predict``: the VHGPR trainer on any CSV table.

    microctl gp fit DATA.csv --x COL[,COL..] --y COL -o/--out GP.npz [--restarts N] [--seed S] [--bias] [--quiet]
    microctl gp predict GP.npz DATA.csv -o/--out PRED.csv

(``--output`` is accepted as a hidden alias of ``--out``.)

``predict`` writes the columns ``mean,var`` (var includes the input-dependent noise), one
row per input row, in the same order; it reads the input columns by the names stored in
the model.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

from microctl.cli.commands._common import (
    add_quiet,
    add_seed,
    check_output_file,
    int_at_least,
)
from microctl.errors import DataError, MicroctlError
from microctl.util.atomic import write_text_atomic
from microctl.util.progress import Progress
from microctl.util.tabular import read_table


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add ``gp`` with its sub-commands ``fit`` and ``predict``."""
    gp = subparsers.add_parser(
        "gp",
        help="variational heteroscedastic GP (VHGPR) on any table",
        description="Fit a variational heteroscedastic GP to CSV columns, or predict with one.",
    )
    sub = gp.add_subparsers(dest="gp_command", metavar="SUBCOMMAND", parser_class=type(gp))
    gp.set_defaults(func=lambda args: _missing_subcommand(gp))

    fit = sub.add_parser("fit", help="fit a VHGPR to columns of a CSV file",
                         description="Fit a VHGPR (maximise the MV bound) and write the model as .npz.")
    fit.add_argument("data", type=Path, metavar="DATA.csv", help="CSV file with a header row")
    fit.add_argument("--x", required=True, metavar="COL[,COL..]", help="input column(s), comma-separated")
    fit.add_argument("--y", required=True, metavar="COL", help="output column")
    _add_out(fit, "GP.npz", "model file to write")
    fit.add_argument("--restarts", type=int_at_least(1, "at least 1", MAX_RESTARTS), default=2, metavar="N",
                     help=f"optimisation runs in total, the first from a homoscedastic GP (default 2, at most "
                     f"{MAX_RESTARTS})")
    add_seed(fit, "seed of the restarts (default 0)")
    fit.add_argument("--bias", action="store_true", help="add a constant term to both kernels")
    add_quiet(fit)
    fit.set_defaults(func=_fit)

    pred = sub.add_parser("predict", help="predictive mean and variance of y for each row",
                          description="Write mean,var of the predictive distribution of y for each row.")
    pred.add_argument("model", type=Path, metavar="GP.npz", help="model written by 'gp fit'")
    pred.add_argument("data", type=Path, metavar="DATA.csv", help="CSV file with the model's input columns")
    _add_out(pred, "PRED.csv", "CSV file to write")
    pred.set_defaults(func=_predict)


def _add_out(parser: argparse.ArgumentParser, metavar: str, help_text: str) -> None:
    """``-o/--out FILE`` (required), as every other command; ``--output`` is a hidden alias
    kept for scripts written before the name was made consistent."""
    group = parser.add_mutually_exclusive_group(required=True)
    group.add_argument("-o", "--out", type=Path, metavar=metavar, help=help_text)
    group.add_argument("--output", dest="out", type=Path, help=argparse.SUPPRESS)


def _missing_subcommand(parser: argparse.ArgumentParser) -> int:
    parser.print_usage(sys.stderr)
    print("microctl gp: error: choose a sub-command: fit or predict", file=sys.stderr)
    return 2


#: Fewest rows ``gp fit`` accepts (a GP's hyperparameters cannot be learned from fewer; as ``train``).
MIN_FIT_ROWS = 5

#: Most optimisation runs ``gp fit --restarts`` may ask for (as ``train --restarts``).
MAX_RESTARTS = 100


def _fit(args: argparse.Namespace) -> int:
    from microctl.gp.vhgpr import VHGPR

    x_cols = [c.strip() for c in args.x.split(",")]
    if not all(x_cols):
        raise DataError(f"--x '{args.x}': empty column name in the list")
    if len(set(x_cols)) != len(x_cols):
        raise DataError(f"--x '{args.x}': a column is named twice")
    y_col = args.y.strip()
    if y_col in x_cols:
        raise DataError(f"--y '{y_col}' is also an input column in --x")
    check_output_file(args.out, "-o", {"the data file DATA.csv": args.data})
    table = read_table(args.data, min_rows=MIN_FIT_ROWS)
    from microctl.models.training import MAX_TRAIN_ROWS

    if len(table.rows) > MAX_TRAIN_ROWS:
        raise DataError(f"{args.data}: {len(table.rows)} rows; the VHGPR is fitted to at most {MAX_TRAIN_ROWS} (its "
                        "cost grows as rows³); fit a subsample")
    X = table.numeric_columns(x_cols)
    y = table.numeric(y_col)
    with Progress(1, "gp fit", quiet=args.quiet) as progress:
        try:
            model = VHGPR(n_restarts=args.restarts, random_state=args.seed, bias=args.bias).fit(X, y)
        except DataError as exc:
            raise DataError(f"{args.data}: {exc}") from None
        progress.step(info=f"bound {model.bound:.4g}")
    model = dataclasses.replace(model, x_names=tuple(x_cols), y_name=y_col)
    model.save(args.out)
    info = model.info
    print(f"fitted VHGPR to {X.shape[0]} rows of {args.data} ({', '.join(x_cols)} -> {y_col})")
    print(f"  bound {model.bound:.6g}   runs {info['restarts_tried']} ({info['restarts_failed']} failed)"
          f"   iterations {info['iterations']}   time {info['time_s']:.2f} s")
    print(f"  wrote {args.out}")
    return 0


def _predict(args: argparse.Namespace) -> int:
    from microctl.gp.vhgpr import FittedVHGPR

    check_output_file(args.out, "-o", {"the model file GP.npz": args.model, "the data file DATA.csv": args.data})
    model = FittedVHGPR.load(args.model)
    if not model.x_names:
        raise DataError(f"{args.model}: the model does not record its input column names")
    table = read_table(args.data, min_rows=1)
    X = table.numeric_columns(list(model.x_names))
    pred = model.predict(X)
    text = "mean,var\n" + "".join(f"{float(m)!r},{float(v)!r}\n" for m, v in zip(pred.y_mean, pred.y_var))
    try:
        write_text_atomic(args.out, text)
    except OSError as exc:  # the folder was checked: this is the machine (full disk, I/O error), exit 1
        raise MicroctlError(f"{args.out}: cannot write: {exc.strerror or exc}") from None
    return 0


__all__ = ["register"]
