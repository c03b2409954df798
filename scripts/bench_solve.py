#!/usr/bin/env python
"""Benchmark the EAFM optimal controller (eq. 4) against single-start solvers.

For each size n of the residual training set a residual model: by default (``--fit physical``)
what ``collect`` + ``train`` give, n covering moves on sim_paper's simulator and the package's
default residual model (``--gp auto``: the exact GP up to 1000 rows, the sparse one above;
``--gp exact`` forces the exact one); or synthetic residual data over the Table I workspace with
a planted heteroscedastic noise (three low-noise wells in (rx, ry) plus a z trend, so the
problem has several local optima per target), seeded, with ``--fit fixed`` (the planted noise
with fixed hyperparameters, no fit) or ``--fit vhgpr`` (a VHGPR fit with a wall-time budget).
Then per target (random target and random state; each method runs over every target before the
next starts, so one method's memory use does not slow another's timed solves):

- ``microctl``: the whole :meth:`OptimalController.solve` call (global seeding, fast SQP, IPOPT
  where the fast path does not converge);
- ``ipopt-1start``: the same IPOPT NLP from one cold start (the AFM smallest-motion command);
- ``slsqp``, ``trust-constr``: scipy.optimize.minimize on the same problem from the same
  start, objective/constraint gradients from the same CasADi graphs;
- ``dense-grid``: a 101 x 101 grid over the redundant set, Newton-projected (no polish).

Reported per method: solve CPU time of this process (``time.process_time``: median, min, max;
the BLAS limited to one thread for all methods alike),
IPOPT/SQP/scipy iterations, success rate (converged, constraint residual <= 1e-8 µm, actuators in
range) and the share of targets on which the method reaches the best objective found by any
method (relative 1e-5).

Then, in the same run:

- start-up: CPU time (user + system of the child process, median of ``--startup-runs``) of
  ``python -c pass``, ``python -c 'import numpy, casadi'``, ``microctl --version`` and a one-shot
  ``microctl solve --target 14`` with a model of 125 moves (``collect`` + ``train`` on sim_paper's
  simulator), each beside the issue's bars (solve <= 2x the numpy+casadi import; ``--version``
  <= 1.2x ``pass`` + 50 ms);
- serve: ``microctl serve`` with that model answering ``--serve-requests`` solve requests (random
  reachable targets from random states) one at a time, round-trip latency median / p90 / max, then
  ``--fuzz`` seeded malformed requests: answered, error objects, crashes (a process that died or
  a request left unanswered).

Usage: ``python scripts/bench_solve.py [--sizes 125,500,2000] [--targets 50] [--seed 0]``.
Nothing is cached.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time
import warnings
from pathlib import Path

import casadi as ca
import numpy as np
from scipy.optimize import Bounds, LinearConstraint, NonlinearConstraint, minimize
from threadpoolctl import threadpool_limits

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from microctl.backends.collect import execute_moves  # noqa: E402
from microctl.backends.simulated import SimulatedStage  # noqa: E402
from microctl.control.controller import (  # noqa: E402
    AFMController,
    ControllerSettings,
    OptimalController,
)
from microctl.gp.vhgpr import VHGPR  # noqa: E402
from microctl.measurement.design import training_moves  # noqa: E402
from microctl.models.afm import AnalyticForwardModel  # noqa: E402
from microctl.models.eafm import EAFM, bind_to_stage  # noqa: E402
from microctl.models.training import (  # noqa: E402
    ResidualData,
    ResidualModelSettings,
    train_residual_model,
)
from microctl.stage.config import load_stage_config  # noqa: E402
from microctl.testing import fixed_hyperparameter_model  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
WELLS = [((0.5, -0.3), 2.0), ((-0.4, 0.2), 1.6), ((0.1, 0.6), 1.2)]  # ((rx, ry) mrad, depth in log var)
REACH_REL = 1e-5


def planted_data(afm, n, rng):
    """Training inputs [s; u], residuals and the planted log noise variance."""
    U = afm.workspace.sample(n, rng)
    S = np.column_stack([rng.uniform(0, 30, n), rng.uniform(0, 32, (n, afm.n_q))])
    ln = np.full(n, np.log(0.15**2)) + 0.02 * U[:, 0]
    for (cx, cy), depth in WELLS:
        ln -= depth * np.exp(-((U[:, 1] - cx) ** 2 + (U[:, 2] - cy) ** 2) / (2 * 0.2**2))
    y = 0.3 * np.sin(U[:, 0] / 8) + 0.2 * U[:, 1] - 0.1 * U[:, 2] + np.exp(ln / 2) * rng.standard_normal(n)
    return np.hstack([S, U]), y, ln


def build_model(afm, n, seed, fit, fit_time, gp="auto"):
    rng = np.random.default_rng(seed)
    X, y, ln = planted_data(afm, n, rng)
    t0 = time.perf_counter()
    if fit == "fixed":
        m = fixed_hyperparameter_model(X, y, ln, f_log_lengthscales=np.array([3.0, 3, 3, 3, 3, 0.0, -0.7, -0.7]))
    elif fit == "physical":
        # what `collect` + `train` give with the defaults: n covering moves on the simulated rig
        cfg = load_stage_config(ROOT / "configs/stage/sim_paper.yaml")
        with SimulatedStage(cfg, seed=seed) as st:
            S, U, T = execute_moves(st, training_moves(afm, "covering", n, seed))
        data = ResidualData(np.hstack([S, U]), T - afm.t_of(U), ())
        return train_residual_model(data, afm, ResidualModelSettings(restarts=1, gp=gp), max_time=fit_time), \
            time.perf_counter() - t0
    else:
        m = VHGPR(n_restarts=1, random_state=seed, max_time=fit_time).fit(X, y)
    return bind_to_stage(m, afm), time.perf_counter() - t0


class ScipyProblem:
    """The eq. 4 problem for scipy, values and gradients from the controller's CasADi graphs."""

    def __init__(self, ctl: OptimalController):
        afm = ctl.afm
        s = ca.MX.sym("s", afm.n_s)
        u = ca.MX.sym("u", afm.n_p)
        e = ctl.eafm.expressions(s, u, ctl.objective.needs)
        J = ctl.objective.mx(s, u, e, afm.K)
        self.fJ = ca.Function("obj", [s, u], [J, ca.gradient(J, u)])
        self.fc = ca.Function("con", [s, u], [e["t_mean"], ca.gradient(e["t_mean"], u)])
        self.afm = afm

    def run(self, method, s, target, u0):
        jref = float(self.fJ(s, u0)[0]) or 1.0

        def f(u):
            v, g = self.fJ(s, u)
            return float(v) / jref, np.array(g).ravel() / jref

        def c(u):
            return float(self.fc(s, u)[0]) - target

        def cj(u):
            return np.array(self.fc(s, u)[1]).ravel()

        ws = self.afm.workspace
        if method == "slsqp":
            cons = [{"type": "eq", "fun": c, "jac": lambda u: cj(u)[None, :]},
                    {"type": "ineq", "fun": lambda u: self.afm.K @ u - self.afm.lo, "jac": lambda u: self.afm.K},
                    {"type": "ineq", "fun": lambda u: self.afm.hi - self.afm.K @ u, "jac": lambda u: -self.afm.K}]
            r = minimize(f, u0, jac=True, method="SLSQP", constraints=cons, bounds=list(zip(ws.u_lo, ws.u_hi)),
                         options={"maxiter": 200, "ftol": 1e-12})
        else:
            cons = [NonlinearConstraint(c, 0.0, 0.0, jac=lambda u: cj(u)[None, :]),
                    LinearConstraint(self.afm.K, self.afm.lo, self.afm.hi)]
            r = minimize(f, u0, jac=True, method="trust-constr", constraints=cons, bounds=Bounds(ws.u_lo, ws.u_hi),
                         options={"maxiter": 500, "gtol": 1e-10, "xtol": 1e-12})
        return r.x, bool(r.success), int(getattr(r, "nit", 0))


def bench_size(afm, n, args):
    model, fit_s = build_model(afm, n, args.seed, args.fit, args.fit_time, args.gp)
    eafm = EAFM(afm, model)
    t0 = time.perf_counter()
    ctl = OptimalController(eafm, ControllerSettings(r_e=args.r_e, grid=args.controller_grid, n_polish=args.n_polish))
    build_s = time.perf_counter() - t0
    base = AFMController(afm)
    sp = ScipyProblem(ctl)
    rng = np.random.default_rng(args.seed + 1)
    states = np.column_stack([rng.uniform(0, 30, args.targets), rng.uniform(0, 32, (args.targets, afm.n_q))])
    # targets inside what the EAFM reaches from each state (5 % margins)
    ranges = np.array([ctl.reachable_interval(s) for s in states])
    targets = ranges[:, 0] + (0.05 + 0.9 * rng.uniform(size=args.targets)) * (ranges[:, 1] - ranges[:, 0])
    methods = ["microctl", "ipopt-1start", "slsqp", "trust-constr", "dense-grid"]
    rec = {m: {"t": [], "it": [], "ok": [], "obj": []} for m in methods}

    def valid(s, u, target):
        if u is None or not np.all(np.isfinite(u)):
            return False
        q = afm.K @ u
        t = eafm.predict(s, u).t_mean[0]
        return bool(abs(t - target) <= 1e-8 and np.all(q >= afm.lo - 1e-9) and np.all(q <= afm.hi + 1e-9))

    def valid_many(s, U, target):
        """valid() for many rows of U at once (mean only: O(m n), no variance solves)."""
        t, _ = eafm.mean_and_grad_u(s, U)
        q = U @ afm.K.T
        return ((np.abs(t - target) <= 1e-8) & np.all(q >= afm.lo - 1e-9, axis=1)
                & np.all(q <= afm.hi + 1e-9, axis=1) & np.all(np.isfinite(U), axis=1))

    def objective(s, u):
        return float(ctl._objective_np(s, u[None, :])[0])

    ctl.solve(float(targets[0]), states[0])  # warm the caches (first-call overheads) outside the timing
    u0s = [base.solve(target, s).u for target, s in zip(targets, states)]

    def run(m, target, s, u0):
        """One timed solve by method m: (CPU s, command or None, success, iterations, objective or None)."""
        jref = (objective(s, u0) or 1.0) if m == "ipopt-1start" else None  # the NLP's scale, untimed
        t1 = time.process_time()
        if m == "microctl":
            r = ctl.solve(target, s)
            x, succ, nit = r.u, r.success, r.iterations
        elif m == "ipopt-1start":  # one cold IPOPT start on the same NLP
            x, st = ctl._run(ctl._ipopt(), u0, np.concatenate([[target], s, [jref]]), afm.workspace.u_lo,
                             afm.workspace.u_hi, ctl._lbg, ctl._ubg)
            succ, nit = st["success"], st["iter"]
        elif m == "dense-grid":
            U, obj, _ = ctl._seeds(s, target, args.grid if n < 1000 else args.grid_large)
            fin = np.flatnonzero(np.isfinite(obj))
            good = fin[valid_many(s, U[fin], target)] if fin.size else fin
            # the full objective (the seeding may score large n with a cheaper proxy)
            best_grid = float(ctl._objective_np(s, U[good]).min()) if good.size else np.inf
            return time.process_time() - t1, None, bool(good.size), 0, best_grid
        else:
            x, succ, nit = sp.run(m, s, target, u0)
        return time.process_time() - t1, x, succ, nit, None

    # method after method, each over every target: interleaved, the dense grid's 10 MB
    # temporaries made the next method's solve measurably slower (the allocator returns them to
    # the system and the next arrays fault their pages in again)
    for i, m in enumerate(methods):
        for k, (target, s, u0) in enumerate(zip(targets, states, u0s)):
            dt, x, succ, nit, obj = run(m, target, s, u0)
            ok = bool(succ) if x is None else bool(succ) and valid(s, x, target)
            rec[m]["t"].append(dt); rec[m]["it"].append(nit); rec[m]["ok"].append(ok)
            rec[m]["obj"].append(obj if x is None else (objective(s, x) if ok else np.inf))
            if not args.quiet:
                print(f"\r  n={n}: method {i + 1}/{len(methods)}, target {k + 1}/{args.targets}", end="",
                      file=sys.stderr, flush=True)
    if not args.quiet:
        print(file=sys.stderr)
    objs = np.array([rec[m]["obj"] for m in methods])
    best = objs.min(axis=0)
    rows = []
    for i, m in enumerate(methods):
        t = np.array(rec[m]["t"]) * 1e3
        reached = objs[i] <= best * (1 + REACH_REL) + 1e-300
        rows.append((n, m, np.median(t), t.min(), t.max(), np.median(rec[m]["it"]), 100 * np.mean(rec[m]["ok"]),
                     100 * np.mean(reached)))
    form = f"{model.posterior_form} GP on {model.X.shape[0]} points"
    return rows, fit_s, build_s, form


# --------------------------------------------------------------------------- start-up and serve

MICROCTL = [sys.executable, "-m", "microctl"]
SIM = ROOT / "configs/stage/sim_paper.yaml"


def child_cpu(cmd, runs, env=None):
    """Median and min CPU seconds (user + system of the child) and median wall seconds of ``cmd`` over ``runs``
    (``env``: variables added to the child's environment)."""
    import resource
    import subprocess

    cpu, wall = [], []
    for _ in range(runs):
        r0 = resource.getrusage(resource.RUSAGE_CHILDREN)
        t0 = time.perf_counter()
        subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, cwd=ROOT,
                       env={**os.environ, **(env or {})})
        wall.append(time.perf_counter() - t0)
        r1 = resource.getrusage(resource.RUSAGE_CHILDREN)
        cpu.append((r1.ru_utime - r0.ru_utime) + (r1.ru_stime - r0.ru_stime))
    return float(np.median(cpu)), float(np.min(cpu)), float(np.median(wall))


def model_125(tmp):
    """A 125-move covering log of sim_paper's simulator and the model `microctl train` makes of it."""
    import subprocess

    log, model = tmp / "log125.csv", tmp / "model125.npz"
    subprocess.run([*MICROCTL, "collect", "--config", str(SIM), "-n", "125", "-o", str(log), "--quiet"], check=True)
    subprocess.run([*MICROCTL, "train", str(log), "--config", str(SIM), "-o", str(model), "--quiet"], check=True)
    return model


def bench_startup(model, runs):
    """Rows (label, CPU median s, CPU min s, wall median s) and the two bars' verdicts."""
    py = sys.executable
    solve = [*MICROCTL, "solve", "--config", str(SIM), "--model", str(model), "--target", "14"]
    one, two = {"OPENBLAS_NUM_THREADS": "1"}, {"OPENBLAS_NUM_THREADS": "2"}
    cases = [("python -c pass", [py, "-c", "pass"], None),
             ("python -c 'import numpy, casadi'", [py, "-c", "import numpy, casadi"], None),
             ("microctl --version", [*MICROCTL, "--version"], None),
             ("microctl solve --target 14 (n = 125)", solve, None),
             # the same two with the BLAS pool sized alike: microctl starts it with one thread
             # (cli.one_blas_thread), python with one per core, whose idle threads spin
             ("  import numpy, casadi, 1 BLAS thread", [py, "-c", "import numpy, casadi"], one),
             ("  microctl solve, 2 BLAS threads", solve, two)]
    rows = [(label, *child_cpu(cmd, runs, env)) for label, cmd, env in cases]
    base, npca, ver, solve_cpu = (rows[k][1] for k in range(4))
    bars = [f"solve / import numpy, casadi = {solve_cpu / npca:.2f}x (bar <= 2x): "
            f"{'met' if solve_cpu <= 2 * npca else 'NOT met'}; with the pools sized alike: "
            f"{solve_cpu / rows[4][1]:.2f}x (1 thread each), {rows[5][1] / npca:.2f}x (2 threads each)",
            f"--version = {ver * 1e3:.0f} ms vs 1.2 x pass + 50 ms = {(1.2 * base + 0.05) * 1e3:.0f} ms: "
            f"{'met' if ver <= 1.2 * base + 0.05 else 'NOT met'}"]
    return rows, bars


def _fuzz_line(rng):
    """One malformed request (seeded): random bytes, cut JSON, wrong types, bad values, deep nesting."""
    import json

    kind = rng.integers(6)
    if kind == 0:
        return b"#" + bytes(rng.integers(0, 256, rng.integers(1, 120)).tolist()).replace(b"\n", b" ")
    if kind == 1:
        text = json.dumps({"op": "solve", "target_um": 10.0})
        return text[: rng.integers(1, len(text))].encode()
    if kind == 2:
        bad = [None, True, "12", [], {}, 1e308, "nan", [1, 2], {"t": 1}]
        key = ["target_um", "state", "baseline", "op"][rng.integers(4)]
        req = {"op": "solve", "target_um": 10.0, key: bad[rng.integers(len(bad))]}
        return json.dumps(req).encode()
    if kind == 3:
        return b"[" * 3000 + b"]" * 3000
    if kind == 4:
        return b'{"op": "solve", "target_um": NaN}'
    return json.dumps({"op": "solve", "target_um": float(rng.choice([-1, 1]) * 10 ** rng.uniform(3, 6))}).encode()


def bench_serve(model, requests, fuzz, seed):
    """Round-trip latencies of `microctl serve` solve requests and the fuzz's outcome."""
    import json
    import subprocess

    from microctl import api

    stage = api.load_stage(SIM)
    ctl = api.Controller(stage, model)
    rng = np.random.default_rng(seed)
    states = np.column_stack([rng.uniform(0, 30, requests), rng.uniform(0, 32, (requests, stage.afm.n_q))])
    reach = np.array([ctl.reachable_interval(st) for st in states[:50]])  # the range hardly moves with the state
    lo, hi = reach[:, 0].max(), reach[:, 1].min()
    targets = lo + (0.05 + 0.9 * rng.uniform(size=requests)) * (hi - lo)
    p = subprocess.Popen([*MICROCTL, "serve", "--config", str(SIM), "--model", str(model), "--quiet"],
                         stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE, cwd=ROOT)

    def ask(line: bytes) -> dict | None:
        p.stdin.write(line + b"\n")
        p.stdin.flush()
        out = p.stdout.readline()
        return json.loads(out) if out else None

    for k in range(20):  # warm-up
        ask(json.dumps({"op": "solve", "target_um": float(targets[k]), "state": states[k].tolist()}).encode())
    lat, ok = [], 0
    for t, st in zip(targets, states):
        line = json.dumps({"op": "solve", "target_um": float(t), "state": st.tolist()}).encode()
        t0 = time.perf_counter()
        r = ask(line)
        lat.append(time.perf_counter() - t0)
        ok += bool(r and r["ok"])
    answered = errors = 0
    for _ in range(fuzz):
        r = ask(_fuzz_line(rng))
        answered += r is not None
        errors += bool(r is not None and not r["ok"])
    alive = p.poll() is None and ask(b'{"op": "state"}') is not None
    p.stdin.close()
    p.wait(timeout=60)
    lat = np.array(lat) * 1e3
    return {"requests": requests, "ok": ok, "median_ms": float(np.median(lat)), "p90_ms": float(np.percentile(lat, 90)),
            "max_ms": float(lat.max()), "fuzz": fuzz, "answered": answered, "errors": errors,
            "crashes": int(not alive) + (fuzz - answered)}


def report_startup_and_serve(args):
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        model = model_125(Path(tmp))
        if args.startup_runs:
            # as `pip install` does for a regular install (numpy's and casadi's .pyc exist): without
            # it, PYTHONDONTWRITEBYTECODE=1 (set on some machines) recompiles microctl every run
            import compileall

            compileall.compile_dir(str(ROOT / "microctl"), quiet=1)
            print()
            print("bytecode: microctl compiled before timing (compileall), as a regular pip install does"
                  f" (PYTHONDONTWRITEBYTECODE={os.environ.get('PYTHONDONTWRITEBYTECODE', 'unset')})")
            rows, bars = bench_startup(model, args.startup_runs)
            print()
            print(f"start-up, CPU of the child process (user + system), median of {args.startup_runs} runs:")
            print(f"{'command':>40} {'CPU med ms':>10} {'min ms':>8} {'wall med ms':>11}")
            for label, med, mn, wall in rows:
                print(f"{label:>40} {med * 1e3:10.0f} {mn * 1e3:8.0f} {wall * 1e3:11.0f}")
            for b in bars:
                print(f"  {b}")
        if args.serve_requests:
            r = bench_serve(model, args.serve_requests, args.fuzz, args.seed)
            print()
            print(f"serve (n = 125, sim_paper): {r['requests']} solve requests one at a time, {r['ok']} answered ok; "
                  f"round trip median {r['median_ms']:.2f} ms, p90 {r['p90_ms']:.2f} ms, max {r['max_ms']:.2f} ms "
                  f"(bar: median <= 3 ms: {'met' if r['median_ms'] <= 3 else 'NOT met'})")
            print(f"serve fuzz: {r['fuzz']} malformed requests, {r['answered']} answered, {r['errors']} error objects, "
                  f"{r['crashes']} crashes (bar: 0)")


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--sizes", default="125,500,2000", help="comma-separated training-set sizes")
    p.add_argument("--targets", type=int, default=50, help="targets per size (>= 50 for the report)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--grid", type=int, default=101, help="dense-grid points per null-space axis")
    p.add_argument("--grid-large", type=int, default=41,
                   help="dense-grid points per axis for n >= 1000 (the full objective costs O(n^2) per point)")
    p.add_argument("--r-e", default=ControllerSettings().r_e, help="the controller's r_e (default: the package's)")
    p.add_argument("--fit", choices=("fixed", "vhgpr", "physical"), default="physical",
                   help="residual model: physical (default: the package's default model fitted to n covering moves "
                   "on sim_paper), fixed (planted heteroscedastic noise, fixed hyperparameters: g's GP variance "
                   "matters everywhere), or vhgpr (a plain VHGPR fit to the planted data)")
    p.add_argument("--gp", choices=("auto", "exact", "sparse"), default="auto",
                   help="the physical model's GP form (default auto: what `microctl train` fits at that size)")
    p.add_argument("--fit-time", type=float, default=300.0, help="VHGPR fit budget per size (s)")
    p.add_argument("--controller-grid", type=int, default=ControllerSettings().grid,
                   help="the controller's seeding grid per null-space axis (its setting 'grid')")
    p.add_argument("--n-polish", type=int, default=ControllerSettings().n_polish,
                   help="grid minima the controller polishes with IPOPT (its setting 'n_polish')")
    p.add_argument("--startup-runs", type=int, default=7, help="runs per start-up row (0: skip the start-up rows)")
    p.add_argument("--serve-requests", type=int, default=1000,
                   help="solve requests timed through `microctl serve` (0: skip the serve rows)")
    p.add_argument("--fuzz", type=int, default=500, help="malformed requests sent to `microctl serve` after them")
    p.add_argument("--quiet", action="store_true")
    args = p.parse_args(argv)
    warnings.filterwarnings("ignore", category=UserWarning, module="scipy")
    afm = AnalyticForwardModel(load_stage_config(ROOT / "configs/stage/table1.yaml").stage)
    sizes = [int(v) for v in args.sizes.split(",")]
    print(f"machine: {platform.platform()}, {platform.processor() or platform.machine()}, "
          f"cpus={os.cpu_count()}, python {platform.python_version()}, casadi {ca.__version__}")
    print(f"targets per size: {args.targets}, seed {args.seed}, model: {args.fit}, r_e: {args.r_e}, "
          f"reach = objective within {REACH_REL:g} (relative) of the best of all methods")
    print("BLAS: one thread for every method (threadpoolctl), as microctl runs its own numerics: a pool's "
          "idle workers spin, and process_time charges that to whichever call is timed next")
    all_rows = []
    for n in sizes:
        with threadpool_limits(limits=1, user_api="blas"):
            rows, fit_s, build_s, form = bench_size(afm, n, args)
        print(f"n={n}: model {fit_s:.1f} s ({form}), controller build {build_s * 1e3:.0f} ms")
        all_rows += rows
    print()
    print(f"{'n':>5} {'method':>13} {'CPU med ms':>10} {'min ms':>8} {'max ms':>9} {'iter':>5} {'success %':>9} "
          f"{'best %':>7}")
    for r in all_rows:
        print(f"{r[0]:5d} {r[1]:>13} {r[2]:10.2f} {r[3]:8.2f} {r[4]:9.2f} {r[5]:5.0f} {r[6]:9.0f} {r[7]:7.0f}")
    report_startup_and_serve(args)


if __name__ == "__main__":
    main()
