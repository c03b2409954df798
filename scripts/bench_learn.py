#!/usr/bin/env python
"""Does learning while operating pay? A stage operated with ``move --learn`` against the frozen model.

For each rig of the hidden-structure families of the repeatability bench
(``scripts/rig_families.py``; the stick-slip family is the structure the default model was
built on, so it is left out unless named):

1. ``collect`` ``--start`` moves (the covering design) on the simulated rig and ``train`` the
   frozen model on them (:func:`microctl.api.train`, ``--restarts``, seed 0);
2. operate the rig for ``--moves`` moves with the public API exactly as ``microctl move
   --learn`` does (:class:`microctl.api.Operator` and :class:`microctl.api.Learner`): targets
   drawn uniformly in [3, 27] µm (seeded), every executed move appended to the log, a refit on
   the whole log every ``--refit-every`` moves (versioned model files); with ``--update`` also
   each move between refits folded into the model at once, as ``move --learn --update`` does;
3. score the frozen model and the last refit the way ``scripts/bench_rigs.py`` scores its
   methods: targets 6, 12, 18, 24 µm in sequence on a fresh copy of the rig, each pose's true
   mean error and true std against the oracle's (the fine search, checked against random
   reaching poses). A rig passes when, at every target, std <= 1.25x the oracle's and
   |true error| <= 0.1 µm.

Usage: ``python scripts/bench_learn.py [--family stroke_patch,light_ball,...] [--rigs 3]
[--start 125] [--moves 1000] [--refit-every 250] [--update] [--restarts 1] [--jobs 2] [--json FILE]
[--markdown FILE]``. Rig k of a family uses seed k (the bench's seeds).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from microctl.cli import one_blas_thread  # noqa: E402

# Before NumPy loads: the workers' numerics on one BLAS thread each, as the command line runs
# them (two threads per worker on two cores oversubscribed them; a user's count wins).
one_blas_thread(os.environ, sys.modules)

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

import bench_rigs  # noqa: E402
import rig_families  # noqa: E402

from microctl import api  # noqa: E402
from microctl.backends.collect import run_collect  # noqa: E402
from microctl.control.controller import AFMController, ControllerSettings, OptimalController  # noqa: E402
from microctl.control.oracle import OracleController  # noqa: E402
from microctl.gp.vhgpr import FittedVHGPR  # noqa: E402
from microctl.measurement.design import training_moves  # noqa: E402
from microctl.models.afm import AnalyticForwardModel  # noqa: E402
from microctl.models.eafm import EAFM  # noqa: E402

#: The families whose noise structure the default model was not written for.
HIDDEN = tuple(f for f in rig_families.FAMILIES if f not in ("clean", "stick_slip"))
#: Operating targets are drawn uniformly in this interval (µm): inside every rig's reach.
OPERATE_RANGE_UM = (3.0, 27.0)


def score(rig, afm: AnalyticForwardModel, model: FittedVHGPR, seed: int) -> list[dict]:
    """The four bench targets in sequence on a fresh copy of the rig (bench_rigs' scoring)."""
    ctrl = OptimalController(EAFM(afm, model), ControllerSettings())
    base = AFMController(afm)
    rows = []
    with rig.stage(seed + 20_000) as stage:
        oracle = OracleController(afm, stage, **bench_rigs.FAMILY_ORACLE)
        prev = None
        for k, target in enumerate(bench_rigs.TARGETS_UM):
            rows.append(bench_rigs._score_target(stage, ctrl, oracle, base, target, stage.state, prev, seed * 10 + k))
            prev = np.asarray(rows[-1]["u"])
            stage.move(prev)
    return rows


def passes(rows: list[dict]) -> bool:
    """Every target within the bench's bars (std <= 1.25x the oracle's, |error| <= 0.1 µm)."""
    return all(t["std_um"] <= bench_rigs.STD_BAR * t["oracle_std_um"] and abs(t["err_um"]) <= bench_rigs.ERR_BAR_UM
               for t in rows)


def run_rig(family: str, seed: int, start: int, moves: int, every: int, restarts: int, update: bool = False) -> dict:
    """Collect, train, operate with learning, score frozen and learned (module docstring)."""
    rig = rig_families.make_family_rig(family, seed)
    stage = api.Stage(rig.config, AnalyticForwardModel(rig.config.stage))
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        log, frozen_path = Path(tmp) / "log.csv", Path(tmp) / "model.npz"
        with rig.stage(seed + 10_000) as sim:
            run_collect(sim, training_moves(stage.afm, "covering", start, seed), log, quiet=True)
        frozen = api.train(log, stage, out=frozen_path, restarts=restarts, seed=0)
        t_train = time.perf_counter() - t0
        targets = np.random.default_rng(seed + 30_000).uniform(*OPERATE_RANGE_UM, size=moves)
        errors, refits = [], []
        with rig.stage(seed + 40_000) as sim, api.Operator(api.Controller(stage, frozen_path), sim, log=log) as op:
            learner = api.Learner(op, frozen_path, every=every, restarts=restarts, seed=0, update=update)
            for t in targets:
                rec = op.move(float(t))
                errors.append(rec.error_um)
                if learner.after_move(rec) is not None:
                    refits.append(len(errors))
        learned = op.controller.eafm.model
        t_operate = time.perf_counter() - t0 - t_train
        rows_frozen = score(rig, stage.afm, frozen, seed)
        rows_learned = score(rig, stage.afm, learned, seed)
    sel = (learned.info.get("noise_selection") or {}).get("selected")
    sel0 = (frozen.info.get("noise_selection") or {}).get("selected")
    err = np.asarray(errors)
    return {"family": family, "seed": seed, "start": start, "moves": moves, "refits_at": refits,
            "frozen": {"targets": rows_frozen, "pass": passes(rows_frozen), "selected": sel0},
            "learned": {"targets": rows_learned, "pass": passes(rows_learned), "selected": sel,
                        # rows of the last fit (a sparse model's X holds its inducing points instead)
                        "n_train": int((learned.info.get("sparse") or {}).get("n", learned.X.shape[0])),
                        "form": learned.posterior_form},
            "operate_rms_error_um": {"first_100": float(np.sqrt(np.mean(err[:100] ** 2))),
                                     "last_100": float(np.sqrt(np.mean(err[-100:] ** 2)))},
            "time_s": {"train": t_train, "operate": t_operate, "total": time.perf_counter() - t0}}


def _worst(rows: list[dict]) -> float:
    return max(t["std_um"] / t["oracle_std_um"] for t in rows)


def table(results: list[dict], families) -> list[dict]:
    """Per family: passes of the frozen and the learned model, worst std ratios, error."""
    out = []
    for fam in families:
        rs = [r for r in results if r["family"] == fam]
        if not rs:
            continue
        wf = [_worst(r["frozen"]["targets"]) for r in rs]
        wl = [_worst(r["learned"]["targets"]) for r in rs]
        out.append({"family": fam, "rigs": len(rs),
                    "frozen_pass": sum(r["frozen"]["pass"] for r in rs),
                    "learned_pass": sum(r["learned"]["pass"] for r in rs),
                    "frozen_worst_ratio_median": float(np.median(wf)), "learned_worst_ratio_median": float(np.median(wl)),
                    "frozen_max_err_um": max(abs(t["err_um"]) for r in rs for t in r["frozen"]["targets"]),
                    "learned_max_err_um": max(abs(t["err_um"]) for r in rs for t in r["learned"]["targets"]),
                    "rms_first_100_um": float(np.median([r["operate_rms_error_um"]["first_100"] for r in rs])),
                    "rms_last_100_um": float(np.median([r["operate_rms_error_um"]["last_100"] for r in rs]))})
    return out


def markdown(rows: list[dict], results: list[dict], header: str, command: str, wall_s: float) -> str:
    lines = ["<!-- generated by scripts/bench_learn.py; do not edit by hand -->", "",
             "# Learning while operating: frozen model against `move --learn`", "", header, "",
             f"Command: `{command}`. Wall time {wall_s:.0f} s.", "",
             "Pass: at every target (6, 12, 18, 24 µm in sequence), true std <= 1.25x the oracle's and "
             "|true error| <= 0.1 µm. Worst ratio: the largest true std / oracle std over the four targets "
             "(median over the family's rigs). RMS error: the measured minus target of the operating "
             "moves, first and last 100 (median over rigs).", "", "<!-- table: learn -->",
             "| family | rigs | frozen pass | learned pass | worst ratio frozen | worst ratio learned "
             "| max \\|err\\| frozen (µm) | max \\|err\\| learned (µm) | RMS first 100 (µm) | RMS last 100 (µm) |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['family']} | {r['rigs']} | {r['frozen_pass']}/{r['rigs']} | {r['learned_pass']}/{r['rigs']} "
                     f"| {r['frozen_worst_ratio_median']:.2f} | {r['learned_worst_ratio_median']:.2f} "
                     f"| {r['frozen_max_err_um']:.3f} | {r['learned_max_err_um']:.3f} "
                     f"| {r['rms_first_100_um']:.3f} | {r['rms_last_100_um']:.3f} |")
    tot_f = sum(r["frozen_pass"] for r in rows)
    tot_l = sum(r["learned_pass"] for r in rows)
    n = sum(r["rigs"] for r in rows)
    lines += ["", f"All families: frozen {tot_f}/{n}, learned {tot_l}/{n}.", "",
              "Noise sources selected per rig (frozen → learned):", ""]
    for res in results:
        lines.append(f"- {res['family']} rig {res['seed']}: {res['frozen']['selected'] or []} → "
                     f"{res['learned']['selected'] or []} ({res['learned']['n_train']} moves, "
                     f"{res['learned']['form']} GP)")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--family", default=",".join(HIDDEN), help=f"comma-separated, of {', '.join(rig_families.FAMILIES)}")
    ap.add_argument("--rigs", type=int, default=3)
    ap.add_argument("--start", type=int, default=125, help="moves the frozen model is trained on")
    ap.add_argument("--moves", type=int, default=1000, help="operating moves")
    ap.add_argument("--refit-every", type=int, default=250)
    ap.add_argument("--update", action="store_true", help="fold each move between refits into the model (move --learn --update)")
    ap.add_argument("--restarts", type=int, default=1)
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--json", metavar="FILE")
    ap.add_argument("--markdown", metavar="FILE")
    args = ap.parse_args(argv)
    fams = tuple(f.strip() for f in args.family.split(",") if f.strip())
    bad = [f for f in fams if f not in rig_families.FAMILIES]
    if bad:
        ap.error(f"unknown family(ies) {bad}; choose from {', '.join(rig_families.FAMILIES)}")
    if min(args.rigs, args.start, args.moves, args.refit_every, args.restarts, args.jobs) < 1:
        ap.error("--rigs, --start, --moves, --refit-every, --restarts and --jobs must be >= 1")
    header = (f"machine: {platform.machine()} {os.cpu_count()} cpu, Python {platform.python_version()}, numpy "
              f"{np.__version__}; families {list(fams)}, {args.rigs} rigs each, start {args.start} moves, "
              f"{args.moves} operating moves, refit every {args.refit_every} (restarts {args.restarts}), "
              f"per-move update {'on' if args.update else 'off'}, jobs {args.jobs}")
    print(header)
    t0 = time.perf_counter()
    jobs = [(f, s) for f in fams for s in range(args.rigs)]
    results = []
    with ProcessPoolExecutor(args.jobs) as ex:
        futs = [ex.submit(run_rig, f, s, args.start, args.moves, args.refit_every, args.restarts,
                          args.update) for f, s in jobs]
        for fu in futs:
            r = fu.result()
            results.append(r)
            print(f"  {r['family']} rig {r['seed']}: frozen {'pass' if r['frozen']['pass'] else 'FAIL'} "
                  f"(worst {_worst(r['frozen']['targets']):.2f}x), learned {'pass' if r['learned']['pass'] else 'FAIL'} "
                  f"(worst {_worst(r['learned']['targets']):.2f}x), {r['time_s']['total']:.0f} s", flush=True)
            if args.json:  # partial results survive an interrupted run
                Path(args.json).write_text(json.dumps({"rigs": results}, indent=1, default=float))
    rows = table(results, fams)
    wall = time.perf_counter() - t0
    print(f"\n{'family':>14}  rigs  frozen pass  learned pass  worst ratio frozen/learned (median)  "
          "max |err| frozen/learned (µm)  RMS error first/last 100 moves (µm)")
    for r in rows:
        print(f"{r['family']:>14}  {r['rigs']:>4}  {r['frozen_pass']:>11}  {r['learned_pass']:>12}  "
              f"{r['frozen_worst_ratio_median']:>17.2f} / {r['learned_worst_ratio_median']:<17.2f}  "
              f"{r['frozen_max_err_um']:>13.3f} / {r['learned_max_err_um']:<13.3f}  "
              f"{r['rms_first_100_um']:>17.3f} / {r['rms_last_100_um']:.3f}")
    n = sum(r["rigs"] for r in rows)
    print(f"all families: frozen {sum(r['frozen_pass'] for r in rows)}/{n} rigs pass, "
          f"learned {sum(r['learned_pass'] for r in rows)}/{n}")
    for res in results:
        print(f"  selected, {res['family']} rig {res['seed']}: {res['frozen']['selected'] or []} -> "
              f"{res['learned']['selected'] or []} ({res['learned']['n_train']} moves, {res['learned']['form']} GP)")
    print(f"wall time {wall:.0f} s")
    command = "python scripts/bench_learn.py " + " ".join(argv if argv is not None else sys.argv[1:])
    if args.markdown:
        Path(args.markdown).write_text(markdown(rows, results, header, command.strip(), wall))
    if args.json:
        Path(args.json).write_text(json.dumps({"summary": rows, "rigs": results}, indent=1, default=float))
    return 0


if __name__ == "__main__":
    sys.exit(main())
