#!/usr/bin/env python
"""Confusion table of ``microctl diagnose`` on data from an independent stage model.

Usage::

    python scripts/diagnosis_confusion.py [--cases 120] [--clean 20] [--off 24] [--loops 8]
        [--corrupt 12] [--timing 3] [--seed 0] [--config configs/stage/table1.yaml]
        [--noise-from configs/stage/sim_paper.yaml]

Every data set comes from ``tests/independent_stage.py``: a stage simulated apart from
microctl's physics (its own per-ball spring forces and contact-set equilibrium, its own sensor
and noise code), with the Table I geometry of ``--config`` and *random* physics the diagnosis is
not told (ball stiffness, per-ball spread, preload, flexure stiffness; healthy readings within
0.2 σ of the configured stage's, the spec's "model right within noise"), the gauge and driver
noise of ``--noise-from``, 125-300 random moves in the workspace. ``microctl diagnose`` is run
with ``--config`` (the configured physics), without the GP variants of the gain.

Tables printed:

1. *Vocabulary*: each case plants one cause of the registry (cycling through them; random
   actuator, magnitude by the registry's ``Cause.draw`` sized for the stage's own preload).
   Named correctly when the first accepted mean cause, or one of its ``equivalent`` entries,
   is the planted cause on the planted actuator (noise plants: no mean cause and
   ``actuator_friction`` on the planted actuator). Parameters are checked on the matching
   entry against :func:`microctl.testing.plant.parameter_bar` when the data resolve the bar
   (3σ ≤ bar). Extra causes named besides the planted one are counted.
2. *Clean*: no defect; any accepted mean cause or ``significant`` is a false positive.
3. *Off-vocabulary*: a smooth bump, a periodic error in one input, a thermal drift with a time
   constant, a direction-dependent curvature, and history-dependent shapes: piezo creep (an
   overshoot growing with the last step on one actuator) and a periodic gauge error (0.15-0.3
   µm, period 8-12 µm along the reading) (equal numbers, in turn); correct when no vocabulary
   cause is named and ``unexplained`` is; the history and periodic flags of the report are
   counted. Then the generator's own hysteresis loops (``--loops``; half-width 0.15-0.3 µm, one
   actuator or all four), once off the vocabulary and now its ``hysteresis`` cause: correct when
   ``hysteresis`` is named on exactly the planted actuators, nothing else, nothing unexplained.
4. *Corrupt cells*: a log (CSV, read by the measurement-log reader) with a random vocabulary
   cause or none and 1-3 corrupt cells (a q cell 40-60 µm, or t shifted by 5-50 µm); correct
   when the outlying rows are exactly the corrupt ones and the named causes equal those of the
   same log without the corruption.
5. *Timing*: ``microctl diagnose`` (the command, with the GP gain) on 300-move logs.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from collections import Counter, defaultdict
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))

import independent_stage as ind  # noqa: E402  (the test-only independent stage generator)

from microctl.cli import main as cli_main  # noqa: E402
from microctl.diagnosis.data import data_from_arrays, read_for_diagnosis  # noqa: E402
from microctl.diagnosis.pipeline import run_diagnosis  # noqa: E402
from microctl.stage.causes import REGISTRY  # noqa: E402

#: The off-vocabulary shapes (the generator's, less those now in the vocabulary).
OFF_SHAPES = tuple(s for s in ind.OFF_VOCABULARY if s not in ind.IN_VOCABULARY_NOW)
from microctl.stage.config import load_stage_config  # noqa: E402
from microctl.testing.plant import parameter_bar  # noqa: E402

SHORT = {"actuator_gain": "gain", "contact_offset": "c_off", "tool_offset": "t_off", "sensor_scale": "scale",
         "sensor_nonlinearity": "quad", "contact_loss": "c_loss", "backlash": "backlash", "hysteresis": "hyst",
         "drift": "drift", "actuator_friction": "friction", "unexplained": "unexpl", "none": "none"}


def _key(cause: str, actuator) -> str:
    return cause if actuator is None else f"{cause}[{actuator}]"


def named_class(report: dict) -> tuple[str, set[str]]:
    """(name of the first accepted mean cause, keys of it and its equivalents)."""
    for e in report["mean_causes"]:
        if e.get("accepted"):
            keys = {_key(e["cause"], e["params"].get("actuator"))}
            keys |= {_key(q["cause"], q["params"].get("actuator")) for q in e.get("equivalent", [])}
            return e["cause"], keys
    return "none", set()


def vocabulary_named(report: dict) -> list[str]:
    """Keys of the accepted vocabulary mean causes (``unexplained`` excluded)."""
    return [_key(e["cause"], e["params"].get("actuator")) for e in report["mean_causes"]
            if e.get("accepted") and e["cause"] != "unexplained"]


def matching_entry(report: dict, truth: dict) -> dict | None:
    """The report entry (accepted or equivalent, mean or noise) of the planted cause/actuator."""
    want = _key(truth["cause"], truth["actuator"])
    for e in report["mean_causes"] + report["noise_causes"]:
        if not e.get("accepted"):
            continue
        for c in [e, *e.get("equivalent", [])]:
            if _key(c["cause"], c["params"].get("actuator")) == want:
                return c
    return None


def params_ok(entry: dict, truth: dict) -> bool | None:
    """Planted parameters recovered within the bars; None when the data cannot resolve the bar
    (rank deficient, or a standard error above a third of the bar)."""
    if entry.get("rank_deficient"):
        return None
    ok = True
    for name, true in truth["params"].items():
        est = entry["params"].get(name)
        se = entry.get("stderr", {}).get(name)
        if est is None or se is None:
            return None
        bar = parameter_bar(name, true)
        if 3 * se > bar:
            return None
        ok &= abs(est - true) <= bar
    return bool(ok)


def to_data(run: "ind.Run"):
    return data_from_arrays(run.u, run.q, run.t, q_prev=run.q_prev, t_prev=run.t_prev, time_s=run.time_s)


class Cases:
    """Independent random streams per table (adding cases to one table leaves the others alone)."""

    def __init__(self, seed: int, geometry, noise: tuple[float, float], physics: dict):
        self.streams = dict(zip(("vocab", "clean", "off", "corrupt", "timing"), np.random.SeedSequence(seed).spawn(5)))
        self.rngs = {k: np.random.default_rng(v) for k, v in self.streams.items()}
        self.geometry = geometry
        self.physics = physics
        self.gauge, self.driver = noise

    def stage(self, table: str):
        rng = self.rngs[table]
        return rng, ind.random_truth(self.geometry, rng, gauge_um=self.gauge, driver_um=self.driver,
                                     physics=self.physics)

    def moves(self, table: str, n: int | None = None):
        rng = self.rngs[table]
        n = int(rng.integers(125, 301)) if n is None else n
        return n, ind.random_moves(self.geometry, n, rng)


def loops_report(cases: Cases, n_loops: int, diagnose, misses: list[str]) -> None:
    """Section 3's second part: the generator's hysteresis loops (:func:`independent_stage.plant_history`),
    correct when ``hysteresis`` is named on exactly the planted actuators and nothing else."""
    ok = flagged = 0
    rmse = []
    for k in range(n_loops):
        rng, truth = cases.stage("off")
        n, u = cases.moves("off")
        truth, info = ind.plant_history(truth, "hysteresis", rng)
        rep = diagnose(to_data(ind.run(truth, u, rng)), k, label=f"loops {k}")
        want = sorted(_key("hysteresis", a) for a in info["actuators"])
        good = sorted(vocabulary_named(rep)) == want and "unexplained" not in rep["accepted"]["mean"]
        ok += good
        flagged += bool(rep["unexplained"].get("history"))
        g = rep.get("gain", {}).get("rmse_um", {})
        if "afm" in g and "extended" in g:
            rmse.append((g["afm"], g["extended"]))
        if not good:
            misses.append(f"loop {k}: {info} n={n} -> accepted {rep['accepted']} {vocabulary_named(rep)}")
        print(f"  loop {k + 1}/{n_loops}: {'ok' if good else 'MISS'}", file=sys.stderr, flush=True)
    print(f"   hysteresis loops (the generator's, now a vocabulary cause): named hysteresis on exactly the planted "
          f"actuators, nothing else, {ok}/{n_loops} (history flag {flagged})")
    if rmse:
        r = np.array(rmse)
        print(f"   their held-out RMSE (5-fold), AFM -> extended model: median {np.median(r[:, 0]):.3f} -> "
              f"{np.median(r[:, 1]):.3f} µm, per loop " + ", ".join(f"{a:.3f} -> {b:.3f}" for a, b in rmse))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", type=int, default=120, help="vocabulary cases (cycling through the registry)")
    ap.add_argument("--clean", type=int, default=20, help="clean data sets")
    ap.add_argument("--off", type=int, default=24,
                    help=f"off-vocabulary cases (the {len(OFF_SHAPES)} shapes in turn)")
    ap.add_argument("--loops", type=int, default=8, help="the generator's hysteresis loops (named hysteresis)")
    ap.add_argument("--corrupt", type=int, default=12, help="logs with 1-3 corrupt cells")
    ap.add_argument("--timing", type=int, default=3, help="300-move logs timed through the diagnose command")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--config", default=str(ROOT / "configs" / "stage" / "table1.yaml"),
                    help="stage whose geometry the generator uses and the diagnosis is given")
    ap.add_argument("--noise-from", default=str(ROOT / "configs" / "stage" / "sim_paper.yaml"),
                    help="stage config whose simulator noise (gauge, driver) the generator uses")
    args = ap.parse_args(argv)
    cfg = load_stage_config(args.config)
    sim = load_stage_config(args.noise_from).backend.simulated
    geo = ind.load_geometry(args.config)
    cases = Cases(args.seed, geo, (sim.gauge_noise_std_um, sim.driver_accuracy_um), ind.load_physics(args.config))
    causes = list(REGISTRY)
    misses: list[str] = []
    t_all = time.perf_counter()
    times = []

    def diagnose(data, k, set_aside=None, label=""):
        t0 = time.perf_counter()
        rep = run_diagnosis(cfg, data, seed=k, gp=False, set_aside=set_aside).report
        dt = time.perf_counter() - t0
        times.append((data.n, dt, label or f"case {k}"))
        print(f"    ({label or k}: n={data.n}, {dt:.1f} s)", file=sys.stderr, flush=True)
        return rep

    print(f"Independent stage generator (tests/independent_stage.py), geometry {Path(args.config).name}, "
          f"noise of {Path(args.noise_from).name} (gauge {sim.gauge_noise_std_um} µm, driver "
          f"{sim.driver_accuracy_um} µm), seed {args.seed}")
    print(flush=True)
    # ---- 1. vocabulary -----------------------------------------------------------------------
    table: dict[str, Counter] = defaultdict(Counter)
    correct = params_good = params_checked = unresolved = extra_cases = gain_sig = mean_cases = 0
    outlier_false = vocab_hist = 0
    per_cause = Counter()
    for k in range(args.cases):
        name = causes[k % len(causes)]
        rng, truth = cases.stage("vocab")
        truth, planted = ind.plant(truth, name, rng)
        n, u = cases.moves("vocab")
        rep = diagnose(to_data(ind.run(truth, u, rng)), k, label=f"vocab {k} {name}")
        first, cls = named_class(rep)
        want = _key(planted["cause"], planted["actuator"])
        if planted["cause"] == "actuator_friction":
            fr = [e for e in rep["noise_causes"] if e.get("accepted") and e["cause"] == "actuator_friction"]
            ok = not vocabulary_named(rep) and any(e["params"]["actuator"] == planted["actuator"] for e in fr)
            col = "actuator_friction" if fr else first
            extra = len(vocabulary_named(rep)) > 0
        else:
            ok = want in cls
            col = first
            extra = len(vocabulary_named(rep)) > 1
        table[name][SHORT.get(col, col) + ("" if ok or col != name else "*")] += 1
        correct += ok
        per_cause[name] += ok
        extra_cases += extra
        vocab_hist += bool(rep["unexplained"].get("history") or rep["unexplained"].get("periodic"))
        outlier_false += rep["outliers"]["count"] > 0
        entry = matching_entry(rep, planted)
        if entry is not None:
            good = params_ok(entry, planted)
            unresolved += good is None
            if good is not None:
                params_checked += 1
                params_good += good
                if not good:
                    misses.append(f"vocab {k}: params of {want}: planted {planted['params']} got {entry['params']} "
                                  f"± {entry['stderr']}")
        if name != "actuator_friction":
            mean_cases += 1
            g = rep.get("gain", {}).get("p_value", {}).get("extended_vs_afm")
            gain_sig += bool(g is not None and g < 0.05)
        if not ok or extra:
            misses.append(f"vocab {k}: planted {want} {planted['params']} (c = {truth.compression_um:.1f} µm) n={n} "
                          f"-> accepted {rep['accepted']} {vocabulary_named(rep)} class {sorted(cls)}")
        print(f"  vocab {k + 1}/{args.cases} {want}: {'ok' if ok else 'MISS'}{' +extra' if extra else ''}",
              file=sys.stderr, flush=True)

    cols = [*(SHORT[c] for c in causes), "unexpl", "none"]
    cols = [x for c in cols for x in (c, c + "*") if any(x in row for row in table.values())]
    print("1. Vocabulary: rows planted, columns first named (* = right cause, wrong actuator)")
    print("planted".ljust(20) + "".join(c.rjust(9) for c in cols) + "   correct")
    for r in causes:
        if r in table:
            tot = sum(table[r].values())
            print(r.ljust(20) + "".join(str(table[r].get(c, 0)).rjust(9) for c in cols) + f"   {per_cause[r]}/{tot}")
    print(f"named correctly (equivalence class counts): {correct}/{args.cases} = "
          f"{100 * correct / max(args.cases, 1):.1f} % (bar >= 95 %)")
    print(f"cases with a vocabulary cause named besides the planted one: {extra_cases}/{args.cases}")
    print(f"cases with a history or periodic flag (the leftover tests of microctl.diagnosis.history): "
          f"{vocab_hist}/{args.cases}")
    print(f"parameters within the bars (10 % gain-like / 0.2 mm offsets / 10 % others): {params_good}/{params_checked} "
          f"resolvable cases (3σ <= bar); {unresolved} not resolvable on their data")
    print(f"significant held-out gain (extended vs afm, one-sided p < 0.05): {gain_sig}/{mean_cases} mean-cause cases")
    print()
    # ---- 2. clean ----------------------------------------------------------------------------
    fp = clean_hist = 0
    for k in range(args.clean):
        rng, truth = cases.stage("clean")
        n, u = cases.moves("clean")
        rep = diagnose(to_data(ind.run(truth, u, rng)), k, label=f"clean {k}")
        bad = rep["discrepancy"]["significant"] or bool(rep["accepted"]["mean"]) or rep["accepted"]["noise"] != [
            "homoscedastic"]
        fp += bad
        clean_hist += bool(rep["unexplained"].get("history") or rep["unexplained"].get("periodic"))
        outlier_false += rep["outliers"]["count"] > 0
        if bad:
            misses.append(f"clean {k}: n={n} p={rep['discrepancy']['p_value']:.3g} accepted {rep['accepted']}")
        print(f"  clean {k + 1}/{args.clean}: {'FP' if bad else 'ok'}", file=sys.stderr, flush=True)

    print(f"2. Clean: false positives (significant, or any cause named) {fp}/{args.clean} (bar 0); "
          f"history or periodic flag {clean_hist}/{args.clean}")
    print()
    # ---- 3. off-vocabulary ---------------------------------------------------------------------
    off = defaultdict(Counter)
    for k in range(args.off):
        shape = OFF_SHAPES[k % len(OFF_SHAPES)]
        rng, truth = cases.stage("off")
        n, u = cases.moves("off")
        truth, info = ind.plant_off_vocabulary(truth, shape, rng, n)
        rep = diagnose(to_data(ind.run(truth, u, rng)), k, label=f"off {k} {shape}")
        vocab = vocabulary_named(rep)
        unexpl = "unexplained" in rep["accepted"]["mean"]
        off[shape]["cases"] += 1
        off[shape]["no vocabulary cause"] += not vocab
        off[shape]["unexplained"] += unexpl
        off[shape]["outlier rows flagged"] += rep["outliers"]["count"] > 0
        off[shape]["history flag"] += bool(rep["unexplained"].get("history"))
        off[shape]["periodic flag"] += bool(rep["unexplained"].get("periodic"))
        if vocab or not unexpl:
            misses.append(f"off {k}: {info} n={n} -> accepted {rep['accepted']} {vocab}")
        print(f"  off {k + 1}/{args.off} {shape}: {'ok' if not vocab and unexpl else 'MISS'}", file=sys.stderr,
              flush=True)

    print("3. Off-vocabulary: no vocabulary cause named / unexplained reported / cases (bar: all)")
    for shape in OFF_SHAPES:
        c = off[shape]
        if c["cases"]:
            print(f"   {shape:22s} {c['no vocabulary cause']}/{c['cases']}  {c['unexplained']}/{c['cases']}"
                  f"   (history flag {c['history flag']}, periodic flag {c['periodic flag']}; "
                  f"outlier rows flagged in {c['outlier rows flagged']})")
    tot = sum(c["cases"] for c in off.values())
    print(f"   {'all':22s} {sum(c['no vocabulary cause'] for c in off.values())}/{tot}  "
          f"{sum(c['unexplained'] for c in off.values())}/{tot}")
    loops_report(cases, args.loops, diagnose, misses)
    print()
    # ---- 4. corrupt cells ----------------------------------------------------------------------
    corrupt_ok = rows_ok = causes_ok = 0
    with tempfile.TemporaryDirectory() as tmp:
        for k in range(args.corrupt):
            rng, truth = cases.stage("corrupt")
            pick = int(rng.integers(0, len(causes) + 1))
            planted = "clean"
            if pick < len(causes):
                truth, p = ind.plant(truth, causes[pick], rng)
                planted = _key(p["cause"], p["actuator"])
            n, u = cases.moves("corrupt")
            run = ind.run(truth, u, rng)
            bad, cells = ind.corrupt_cells(run, rng, int(rng.integers(1, 4)))
            logs = []
            for tag, r in (("clean", run), ("corrupt", bad)):
                path = Path(tmp) / f"{k}_{tag}.csv"
                r.write_log(path, cfg.stage.actuator_names, cfg.stage.dof, cfg.stage.tool.name)
                logs.append(read_for_diagnosis(path, cfg.stage)[:2])  # as `microctl diagnose` reads it
            rep_clean = diagnose(logs[0][0], k, logs[0][1], label=f"corrupt {k} (clean copy)")
            rep_bad = diagnose(logs[1][0], k, logs[1][1], label=f"corrupt {k}")
            want_lines = sorted(r + 2 for r, _, _ in cells)  # CSV line numbers (header = line 1)
            got_lines = sorted(o["line"] for o in rep_bad["outliers"]["rows"])
            r_ok = got_lines == want_lines
            c_ok = (rep_clean["accepted"] == rep_bad["accepted"]
                    and vocabulary_named(rep_clean) == vocabulary_named(rep_bad))
            rows_ok += r_ok
            causes_ok += c_ok
            corrupt_ok += r_ok and c_ok
            if not (r_ok and c_ok):
                misses.append(f"corrupt {k}: planted {planted}, cells {cells}: outlier lines {got_lines} (want "
                              f"{want_lines}); named {rep_bad['accepted']} {vocabulary_named(rep_bad)} vs clean "
                              f"{rep_clean['accepted']} {vocabulary_named(rep_clean)}")
            print(f"  corrupt {k + 1}/{args.corrupt}: {'ok' if r_ok and c_ok else 'MISS'}", file=sys.stderr,
                  flush=True)

    print(f"4. Corrupt cells: outlying rows exactly the corrupt ones {rows_ok}/{args.corrupt}; named causes those of "
          f"the clean log {causes_ok}/{args.corrupt}; both {corrupt_ok}/{args.corrupt}")
    print(f"   (vocabulary and clean cases with any row flagged as an outlier: {outlier_false}/{args.cases + args.clean})")
    print()
    # ---- 5. timing of the command on 300 moves --------------------------------------------------
    timing = []
    with tempfile.TemporaryDirectory() as tmp:
        for k in range(args.timing):
            rng, truth = cases.stage("timing")
            kind = ["contact_loss", "hysteresis", None][k % 3]
            if kind in REGISTRY:
                truth, _ = ind.plant(truth, kind, rng)
            elif kind is not None:
                truth, _ = ind.plant_off_vocabulary(truth, kind, rng, 300)
            _, u = cases.moves("timing", 300)
            path = Path(tmp) / f"t{k}.csv"
            ind.run(truth, u, rng).write_log(path, cfg.stage.actuator_names, cfg.stage.dof, cfg.stage.tool.name)
            t0 = time.perf_counter()
            rc = cli_main(["diagnose", str(path), "--config", args.config, "--out", str(Path(tmp) / f"o{k}"),
                           "--quiet"])
            timing.append((kind or "clean", rc, time.perf_counter() - t0))
    total = time.perf_counter() - t_all

    ts = np.array([t for _, t, _ in times])
    big = [t for n, t, _ in times if n >= 250]
    print(f"5. Timing: run_diagnosis without the GP gain, per data set: median {np.median(ts):.1f} s, max {ts.max():.1f} s; "
          f"n >= 250: median {np.median(big) if big else float('nan'):.1f} s, max {max(big) if big else float('nan'):.1f} s")
    slowest = sorted(times, key=lambda x: -x[1])[:3]
    print("   slowest: " + "; ".join(f"{label} (n = {n}) {t:.1f} s" for n, t, label in slowest))
    for kind, rc, t in timing:
        print(f"   microctl diagnose (GP gain, figures) on 300 moves, {kind}: {t:.1f} s (exit {rc}) (bar <= 60 s)")
    print(f"total {total:.0f} s")
    if misses:
        print("\nmisses and extras:")
        for m in misses:
            print("  " + m)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
