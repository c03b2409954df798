"""``microctl train``: fit the heteroscedastic GP to the AFM residual of a measurement log (eq. 3)."""

from __future__ import annotations

import argparse
import sys
import time

from microctl.cli.commands._common import add_quiet, add_seed, check_output_file
from microctl.errors import ConfigError, DataError
from microctl.measurement.log import read_log
from microctl.measurement.scale import check_reading_scale
from microctl.models.afm import AnalyticForwardModel
from microctl.models.floor_check import with_floor_check
from microctl.models.outlier_screen import describe_screen
from microctl.models.noise_inputs import G_INPUTS, G_STARTS
from microctl.models.training import (
    GP_FORMS,
    AUTO_SPARSE_ROWS,
    MAX_TRAIN_ROWS,
    NOISE_MODELS,
    ResidualModelSettings,
    max_train_rows,
    noise_summary,
    residual_dataset,
    train_residual_model,
    uses_sparse,
)
from microctl.stage.config import load_stage_config
from microctl.util.fields import SettingError

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
    d = ResidualModelSettings()
    p.add_argument("--noise-model", choices=NOISE_MODELS, default=d.noise_model,
                   help=f"noise model of the GP (default {d.noise_model}: a noise floor plus per-actuator "
                   "stick-slip as g's prior mean; hgp: the paper's constant prior mean)")
    p.add_argument("--no-linear-trend", dest="linear_trend", action="store_false",
                   help="no affine trend in u in the mean correction (the paper's SE kernel alone)")
    p.add_argument("--se", choices=("auto", "on", "off"), default=d.se,
                   help=f"the mean correction's SE part (default {d.se}: kept only where the data pay for it)")
    p.add_argument("--no-mean-shift", dest="mean_shift", action="store_false",
                   help="no trend in the selected noise sources in the mean correction (the mean shift that "
                   "scatter causes, docs/vhgpr.md)")
    p.add_argument("--g-inputs", choices=tuple(G_INPUTS), default=d.g_inputs,
                   help=f"what the noise GP reads (default {d.g_inputs}: x = [s_prev; u]; actuators: each actuator's "
                   "position and step, docs/vhgpr.md)")
    p.add_argument("--g-start", choices=G_STARTS, default=d.g_start,
                   help=f"where the noise GP's fit starts (default {d.g_start}: the homoscedastic GP; residuals: "
                   "one more run from the log squared residuals, docs/vhgpr.md)")
    p.add_argument("--g-gp", choices=("auto", "on", "off"), default=d.g_gp,
                   help=f"the noise GP beside the noise sources (default {d.g_gp}; auto: with the dictionary noise model "
                   "kept only where the data pay for it; off: the noise is the sources alone, docs/vhgpr.md)")
    p.add_argument("--noise-source", dest="noise_sources", action="append", metavar="NAME",
                   help="name a noise source instead of letting the data select them (repeat for each; a candidate "
                   "such as dq4:sat@4 or a quantity such as dq4 or drx, docs/controller.md; 'none': no source)")
    p.add_argument("--gp", choices=GP_FORMS, default=d.gp,
                   help=f"the GP's form (default {d.gp}: exact up to {AUTO_SPARSE_ROWS} rows, sparse above)")
    p.add_argument("--inducing", type=int, default=d.inducing, metavar="M",
                   help=f"inducing points of the sparse form (default {d.inducing})")
    p.add_argument("--restarts", type=int, default=d.restarts, metavar="N",
                   help=f"optimisation runs (default {d.restarts})")
    add_seed(p, f"seed of the restarts (default {d.seed})")
    add_quiet(p)
    p.set_defaults(func=_run)


def _named_sources(given: list[str] | None) -> tuple[str, ...] | None:
    """``--noise-source`` values as the setting: None when not given, () for ``none`` alone."""
    if given is None:
        return None
    if "none" in given and len(given) > 1:
        raise ConfigError(f"--noise-source: 'none' names no source and cannot go with others, got {given}")
    return () if given == ["none"] else tuple(given)


def _run(args: argparse.Namespace) -> int:
    if args.se == "off" and not args.linear_trend:
        raise ConfigError("--se off needs the linear trend (without the trend and the SE part the mean correction "
                          "would be a constant): drop --no-linear-trend, or use --se auto or on")
    try:
        settings = ResidualModelSettings(noise_model=args.noise_model, linear_trend=args.linear_trend, se=args.se,
                                         restarts=args.restarts, seed=args.seed, gp=args.gp,
                                         inducing=args.inducing, mean_shift=args.mean_shift, g_inputs=args.g_inputs,
                                         g_start=args.g_start, g_gp=args.g_gp,
                                         noise_sources=_named_sources(args.noise_sources))
    except SettingError as exc:  # name the option, not the field
        raise ConfigError(f"--{exc.field.replace('_', '-')}: {exc.reason}") from None
    check_output_file(args.out, "-o", {"the measurement log LOG.csv": args.log, "the stage config --config": args.config})
    config = load_stage_config(args.config)
    afm = AnalyticForwardModel(config.stage)
    log = read_log(args.log, config.stage, min_rows=MIN_ROWS)
    check_reading_scale(log, afm)  # readings in mm, not µm, would train a model of nothing
    if len(log) > max_train_rows(settings):
        hint = ("(the exact GP's cost grows as rows³); use --gp auto or sparse, or train on a subsample of the log"
                if settings.gp == "exact" else "(the sparse GP's memory grows with rows); train on a subsample")
        raise DataError(f"{args.log}: {len(log)} rows; a residual model with --gp {settings.gp} is trained on at most "
                        f"{max_train_rows(settings)} {hint}")
    data = residual_dataset(log, afm)
    note = afm.dynamic_corrections_note()
    if note:
        print(f"train: note: {note}", file=sys.stderr)
    t0 = time.perf_counter()
    if not args.quiet and sys.stderr.isatty():
        form = (f"sparse, {settings.inducing} inducing points" if uses_sparse(len(data.y), settings) else "exact")
        print(f"train: fitting the VHGPR ({form}) to {len(data.y)} residuals ({args.restarts} run(s))...",
              file=sys.stderr)
    try:
        model = train_residual_model(data, afm, settings)
    except DataError as exc:  # e.g. "y is constant": say which file
        raise DataError(f"{args.log}: the AFM residuals of its {len(data.y)} rows: {exc}") from None
    model, check = with_floor_check(model, data)  # a degenerate floor is kept in the model's info
    model.save(args.out)
    # the result on stdout (progress and notes go to stderr): shown also with --quiet
    form = "" if model.posterior_form == "exact" else f" (sparse, {model.X.shape[0]} inducing points)"
    print(f"train: {len(data.y)} rows{form}, bound {model.bound:.4g}, {time.perf_counter() - t0:.1f} s; "
          f"model for stage '{config.stage.name}' written to {args.out}")
    print(f"train: {describe_noise(noise_summary(model, afm))}")
    ggp = model.info.get("noise_selection", {}).get("g_gp")
    if ggp is not None:  # microctl.models.g_gp_selection
        print(f"train: noise GP beside the sources {'kept' if ggp['kept_gp'] else 'dropped'}: it raised the bound by "
              f"{ggp['bound_with_gp'] - ggp['bound_without_gp']:.1f} nats, needed {ggp['penalty']:.1f}")
    screened = describe_screen(model.info.get("noise_selection", {}).get("screened"), log.seq)
    if screened:
        print(f"train: {screened}")
    if check is not None:  # degenerate
        print(f"train: warning: {check.describe()}")
    sel = model.info.get("se_selection")
    if sel is not None:
        print("train: mean correction: affine trend in u"
              + (" plus an SE part" if sel["kept_se"] else "")
              + f" (SE part {'kept' if sel['kept_se'] else 'dropped'}: it raised the bound by "
              f"{sel['bound_with_se'] - sel['bound_affine']:.1f} nats, needed {sel['penalty']:.1f})")
    return 0


def describe_noise(summary: dict) -> str:
    """One line: the noise model; for ``dictionary`` the sources the data selected, for ``physical``
    the floor and per-actuator stick-slip (± standard error)."""
    sel = summary.get("selection")
    named = None if sel is None else sel.get("declared")
    if summary["noise_model"] == "dictionary" and named is not None:  # --noise-source: named, not selected
        src = ", ".join(summary["sources"]) or "none"
        return (f"noise model dictionary: floor std {summary['floor_std_um']:.4f} µm; sources named "
                f"({', '.join(named) or 'none'}), not selected by the data: {src}")
    if summary["noise_model"] == "dictionary" and not summary["sources"]:
        rest = "" if (sel.get("g_gp") or {}).get("kept_gp") is False else "; g's GP models the rest"
        return (f"noise model dictionary: no noise source selected among {sel['candidates']} candidates "
                f"(floor std {summary['floor_std_um']:.4f} µm everywhere{rest})")
    if summary["noise_model"] == "dictionary":
        src = ", ".join(summary["sources"])
        swaps = "; ".join(f"{a} -> {b}" for a, b in sel.get("shape_swaps", []))
        swaps = f" (shapes re-chosen with the other sources in: {swaps})" if swaps else ""
        shift = sel.get("mean_shift")
        shift = (f"; the mean correction has a trend in {', '.join(shift['features'])} (the mean shift that "
                 f"scatter causes)") if shift else ""
        return (f"noise model dictionary: floor std {summary['floor_std_um']:.4f} µm; sources selected by the data "
                f"among {sel['candidates']} candidates: {src}{swaps}{shift}")
    if summary["noise_model"] != "physical":
        return "noise model hgp (the paper's: g ~ GP(mu0, K_g))"
    acts = ", ".join(f"{name} {a['friction_std_per_um']:.3f} ± {a['friction_std_per_um_se']:.3f}"
                     for name, a in summary["actuators"].items())
    return (f"noise model physical: floor std {summary['floor_std_um']:.4f} µm; stick-slip std per µm moved "
            f"(through the AFM's contact sensitivities): {acts}")
