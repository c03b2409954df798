#!/usr/bin/env python
"""Benchmark the VHGPR trainer against scikit-learn's homoscedastic GP.

For the motorcycle data (all 133 points as train and test, the authors' protocol) and for
synthetic data with a known mean and noise function (n = 125, 500, 2000 training points,
a separate seeded hold-out set of 2000 points), report the median fit time over a few
repeats and the mean negative log predictive density (NLPD, Gaussian predictive) of

* microctl's VHGPR (default settings, one restart for n = 2000; and one optimiser start,
  ``n_restarts=1, g_start="f"``, as scikit-learn's: the restarts-matched comparison),
* scikit-learn ``GaussianProcessRegressor(C * RBF + WhiteKernel, normalize_y=True)``,
* for synthetic data, the oracle that knows the true mean and noise,

plus the correlation of the learned mean log-noise with the true one.

At scale (``--scale 2000,5000,20000``): a 3-D synthetic whose noise depends on an input the
mean ignores (:func:`planted3d`), hold-out 2000 points: the exact VHGPR (defaults, and
``g_start="f"``) and scikit-learn where n <= 2000, the sparse VHGPR (:mod:`microctl.gp.sparse`,
default settings) at every n, fit time, NLPD, and the time of :func:`microctl.gp.sparse.update`
with 10 new points. ``--stage-days D``: a simulated stage log (``configs/stage/sim_paper.yaml``,
200 covering-design moves a day for D days, hold-out 2000 moves with another seed): the residual
model (``microctl train`` defaults) exact on the first 2000 moves, sparse on 2000 and on all,
its hold-out NLPD and the controller's per-call CPU time (median over 15 targets) on each.

``--iter-sweep 20,40,...``: one-start fits of the motorcycle data and the 1-D synthetic at n = 125
and 500 with each iteration cap (bound, hold-out NLPD, evaluations, time): what the default cap
(:func:`microctl.gp.trainer.default_max_iter`) gives up.

Usage: ``python scripts/bench_vhgpr.py [--repeats 3] [--sizes 125,500,2000] [--scale 1000,2000,5000,20000]
[--stage-days 100] [--iter-sweep 20,40,60,100,200,400]``.
scikit-learn is needed by this script only (``pip install microctl[bench]``).
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import sys
import time
import warnings
from pathlib import Path
from typing import Any

import numpy as np

from microctl.gp.homoscedastic import INIT_STARTS
from microctl.gp.vhgpr import VHGPR

#: the motorcycle benchmark data, shipped with the tests (tests/data/README.md)
MCYCLE = Path(__file__).resolve().parents[1] / "tests" / "data" / "mcycle.csv"


def planted(n: int, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """x ~ U(0, 1); f = sin(2 pi x) + x/2; noise sd 0.1 + 0.5 exp(-(x - 0.7)^2 / (2 0.15^2))."""
    rng = np.random.default_rng(seed)
    x = rng.uniform(0.0, 1.0, n)
    f = np.sin(2 * np.pi * x) + 0.5 * x
    sd = 0.1 + 0.5 * np.exp(-0.5 * ((x - 0.7) / 0.15) ** 2)
    return x[:, None], f + sd * rng.standard_normal(n), f, 2 * np.log(sd)


def planted3d(n: int, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """x ~ U(-1, 1)^3; f = sin(2 x0) + x1^2 / 2; log noise variance -3 + 1.5 x2 + x0 (x2: not in f)."""
    rng = np.random.default_rng(seed)
    X = rng.uniform(-1.0, 1.0, (n, 3))
    f = np.sin(2.0 * X[:, 0]) + 0.5 * X[:, 1] ** 2
    g = -3.0 + 1.5 * X[:, 2] + X[:, 0]
    return X, f + np.exp(0.5 * g) * rng.standard_normal(n), f, g


def gauss_nlpd(y: np.ndarray, mean: np.ndarray, var: np.ndarray) -> float:
    return float(np.mean(0.5 * np.log(2 * np.pi * var) + 0.5 * (y - mean) ** 2 / var))


def fit_sklearn(X: np.ndarray, y: np.ndarray, evaluations: list[int] | None = None):
    """scikit-learn's GP, its default optimiser (one L-BFGS-B start). With ``evaluations``, the
    same L-BFGS-B call through a callable optimiser that counts the likelihood evaluations (appended)."""
    from sklearn.gaussian_process import GaussianProcessRegressor
    from sklearn.gaussian_process.kernels import RBF, ConstantKernel, WhiteKernel

    kernel = ConstantKernel(1.0) * RBF(length_scale=np.full(X.shape[1], 0.3 * X.std(axis=0).mean() + 1e-12)) \
        + WhiteKernel(0.1)
    from threadpoolctl import threadpool_limits  # installed with scikit-learn

    optimizer: Any = "fmin_l_bfgs_b"
    if evaluations is not None:
        from scipy.optimize import minimize

        def counted(obj_func, initial_theta, bounds):  # scikit-learn's own "fmin_l_bfgs_b" call, counted
            res = minimize(obj_func, initial_theta, method="L-BFGS-B", jac=True, bounds=bounds)
            evaluations.append(int(res.nfev))
            return res.x, res.fun

        optimizer = counted

    # One BLAS thread, as VHGPR.fit uses, so the times compare like with like.
    with warnings.catch_warnings(), threadpool_limits(limits=1, user_api="blas"):
        warnings.simplefilter("ignore")
        return GaussianProcessRegressor(kernel=kernel, normalize_y=True, random_state=0, optimizer=optimizer).fit(X, y)


def sklearn_evaluations(X: np.ndarray, y: np.ndarray, fitted) -> int:
    """Likelihood evaluations of scikit-learn's fit, counted in a second fit that must reach the
    same kernel as ``fitted`` (its default optimiser's); -1 if it does not."""
    counted: list[int] = []
    same = fit_sklearn(X, y, counted).kernel_.theta
    return counted[0] if len(counted) == 1 and np.allclose(same, fitted.kernel_.theta, rtol=0, atol=1e-9) else -1


def evaluation_columns(model, t_sk: float, sk_evals: int) -> str:
    """``init+runs`` evaluations of the VHGPR fit, scikit-learn's, and the time per evaluation of
    each (VHGPR: the median over its runs of each run's median bound evaluation, i.e. the run's own
    median where there is one run; scikit-learn: fit time / evaluations)."""
    init = (model.info.get("homoscedastic_init") or {}).get("evaluations", 0)
    times = [r["eval_time_median_s"] for r in model.info["runs"] if r.get("eval_time_median_s")]
    ms_vh = 1e3 * statistics.median(times) if times else float("nan")
    ms_sk = 1e3 * t_sk / sk_evals if sk_evals > 0 else float("nan")
    evals = f"{init}+{model.info['evaluations']}"
    return f"{evals:>10s} {sk_evals:>6d} {ms_vh:>8.2f} {ms_sk:>8.2f}"


def timed(fn, repeats: int):
    times, out = [], None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times), out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeats", type=int, default=3, help="repeats per fit for n <= 500 and mcycle (median)")
    ap.add_argument("--big-repeats", type=int, default=1, help="repeats for n > 500")
    ap.add_argument("--sizes", default="125,500,2000", help="synthetic training sizes")
    ap.add_argument("--no-sklearn", action="store_true", help="skip the scikit-learn baseline")
    ap.add_argument("--scale", default="", help="sizes of the 3-D scale section (e.g. 2000,5000,20000; empty: skip)")
    ap.add_argument("--stage-days", type=int, default=0, help="days of 200 moves of the stage section (0: skip)")
    ap.add_argument("--iter-sweep", default="", help="iteration caps of the sweep section (e.g. 20,40,60,100,200,400;"
                    " empty: skip)")
    args = ap.parse_args(argv)

    import scipy

    print(f"machine: {platform.platform()}, {platform.processor() or platform.machine()}, "
          f"cpu_count={os.cpu_count()}, python {platform.python_version()}, numpy {np.__version__}, "
          f"scipy {scipy.__version__}")
    try:
        import sklearn

        print(f"scikit-learn {sklearn.__version__}")
    except ImportError:
        args.no_sklearn = True
        print("scikit-learn not installed: baseline skipped")

    cases = []
    path = MCYCLE
    data = np.loadtxt(path, delimiter=",", skiprows=1)
    # each data set twice: the defaults (one restart at n > 500), and one start as scikit-learn's
    # (its optimiser runs once: n_restarts_optimizer=0), the restarts-matched comparison
    one_start = {"n_restarts": 1, "g_start": "f"}
    cases.append(("mcycle", data[:, :1], data[:, 1], data[:, :1], data[:, 1], None, None, args.repeats, {}))
    cases.append(("mcycle", data[:, :1], data[:, 1], data[:, :1], data[:, 1], None, None, args.repeats, one_start))
    Xt, yt, ft, gt = planted(2000, seed=1000)
    for n in (int(s) for s in args.sizes.split(",")):
        X, y, _, _ = planted(n, seed=n)
        big = n > 500
        reps = args.big_repeats if big else args.repeats
        cases.append(("synthetic", X, y, Xt, yt, ft, gt, reps, {"n_restarts": 1} if big else {}))
        cases.append(("synthetic", X, y, Xt, yt, ft, gt, reps, one_start))

    header = (f"{'data':10s} {'n':>5s} {'settings':24s} {'vhgpr s':>8s} {'sklearn s':>9s} {'ratio':>6s} "
              f"{'NLPD vhgpr':>10s} {'sklearn':>8s} {'oracle':>8s} {'vh-oracle':>9s} {'corr g':>7s} {'iters':>6s} "
              f"{'evals vh':>10s} {'sk':>6s} {'ms/ev vh':>8s} {'sk':>8s}")
    print()
    print(header)
    print("-" * len(header))
    sk_done: dict[tuple[str, int], tuple[float, float, int]] = {}  # one scikit-learn timing per data set
    for name, X, y, Xte, yte, fte, gte, reps, kw in cases:
        t_vh, model = timed(lambda: VHGPR(**kw).fit(X, y), reps)
        p = model.predict(Xte)
        nlpd_vh = gauss_nlpd(yte, p.y_mean, p.y_var)
        if args.no_sklearn:
            t_sk, nlpd_sk, sk_evals = float("nan"), float("nan"), -1
        elif (name, X.shape[0]) in sk_done:
            t_sk, nlpd_sk, sk_evals = sk_done[(name, X.shape[0])]
        else:
            t_sk, sk = timed(lambda: fit_sklearn(X, y), reps)
            m, s = sk.predict(Xte, return_std=True)
            nlpd_sk = gauss_nlpd(yte, m, s**2)
            sk_evals = sklearn_evaluations(X, y, sk)
            sk_done[(name, X.shape[0])] = (t_sk, nlpd_sk, sk_evals)
        if fte is not None:
            oracle = gauss_nlpd(yte, fte, np.exp(gte))
            corr = float(np.corrcoef(p.g_mean, gte)[0, 1])
        else:
            oracle, corr = float("nan"), float("nan")
        settings = ",".join(f"{k}={v}" for k, v in kw.items()) or "defaults"
        print(f"{name:10s} {X.shape[0]:5d} {settings:24s} {t_vh:8.2f} {t_sk:9.2f} {t_vh / t_sk:6.2f} "
              f"{nlpd_vh:10.4f} {nlpd_sk:8.4f} {oracle:8.4f} {nlpd_vh - oracle:9.4f} {corr:7.3f} "
              f"{model.info['iterations']:6d} {evaluation_columns(model, t_sk, sk_evals)}", flush=True)
    print()
    print("times: median wall-clock seconds of the fit (VHGPR includes its homoscedastic initialisation),"
          " both with one BLAS thread; ratio = vhgpr / sklearn; NLPD in nats on the hold-out set of 2000"
          " points (mcycle: train = test); corr g = correlation of the learned mean log noise variance"
          " with the true one; iters = L-BFGS-B iterations over all runs; n_restarts=1,g_start=f: one"
          " optimiser start, as scikit-learn's (restarts matched); evals vh = likelihood evaluations of"
          f" the homoscedastic initialisation (its {len(INIT_STARTS)} starts) + bound evaluations of the VHGPR"
          " runs, sk ="
          " scikit-learn's (counted in a second fit that reaches the same kernel; -1: it did not); ms/ev ="
          " milliseconds per evaluation (VHGPR: its runs' median bound evaluation, the median over runs;"
          " scikit-learn: fit time / evaluations). A fit's time is about evaluations x time per evaluation.")
    if args.iter_sweep:
        sweep_section([int(v) for v in args.iter_sweep.split(",")], data, (125, 500))
    if args.scale:
        scale_section([int(v) for v in args.scale.split(",")], args.no_sklearn)
    if args.stage_days:
        stage_section(args.stage_days)
    print(f"load average at the end: {' '.join(f'{v:.2f}' for v in os.getloadavg())}")
    return 0


def iteration_sweep(X: np.ndarray, y: np.ndarray, Xte: np.ndarray, yte: np.ndarray, caps: list[int]) -> list[dict]:
    """One-start fits (``n_restarts=1, g_start="f"``) with each iteration cap: the bound, the
    hold-out NLPD, the evaluations and the time. The runs share their start, so a larger cap
    continues the same L-BFGS-B path and the best bound found can only grow."""
    rows = []
    for cap in caps:
        t, model = timed(lambda: VHGPR(n_restarts=1, g_start="f", max_iter=cap).fit(X, y), 1)
        p = model.predict(Xte)
        rows.append({"cap": cap, "iterations": model.info["iterations"], "evaluations": model.info["evaluations"],
                     "bound": model.bound, "nlpd": gauss_nlpd(yte, p.y_mean, p.y_var), "time_s": t})
    return rows


def sweep_section(caps: list[int], mcycle: np.ndarray, sizes: tuple[int, ...]) -> None:
    """How the bound and the hold-out NLPD move with the iteration cap (mcycle, and the 1-D synthetic)."""
    Xt, yt, _, _ = planted(2000, seed=1000)
    sets = [("mcycle", mcycle[:, :1], mcycle[:, 1], mcycle[:, :1], mcycle[:, 1])]
    sets += [("synthetic", *planted(n, seed=n)[:2], Xt, yt) for n in sizes]
    print()
    print("iteration sweep: one start (n_restarts=1, g_start=f), max_iter = cap; one BLAS thread")
    header = f"{'data':10s} {'n':>5s} {'cap':>5s} {'iters':>6s} {'evals':>6s} {'bound':>10s} {'NLPD':>8s} {'fit s':>7s}"
    print(header)
    print("-" * len(header))
    for name, X, y, Xte, yte in sets:
        for r in iteration_sweep(X, y, Xte, yte, caps):
            print(f"{name:10s} {X.shape[0]:5d} {r['cap']:5d} {r['iterations']:6d} {r['evaluations']:6d} "
                  f"{r['bound']:10.4f} {r['nlpd']:8.4f} {r['time_s']:7.2f}", flush=True)
    print("bound: the MV bound of the fit (nats); NLPD as in the first table. The default cap is 100 up to"
          " n = 200, then fewer (microctl.gp.trainer.default_max_iter).")


def scale_section(sizes: list[int], no_sklearn: bool) -> None:
    """Exact (defaults, and with g_start="f"), scikit-learn (n <= 2000) and sparse on the 3-D synthetic."""
    from microctl.gp.sparse import SparseVHGPR, update

    Xt, yt, ft, gt = planted3d(2000, seed=999)
    oracle = gauss_nlpd(yt, ft, np.exp(gt))
    print()
    print(f"scale: 3-D synthetic (planted3d), hold-out 2000 points, oracle NLPD {oracle:.4f}; one BLAS thread")
    header = f"{'n':>6s} {'model':22s} {'fit s':>8s} {'NLPD':>8s} {'-oracle':>8s} {'corr g':>7s} {'update10 s':>10s}"
    print(header)
    print("-" * len(header))
    for n in sizes:
        X, y, _, _ = planted3d(n, seed=n + 7)
        rows = []
        if n <= 2000:
            rows.append(("exact (defaults)", lambda: VHGPR().fit(X, y)))
            rows.append(("exact (g_start=f)", lambda: VHGPR(g_start="f").fit(X, y)))
        rows.append(("sparse (M=256)", lambda: SparseVHGPR().fit(X, y)))
        for label, fit in rows:
            t, model = timed(fit, 1)
            p = model.predict(Xt)
            nl = gauss_nlpd(yt, p.y_mean, p.y_var)
            upd = ""
            if model.posterior_form == "sparse":
                Xn, yn, _, _ = planted3d(10, seed=n + 8)
                upd = f"{timed(lambda: update(model, Xn, yn), 5)[0]:10.3f}"
            print(f"{n:6d} {label:22s} {t:8.2f} {nl:8.4f} {nl - oracle:8.4f} "
                  f"{float(np.corrcoef(p.g_mean, gt)[0, 1]):7.3f} {upd:>10s}", flush=True)
        if n <= 2000 and not no_sklearn:
            t, sk = timed(lambda: fit_sklearn(X, y), 1)
            m, sd = sk.predict(Xt, return_std=True)
            nl = gauss_nlpd(yt, m, sd**2)
            print(f"{n:6d} {'scikit-learn':22s} {t:8.2f} {nl:8.4f} {nl - oracle:8.4f} {'':>7s} {'':>10s}", flush=True)
    print("fit s: wall-clock seconds of one fit (sparse: includes the exact fit of its hyperparameters on "
          "1000 points); update10 s: median of 5 updates with 10 new points; corr g: correlation of the "
          "learned mean log noise variance with the true one.")


def stage_section(days: int) -> None:
    """A simulated stage operated ``days`` x 200 moves: exact vs sparse residual models, NLPD, controller time."""
    import tempfile

    from microctl import api
    from microctl.control.controller import OptimalController
    from microctl.measurement.log import read_log
    from microctl.models.eafm import EAFM
    from microctl.models.training import ResidualModelSettings, residual_dataset, train_residual_model

    stage = api.load_stage(Path(__file__).resolve().parents[1] / "configs" / "stage" / "sim_paper.yaml")
    afm = stage.afm
    n = 200 * days
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        api.collect(stage, n, Path(tmp) / "log.csv", seed=11)
        api.collect(stage, 2000, Path(tmp) / "hold.csv", seed=12)
        log = read_log(Path(tmp) / "log.csv", stage.config.stage)
        hold = residual_dataset(read_log(Path(tmp) / "hold.csv", stage.config.stage), afm)
        data = residual_dataset(log, afm)
        collect_s = time.perf_counter() - t0
    print()
    print(f"stage: {stage.name}, {days} days x 200 moves = {n} training moves (collected with the hold-out's 2000 "
          f"in {collect_s:.1f} s); residual model with the train command's defaults; NLPD on the hold-out moves "
          "(µm); controller: CPU ms per solve, median over 15 targets in [4, 26] µm from the zero state, "
          "after one untimed pass over them")
    header = f"{'moves':>6s} {'model':10s} {'fit s':>8s} {'NLPD':>8s} {'inputs':>7s} {'ctl ms':>7s}"
    print(header)
    print("-" * len(header))
    sub = type(data)(X=data.X[:2000], y=data.y[:2000], x_names=data.x_names)
    cases = [(2000, "exact", sub), (2000, "sparse", sub)]
    if n > 2000:
        cases.append((n, "sparse", data))
    targets = np.linspace(4.0, 26.0, 15)
    for moves, form, d in cases:
        t0 = time.perf_counter()
        model = train_residual_model(d, afm, ResidualModelSettings(gp=form))
        fit_s = time.perf_counter() - t0
        ctl = OptimalController(EAFM(afm, model))
        state = stage.zero_state()
        for tg in targets:  # one untimed pass: builds what a solver builds at its first use (IPOPT, lazily)
            ctl.solve(float(tg), state)
        cpu = []
        for tg in targets:
            c0 = time.process_time()
            ctl.solve(float(tg), state)
            cpu.append(time.process_time() - c0)
        print(f"{moves:6d} {form:10s} {fit_s:8.1f} {model.nlpd(hold.X, hold.y):8.4f} {model.X.shape[0]:7d} "
              f"{1e3 * statistics.median(cpu):7.2f}", flush=True)
    print("inputs: the points the posterior holds (training moves, or inducing points).")


if __name__ == "__main__":
    sys.exit(main())
