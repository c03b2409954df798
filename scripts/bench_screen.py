#!/usr/bin/env python
"""The corrupt-reading screen of training on every rig family and on the paper-scale rig.

Usage::

    python scripts/bench_screen.py [--family all] [--rigs 12] [--planted-rigs 6] [--moves 200]
        [--paper-logs 10] [--paper-moves 285] [--jobs 2]

What it measures (:mod:`microctl.models.outlier_screen`, run as ``microctl train`` runs it:
``microctl.models.training._screened``, the first fit, the source selection, the screen and the
whole-model confirmation, in rounds):

- *unaltered logs*: ``--moves`` covering moves on ``--rigs`` seeded rigs of each family of
  ``scripts/rig_families.py`` (seed k, stage seed k + 10000, as ``bench_rigs.py`` collects
  them), and ``--paper-logs`` logs of ``--paper-moves`` covering moves on
  ``configs/stage/sim_paper_scale.yaml`` (design seed k, simulator seed 1000 + k): every row
  set aside there is a legitimate reading lost (the bar: none);
- *a planted corrupt reading*: on the first ``--planted-rigs`` rigs of each family the reading
  of the middle row is raised by 1 µm and by 3 µm (the families' scatter is 0.01-0.3 µm), on
  the paper-scale logs by 5 µm and 20 µm (its scatter reaches several µm); found = exactly that
  row set aside, other = rows set aside besides it.

Prints a table per family and the rows set aside with their z, and the machine.
"""

from __future__ import annotations

import argparse
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

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

import rig_families as RF  # noqa: E402

from microctl.backends.collect import run_collect  # noqa: E402
from microctl.backends.base import make_backend  # noqa: E402
from microctl.measurement.design import training_moves  # noqa: E402
from microctl.measurement.log import read_log  # noqa: E402
from microctl.models.afm import AnalyticForwardModel  # noqa: E402
from microctl.models.training import ResidualData, ResidualModelSettings, _screened, residual_dataset  # noqa: E402
from microctl.stage.config import load_stage_config  # noqa: E402

PAPER_SCALE = HERE.parent / "configs" / "stage" / "sim_paper_scale.yaml"


def _screen(data: ResidualData, afm: AnalyticForwardModel, row: int, bump_um: float) -> dict:
    y = data.y.copy()
    y[row] += bump_um
    t0 = time.perf_counter()
    _, _, rec = _screened(ResidualData(data.X, y, data.x_names), afm, ResidualModelSettings(), None)
    return {"rows": rec["rows"], "z": rec["z"], "withheld": rec["withheld"], "nu": rec["tail_nu"],
            "time_s": time.perf_counter() - t0}


def _collect(stage_backend, afm: AnalyticForwardModel, n: int, seed: int, stage) -> ResidualData:
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "log.csv"
        with stage_backend as st:
            run_collect(st, training_moves(afm, "covering", n, seed), path, quiet=True)
        return residual_dataset(read_log(path, stage, min_rows=5), afm)


def family_job(args: tuple) -> dict:
    """One rig of a family: the unaltered log, and (planted rigs) +1 and +3 µm at the middle row."""
    family, seed, moves, planted = args
    rig = RF.make_family_rig(family, seed)
    afm = AnalyticForwardModel(rig.config.stage)
    data = _collect(rig.stage(seed + 10000), afm, moves, seed, rig.config.stage)
    out = {"family": family, "seed": seed, "0": _screen(data, afm, moves // 2, 0.0)}
    for b in ((1.0, 3.0) if planted else ()):
        out[f"{b:g}"] = _screen(data, afm, moves // 2, b)
    return out


def paper_job(args: tuple) -> dict:
    """One paper-scale log: unaltered, +5 and +20 µm at the middle row."""
    k, moves = args
    cfg = load_stage_config(PAPER_SCALE)
    afm = AnalyticForwardModel(cfg.stage)
    data = _collect(make_backend(cfg, seed=1000 + k), afm, moves, k, cfg.stage)
    out = {"family": "paper_scale", "seed": k, "0": _screen(data, afm, moves // 2, 0.0)}
    for b in (5.0, 20.0):
        out[f"{b:g}"] = _screen(data, afm, moves // 2, b)
    return out


def _table(results: list[dict], bumps: dict[str, tuple[str, ...]]) -> list[str]:
    lines = ["family        logs  with a row set aside  rows  withheld  planted           found  other rows  "
             "time (s), median",
             "-" * 112]
    for fam in dict.fromkeys(r["family"] for r in results):
        rs = [r for r in results if r["family"] == fam]
        clean = [r["0"] for r in rs]
        lost = sum(bool(c["rows"]) for c in clean)
        nrows = sum(len(c["rows"]) for c in clean)
        wh = sum(bool(c["withheld"]) for c in clean)
        planted = []
        for b in bumps.get(fam, bumps["*"]):
            ps = [r[b] for r in rs if b in r]
            if ps:
                mid = [r for r in rs if b in r]
                found = sum(p["rows"].count(_mid(r)) == 1 for p, r in zip(ps, mid))
                other = sum(len([i for i in p["rows"] if i != _mid(r)]) for p, r in zip(ps, mid))
                planted.append(f"+{b} µm {found}/{len(ps)} (other {other})")
        t = np.median([x["time_s"] for r in rs for k, x in r.items() if isinstance(x, dict)])
        lines.append(f"{fam:12s} {len(clean):5d}  {lost:20d}  {nrows:4d}  {wh:8d}  {'; '.join(planted):30s}  "
                     f"{t:.1f}")
    return lines


def _mid(r: dict) -> int:
    return r["moves"] // 2


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--family", default="all", help="a family of scripts/rig_families.py, or all (default)")
    ap.add_argument("--rigs", type=int, default=12, help="seeded rigs per family (default 12)")
    ap.add_argument("--planted-rigs", type=int, default=6, help="of those, rigs with a planted reading (default 6)")
    ap.add_argument("--moves", type=int, default=200, help="covering moves per family log (default 200)")
    ap.add_argument("--paper-logs", type=int, default=10, help="paper-scale logs (default 10; 0: none)")
    ap.add_argument("--paper-moves", type=int, default=285,
                    help="moves per paper-scale log (default 285: the experiment's 125 + 4 x 40)")
    ap.add_argument("--jobs", type=int, default=2, help="processes (default 2)")
    a = ap.parse_args(argv)
    fams = RF.FAMILIES if a.family == "all" else (a.family,)
    if any(f not in RF.FAMILIES for f in fams):
        ap.error(f"--family: one of {', '.join(RF.FAMILIES)} or all")
    jobs = [(f, s, a.moves, s < a.planted_rigs) for s in range(a.rigs) for f in fams]
    print(f"machine: {platform.platform()}, {platform.processor() or platform.machine()}, cpus={os.cpu_count()}, "
          f"python {platform.python_version()}, numpy {np.__version__}; families {list(fams)}, {a.rigs} rigs "
          f"({a.planted_rigs} planted), {a.moves} moves; paper-scale logs {a.paper_logs} x {a.paper_moves} moves; "
          f"jobs {a.jobs}", flush=True)
    t0 = time.perf_counter()
    results = []
    with ProcessPoolExecutor(a.jobs) as pool:
        futures = [pool.submit(family_job, j) for j in jobs]
        futures += [pool.submit(paper_job, (k, a.paper_moves)) for k in range(a.paper_logs)]
        for f in futures:
            r = f.result()
            r["moves"] = a.paper_moves if r["family"] == "paper_scale" else a.moves
            results.append(r)
            print(f"  {r['family']} {r['seed']}: " + "; ".join(
                f"{k}: rows {v['rows']} z {[round(z, 1) for z in v['z']]}" for k, v in r.items()
                if isinstance(v, dict)), file=sys.stderr, flush=True)
    print("\n".join(_table(results, {"paper_scale": ("5", "20"), "*": ("1", "3")})))
    print("logs: unaltered logs; with a row set aside / rows: legitimate readings the screen set aside "
          "(bar: none); withheld: logs where more rows than 2 % exceeded the first bound; planted: a reading "
          "raised at the middle row, found = exactly that row set aside, other = rows set aside besides it; "
          f"time: median seconds of training's steps 1-2 with the screen. Wall time {time.perf_counter() - t0:.0f} s.")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
