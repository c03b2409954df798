#!/usr/bin/env python
"""Benchmark the VHGPR trainer against scikit-learn's homoscedastic GP.

For the motorcycle data (all 133 points as train and test, the authors' protocol) and for
synthetic data with a known mean and noise function (n = 125, 500, 2000 training points,
a separate seeded hold-out set of 2000 points), report the median fit time over a few
repeats and the mean negative log predictive density (NLPD, Gaussian predictive) of

* microctl's VHGPR (default settings; one optimisation run for n = 2000),
* scikit-learn ``GaussianProcessRegressor(C * RBF + WhiteKernel, normalize_y=True)``,
* for synthetic data, the oracle that knows the true mean and noise,

plus the correlation of the learned mean log-noise with the true one.

Usage: ``python scripts/bench_vhgpr.py [--repeats 3] [--sizes 125,500,2000]``.
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

import numpy as np

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


def gauss_nlpd(y: np.ndarray, mean: np.ndarray, var: np.ndarray) -> float:
    return float(np.mean(0.5 * np.log(2 * np.pi * var) + 0.5 * (y - mean) ** 2 / var))


def fit_sklearn(X: np.ndarray, y: np.ndarray):
    from sklearn.gaussian_process import GaussianProcessRegressor
    from sklearn.gaussian_process.kernels import RBF, ConstantKernel, WhiteKernel

    kernel = ConstantKernel(1.0) * RBF(length_scale=np.full(X.shape[1], 0.3 * X.std(axis=0).mean() + 1e-12)) \
        + WhiteKernel(0.1)
    from threadpoolctl import threadpool_limits  # installed with scikit-learn

    # One BLAS thread, as VHGPR.fit uses, so the times compare like with like.
    with warnings.catch_warnings(), threadpool_limits(limits=1, user_api="blas"):
        warnings.simplefilter("ignore")
        return GaussianProcessRegressor(kernel=kernel, normalize_y=True, random_state=0).fit(X, y)


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
    cases.append(("mcycle", data[:, :1], data[:, 1], data[:, :1], data[:, 1], None, None, args.repeats, {}))
    Xt, yt, ft, gt = planted(2000, seed=1000)
    for n in (int(s) for s in args.sizes.split(",")):
        X, y, _, _ = planted(n, seed=n)
        big = n > 500
        cases.append(("synthetic", X, y, Xt, yt, ft, gt, args.big_repeats if big else args.repeats,
                      {"n_restarts": 1} if big else {}))

    header = (f"{'data':10s} {'n':>5s} {'settings':14s} {'vhgpr s':>8s} {'sklearn s':>9s} {'ratio':>6s} "
              f"{'NLPD vhgpr':>10s} {'sklearn':>8s} {'oracle':>8s} {'vh-oracle':>9s} {'corr g':>7s} {'iters':>6s}")
    print()
    print(header)
    print("-" * len(header))
    for name, X, y, Xte, yte, fte, gte, reps, kw in cases:
        t_vh, model = timed(lambda: VHGPR(**kw).fit(X, y), reps)
        p = model.predict(Xte)
        nlpd_vh = gauss_nlpd(yte, p.y_mean, p.y_var)
        if args.no_sklearn:
            t_sk, nlpd_sk = float("nan"), float("nan")
        else:
            t_sk, sk = timed(lambda: fit_sklearn(X, y), reps)
            m, s = sk.predict(Xte, return_std=True)
            nlpd_sk = gauss_nlpd(yte, m, s**2)
        if fte is not None:
            oracle = gauss_nlpd(yte, fte, np.exp(gte))
            corr = float(np.corrcoef(p.g_mean, gte)[0, 1])
        else:
            oracle, corr = float("nan"), float("nan")
        settings = ",".join(f"{k}={v}" for k, v in kw.items()) or "defaults"
        print(f"{name:10s} {X.shape[0]:5d} {settings:14s} {t_vh:8.2f} {t_sk:9.2f} {t_vh / t_sk:6.2f} "
              f"{nlpd_vh:10.4f} {nlpd_sk:8.4f} {oracle:8.4f} {nlpd_vh - oracle:9.4f} {corr:7.3f} "
              f"{model.info['iterations']:6d}", flush=True)
    print()
    print("times: median wall-clock seconds of the fit (VHGPR includes its homoscedastic initialisation),"
          " both with one BLAS thread; ratio = vhgpr / sklearn; NLPD in nats on the hold-out set of 2000"
          " points (mcycle: train = test); corr g = correlation of the learned mean log noise variance"
          " with the true one; iters = L-BFGS-B iterations over all runs.")
    print(f"load average at the end: {' '.join(f'{v:.2f}' for v in os.getloadavg())}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
