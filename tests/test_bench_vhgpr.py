"""The evaluation counts of scripts/bench_vhgpr.py: what each fit's time is made of.

scikit-learn's count is checked against an independent count (its own likelihood method wrapped
during a default fit); the VHGPR's against its fit record, which tests/gp/test_vhgpr.py checks
against counted calls.
"""

from __future__ import annotations

import numpy as np
import pytest

from microctl.gp.vhgpr import VHGPR
from script_loader import load_script

pytest.importorskip("sklearn")
bench = load_script("bench_vhgpr")


def _data(n: int = 40) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(3)
    X = rng.uniform(0.0, 1.0, (n, 1))
    return X, np.sin(6.0 * X[:, 0]) + 0.1 * rng.standard_normal(n)


def test_sklearn_evaluations_equal_the_calls_of_its_default_fit(monkeypatch) -> None:
    from sklearn.gaussian_process import GaussianProcessRegressor

    X, y = _data()
    calls = {"n": 0}
    lml = GaussianProcessRegressor.log_marginal_likelihood

    def counted(self, theta=None, eval_gradient=False, clone_kernel=True):
        calls["n"] += bool(eval_gradient)  # the optimiser's calls; the fit's last one has no gradient
        return lml(self, theta, eval_gradient, clone_kernel)

    monkeypatch.setattr(GaussianProcessRegressor, "log_marginal_likelihood", counted)
    fitted = bench.fit_sklearn(X, y)
    default_calls = calls["n"]
    monkeypatch.undo()
    assert default_calls > 2
    assert bench.sklearn_evaluations(X, y, fitted) == default_calls


def test_evaluation_columns_read_the_fit_record() -> None:
    X, y = _data()
    model = VHGPR(n_restarts=1, g_start="f", max_iter=10).fit(X, y)
    cols = bench.evaluation_columns(model, t_sk=0.02, sk_evals=10).split()
    init, runs = (int(v) for v in cols[0].split("+"))
    assert init == model.info["homoscedastic_init"]["evaluations"] > 0
    assert runs == model.info["evaluations"] == model.info["runs"][0]["evaluations"]
    assert int(cols[1]) == 10
    assert float(cols[2]) == pytest.approx(1e3 * model.info["runs"][0]["eval_time_median_s"], abs=0.006)
    assert float(cols[3]) == pytest.approx(2.0)
    assert bench.evaluation_columns(model, t_sk=0.02, sk_evals=-1).split()[3] == "nan"


def test_iteration_sweep_continues_one_path() -> None:
    """Larger caps continue the same L-BFGS-B path from the same start: no more iterations than the
    cap, and the bound found never falls as the cap grows (a sweep whose rows were unrelated fits
    could not be read as "what the cap gives up")."""
    X, y = _data(50)
    rows = bench.iteration_sweep(X, y, X, y, [2, 5, 10, 20])
    assert [r["cap"] for r in rows] == [2, 5, 10, 20]
    for r in rows:
        assert 1 <= r["iterations"] <= r["cap"] and np.isfinite(r["nlpd"]) and r["time_s"] > 0.0
    bounds = [r["bound"] for r in rows]
    assert all(b1 >= b0 for b0, b1 in zip(bounds, bounds[1:]))
    assert bounds[-1] > bounds[0]
