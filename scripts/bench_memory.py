"""The controller with the hysteresis memory against without it, on simulated stages with piezo hysteresis.

Each rig is ``sim_paper`` (its stick-slip and gauge noise) with a hysteresis loop planted
(:class:`~microctl.stage.causes.Hysteresis`, drawn as the cause registry plants it: h ~ U(0.15, 0.4)
µm, R ~ U(2, 8) µm) on one actuator (even rigs) or on all four (odd rigs). A log of ``--moves``
space-filling moves is collected once, and two residual models are trained on it with the
package defaults (``microctl train``):

- ``without``: ``stage.corrections`` hold the simulator's static causes (sim_paper's actuator
  gains, as a diagnosed stage's extended config would) but no hysteresis: the GP learns what it
  can of the loop from x = [s; u];
- ``memory``: the same corrections and the planted loop (what ``microctl diagnose`` writes into
  ``extended.yaml`` when it names it; here the true parameters): the AFM carries the play states,
  the residual is taken with the loop run along the log, and the controller meets the target
  with the play states it steps with every command it sends (:mod:`microctl.control.memory`).

- ``diagnosed`` (with ``--diagnose``): the corrections ``microctl diagnose`` extends the
  ``without`` config with from the same log (``run_diagnosis``, its extended config: whatever
  it names, with its fitted parameters), the realistic path from a log to the memory.

As a floor, the same rig without the loop (``no loop``: trained and driven the same way) shows
what the rest of the stage (stick-slip, the GP's accuracy from that many moves) leaves.

Each model's optimal controller then drives a fresh simulated stage (same seed for both)
through ``--targets`` random targets in random order (reversals of every length). Scored
against the simulator's truth at the executed commands (its mean reading given the stage's
real play states, ``SimulatedStage.true_mean``): the RMS and largest |true mean - target|.

    python scripts/bench_memory.py --rigs 10 --moves 200 --targets 20
"""

from __future__ import annotations

import argparse
import platform
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from microctl import api
from microctl.backends.simulated import SimulatedStage
from microctl.models.afm import AnalyticForwardModel
from microctl.stage.causes import REGISTRY, Hysteresis, preload_compression_um
from microctl.testing.plant import simulate, with_effects


def _rig(base: api.Stage, k: int) -> tuple[api.Stage, api.Stage, api.Stage, tuple[Hysteresis, ...]]:
    """(stage as shipped, stage with the loop in its corrections, both simulating it; the stage
    without the loop planted; the loop) of rig k."""
    rng = np.random.default_rng(7100 + k)
    comp = preload_compression_um(base.config.stage)
    acts = (1, 2, 3, 4) if k % 2 else (int(rng.integers(1, 5)),)
    loop = tuple(Hysteresis.draw(rng, a, compression_um=comp) for a in acts)
    shipped = base.config.backend.simulated.effects
    # every arm knows the simulator's static causes (sim_paper's actuator gains), as a diagnosed
    # stage's extended config would: the arms differ by the loop alone
    static = replace(base.config.stage.corrections,
                     **{n: getattr(shipped, n) for n, c in REGISTRY.items() if c.kind == "static"})
    known = replace(base.config, stage=replace(base.config.stage, corrections=static))
    cfg = with_effects(known, replace(shipped, hysteresis=loop), seed=7100 + k)
    plain = api.Stage(cfg, AnalyticForwardModel(cfg.stage))
    cfg_m = replace(cfg, stage=replace(cfg.stage, corrections=replace(static, hysteresis=loop)))
    cfg_0 = with_effects(known, shipped, seed=7100 + k)
    return (plain, api.Stage(cfg_m, AnalyticForwardModel(cfg_m.stage)),
            api.Stage(cfg_0, AnalyticForwardModel(cfg_0.stage)), loop)


def _diagnosed(plain: api.Stage, data, k: int) -> api.Stage:
    """The stage config ``run_diagnosis`` extends ``plain`` with from the log's data, simulating the same rig."""
    from microctl.diagnosis.pipeline import run_diagnosis

    ext = run_diagnosis(plain.config, data, seed=k, gain=False).extended_config
    ext = replace(ext, backend=plain.config.backend)
    return api.Stage(ext, AnalyticForwardModel(ext.stage))


def _named(stage: api.Stage) -> str:
    """The causes in a stage's corrections, e.g. ``hysteresis[2,4]``."""
    out = []
    for name, cause in REGISTRY.items():
        value = getattr(stage.config.stage.corrections, name)
        if value and cause.kind != "noise":
            acts = [str(c.actuator) for c in value] if isinstance(value, tuple) else []
            out.append(f"{name}[{','.join(acts)}]" if acts else name)
    return " ".join(out) or "none"


def _drive(stage: api.Stage, model: Path, targets: np.ndarray, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """True mean error and true std at each target, the controller from ``model`` driving a fresh stage."""
    ctl = api.Controller(stage, model)
    b = SimulatedStage(stage.config, seed=seed)
    afm = stage.afm
    z = afm.memory.step(None, b.state[1:]) if afm.memory.active else None
    err, sd = [], []
    for tg in targets:
        s = b.state
        res = ctl.solve(float(tg), s, memory=z)
        err.append(float(b.true_mean(s, res.u)) - float(tg))
        sd.append(float(np.sqrt(b.true_var(s, res.u))))
        b.move(res.u)
        if z is not None:
            z = afm.memory.step(z, b.state[1:])
    return np.array(err), np.array(sd)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rigs", type=int, default=10)
    ap.add_argument("--moves", type=int, default=200)
    ap.add_argument("--targets", type=int, default=20)
    ap.add_argument("--diagnose", action="store_true", help="add the diagnosed arm (run_diagnosis on the log)")
    args = ap.parse_args(argv)
    base = api.load_stage("sim_paper")
    lo, hi = base.afm.t_range()
    print(f"# bench_memory: {platform.node()} ({platform.machine()}), Python {platform.python_version()}, "
          f"{args.rigs} rigs, {args.moves} training moves, {args.targets} targets in "
          f"[{lo + 0.15 * (hi - lo):.1f}, {hi - 0.15 * (hi - lo):.1f}] µm\n")
    dh = "diagnosed: RMS / max |err| µm (named) | " if args.diagnose else ""
    print("| rig | loop (actuator: h µm / R µm) | without: RMS / max |err| µm | memory: RMS / max |err| µm "
          f"| no loop: RMS / max |err| µm | {dh}mean true std without / memory µm | train s (w/m) |")
    print("|---" * (7 + args.diagnose) + "|")
    wins, wins_d, rms_w, rms_m, rms_d = 0, 0, [], [], []
    t_all = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        for k in range(args.rigs):
            plain, mem, clean, loop = _rig(base, k)
            log, log0 = Path(tmp) / f"rig{k}.csv", Path(tmp) / f"rig{k}_clean.csv"
            data = simulate(plain.config, plain.config.backend.simulated.effects, args.moves, seed=7100 + k,
                            log_path=log)
            simulate(clean.config, clean.config.backend.simulated.effects, args.moves, seed=7100 + k, log_path=log0)
            rng = np.random.default_rng(7200 + k)
            targets = rng.uniform(lo + 0.15 * (hi - lo), hi - 0.15 * (hi - lo), args.targets)
            out = {}
            arms = [("without", plain, log), ("memory", mem, log), ("clean", clean, log0)]
            if args.diagnose:
                arms.append(("diagnosed", _diagnosed(plain, data, k), log))
            for name, stage, path in arms:
                t0 = time.perf_counter()
                model = Path(tmp) / f"rig{k}_{name}.npz"
                api.train(path, stage, out=model, seed=k)
                ts = time.perf_counter() - t0
                e, sd = _drive(stage, model, targets, seed=7300 + k)
                out[name] = (float(np.sqrt(np.mean(e ** 2))), float(np.max(np.abs(e))), float(np.mean(sd)), ts)
            (rw, mw, sw, tw), (rm, mm, sm, tm), (r0, m0, _, _) = out["without"], out["memory"], out["clean"]
            wins += rm < rw
            rms_w.append(rw)
            rms_m.append(rm)
            desc = ", ".join(f"{c.actuator}: {c.half_width_um:.2f}/{c.range_um:.1f}" for c in loop)
            diag = ""
            if args.diagnose:
                rd, md, _, _ = out["diagnosed"]
                wins_d += rd < rw
                rms_d.append(rd)
                diag = f"{rd:.3f} / {md:.3f} ({_named(arms[-1][1])}) | "
            print(f"| {k} | {desc} | {rw:.3f} / {mw:.3f} | {rm:.3f} / {mm:.3f} | {r0:.3f} / {m0:.3f} | {diag}"
                  f"{sw:.3f} / {sm:.3f} | {tw:.0f} / {tm:.0f} |", flush=True)
    print(f"\nRMS true error lower with the memory on {wins}/{args.rigs} rigs; median RMS without "
          f"{np.median(rms_w):.3f} µm, with the memory {np.median(rms_m):.3f} µm "
          f"(wall {time.perf_counter() - t_all:.0f} s)")
    if args.diagnose:
        print(f"diagnosed: RMS true error lower than without on {wins_d}/{args.rigs} rigs; median RMS "
              f"{np.median(rms_d):.3f} µm")
    return 0


if __name__ == "__main__":
    sys.exit(main())
