#!/usr/bin/env python
"""f's posterior variance: the feature form of its kernel against the dense form, timed and compared.

For each training size in ``--sizes`` (125, 500, 1000): ``n`` covering moves on sim_paper's
simulator and the residual model ``microctl train`` makes of them with the defaults
(``scripts/bench_solve.py``'s ``build_model``, its ``physical`` fit) (f's SE
part off once the data do not pay for it). The model's posterior is built twice,
``Posterior(model, f_form="dense")`` (``k** - ||L^-1 k||^2``, O(n^2) per point) and
``f_form="features"`` (:class:`~microctl.gp.posterior.Posterior`: O(n p)), and each is timed on

- ``numpy``: ``f_var_std`` at ``--points`` (1000) random standardised inputs (the controller's
  seeding evaluates such batches);
- ``casadi``: one evaluation of f's variance, its gradient and its Hessian at a random input
  (what IPOPT asks of the objective per iteration, exact Hessian), median over ``--evals``.

Also printed: the largest difference features - dense relative to the dense value, and the
largest interval width e(x*, x*) at those inputs (the feature form exceeds the exact variance
by at most that width and is never below it: ``tests/gp/test_f_variance_feature_form.py``).
Medians of ``--repeats`` (7) runs for NumPy. Single BLAS thread (as ``microctl`` runs).

Usage: ``python scripts/bench_posterior.py [--sizes 125,500,1000] [--points 1000] [--evals 200]``.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from microctl.cli import one_blas_thread  # noqa: E402

one_blas_thread(os.environ, sys.modules)

import casadi as ca  # noqa: E402
import numpy as np  # noqa: E402

from bench_solve import ROOT, build_model  # noqa: E402

from microctl.gp.posterior import Posterior  # noqa: E402
from microctl.models.afm import AnalyticForwardModel  # noqa: E402
from microctl.stage.config import load_stage_config  # noqa: E402


def casadi_timer(post: Posterior, d: int):
    x = ca.MX.sym("xs", d)
    v = post.casadi(x, ("f_var",))["f_var"]
    return ca.Function("f_var", [x], [v, ca.gradient(v, x), ca.hessian(v, x)[0]], ["xs"], ["f_var", "grad", "hess"])


def median_ms(fn, repeats: int) -> float:
    t = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        t.append(time.perf_counter() - t0)
    return 1e3 * float(np.median(t))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sizes", default="125,500,1000")
    ap.add_argument("--points", type=int, default=1000)
    ap.add_argument("--evals", type=int, default=200)
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    print(f"machine: {platform.platform()}, {platform.processor() or platform.machine()}, cpus={os.cpu_count()}, "
          f"python {platform.python_version()}, numpy {np.__version__}, casadi {ca.__version__}")
    print(f"points {args.points} (numpy batch), evals {args.evals} (casadi value + gradient + Hessian), "
          f"repeats {args.repeats}, seed {args.seed}\n")
    print(f"{'n':>5} {'p':>3} {'auto form':>9} {'numpy dense ms':>14} {'numpy feat ms':>13} {'ratio':>6} "
          f"{'casadi dense us':>15} {'casadi feat us':>14} {'ratio':>6} {'max rel diff':>12} {'max width':>10}")
    rng = np.random.default_rng(args.seed)
    afm = AnalyticForwardModel(load_stage_config(ROOT / "configs/stage/sim_paper.yaml").stage)
    for n in (int(s) for s in args.sizes.split(",") if s.strip()):
        model, _ = build_model(afm, n, args.seed, "physical", None)  # bench_solve's: collect + train defaults
        dense, feat = Posterior(model, f_form="dense"), Posterior(model, f_form="features")
        auto = "features" if Posterior(model).f_low_rank else "dense"
        X = dense.X
        xs = X[rng.integers(0, X.shape[0], args.points)] + 0.3 * rng.standard_normal((args.points, X.shape[1]))
        vd, vf = dense.f_var_std(xs), feat.f_var_std(xs)
        t_nd = median_ms(lambda: dense.f_var_std(xs), args.repeats)
        t_nf = median_ms(lambda: feat.f_var_std(xs), args.repeats)
        fd, ff = casadi_timer(dense, X.shape[1]), casadi_timer(feat, X.shape[1])
        pts = xs[: args.evals]
        fd(pts[0]), ff(pts[0])
        t_cd = 1e3 * median_ms(lambda: [fd(p) for p in pts], 3) / len(pts)
        t_cf = 1e3 * median_ms(lambda: [ff(p) for p in pts], 3) / len(pts)
        rel = float(np.max(np.abs(vf - vd) / np.abs(vd)))
        width = float(np.max(feat.f_kernel.se_remainder_diag(xs)))
        p = feat.f_kernel.feature_weights.size
        print(f"{n:>5} {p:>3} {auto:>9} {t_nd:>14.2f} {t_nf:>13.2f} {t_nd / t_nf:>6.1f} {t_cd:>15.1f} {t_cf:>14.1f} "
              f"{t_cd / t_cf:>6.1f} {rel:>12.2e} {width:>10.2e}")
    print("\nmax rel diff: max |features - dense| / dense over the points; max width: the largest e(x*, x*) there "
          "(standardised units: the output variance is 1)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
