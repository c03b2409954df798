"""Outlier tests, the flexible term's leave-one-out values and the report's clarity, against
independent answers (brute-force refits, known quantiles)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from conftest import CONFIGS

from microctl.diagnosis import outliers
from microctl.diagnosis.data import data_from_arrays
from microctl.diagnosis.flexible import Flexible
from microctl.diagnosis.outliers import (
    MAX_OUTLIER_FRACTION,
    critical_z,
    robust_residual,
    screen,
    tail_scale,
)
from microctl.diagnosis.residuals import fit_gp, generic_basis, gp_inputs
from microctl.stage.causes import ActuatorGain, ContactOffset, Effects
from microctl.stage.config import load_stage_config


def _run(n=150, seed=0):
    rng = np.random.default_rng(seed)
    u = np.column_stack([rng.uniform(0, 32, n), rng.uniform(-1, 1, n), rng.uniform(-1, 1, n)])
    q = rng.uniform(0, 32, (n, 4))
    return data_from_arrays(u, q, np.zeros(n), time_s=np.arange(1.0, n + 1)), rng


def test_critical_value_is_the_bonferroni_normal_quantile():
    # two-sided per row, Bonferroni over n: n · P(|Z| > z) = n · erfc(z / √2) = α (math.erfc, not scipy)
    for n in (100, 300):
        z = critical_z(n, 2.5e-4)
        assert n * math.erfc(z / math.sqrt(2.0)) == pytest.approx(2.5e-4, rel=1e-9)
    assert critical_z(300, 2.5e-4) == pytest.approx(4.927, abs=1e-3)


def test_robust_regression_ignores_gross_errors():
    """Bisquare IRLS: the fit of the clean rows (OLS on them) is recovered with 3 gross errors in."""
    data, rng = _run()
    B = generic_basis(data)
    beta = rng.normal(0, 1, B.shape[1])
    y = B @ beta + 0.05 * rng.standard_normal(data.n)
    bad = np.array([10, 70, 131])
    y_bad = y.copy()
    y_bad[bad] += [30.0, -12.0, 8.0]
    r, s = robust_residual(B, y_bad)
    clean = np.setdiff1d(np.arange(data.n), bad)
    coef, *_ = np.linalg.lstsq(B[clean], y[clean], rcond=None)
    np.testing.assert_allclose(y_bad - r, B @ coef, atol=0.02)  # the robust fit is the clean fit (±0.4 σ)
    assert s == pytest.approx(0.05, rel=0.3)  # MAD scale of the noise (n = 150, 44 columns)
    flags = screen(y_bad, data, 2.5e-4)  # the configured model's residual is y here
    assert np.flatnonzero(flags).tolist() == bad.tolist()


def test_tail_scale_is_one_for_gaussian_and_grows_with_heavy_tails():
    rng = np.random.default_rng(1)
    z = rng.standard_normal(20000)
    assert tail_scale(z) == pytest.approx(1.0, abs=0.03)
    t3 = rng.standard_t(3, 20000)  # heavier tails than its bulk says
    assert tail_scale(t3) > 1.15 * 1.4826 * np.median(np.abs(t3 - np.median(t3)))


def test_many_rows_beyond_the_critical_value_are_structure_not_outliers():
    rng = np.random.default_rng(2)
    n = 200
    r = 0.05 * rng.standard_normal(n)
    k = int(MAX_OUTLIER_FRACTION * n) + 1
    r[:k] += 5.0  # a region the model gets wrong
    assert not outliers.row_test(r, np.full(n, 0.05), np.ones(n, bool), 2.5e-4).outlier.any()
    r[:k] -= 5.0
    r[:2] += 5.0
    assert np.flatnonzero(outliers.row_test(r, np.full(n, 0.05), np.ones(n, bool), 2.5e-4).outlier).tolist() == [0, 1]


def test_flexible_term_leave_one_out_without_gp_equals_refits():
    data, rng = _run(120, seed=3)
    resid = np.sin(data.u[:, 1] * 2) + 0.05 * rng.standard_normal(data.n)
    fitted = np.ones(data.n, bool)
    fitted[5] = False  # one row left out of the fit: the fit's prediction there
    flex = Flexible.fit(data, fitted, resid[fitted], None)
    B = generic_basis(data)
    idx = np.flatnonzero(fitted)
    for k in (0, 17, 60):  # brute force: refit without row k
        others = idx[idx != k]
        coef, *_ = np.linalg.lstsq(B[others], resid[others], rcond=None)
        assert flex.values[k] == pytest.approx(B[k] @ coef, abs=1e-8)
    coef, *_ = np.linalg.lstsq(B[idx], resid[idx], rcond=None)
    assert flex.values[5] == pytest.approx(B[5] @ coef, abs=1e-8)


@pytest.mark.slow
def test_flexible_term_leave_one_out_with_gp_equals_conditioning_on_the_others():
    """R&W eq. 5.12 against conditioning the GP on the other rows (basis part held)."""
    data, rng = _run(80, seed=4)
    resid = 0.3 * np.sin(2 * data.u[:, 1]) + 0.05 * rng.standard_normal(data.n)
    gp = fit_gp(gp_inputs(data), resid)
    fitted = np.ones(data.n, bool)
    flex = Flexible.fit(data, fitted, resid, gp)
    B = generic_basis(data)
    coef, *_ = np.linalg.lstsq(B, resid, rcond=None)
    e = resid - B @ coef
    X = gp_inputs(data)
    for k in (3, 40):
        o = np.setdiff1d(np.arange(data.n), [k])
        K = gp.kernel(X[o]) + gp.noise_std_um**2 * np.eye(o.size)
        ks = gp.kernel(X[[k]], X[o])[0]
        mean = B[k] @ coef + ks @ np.linalg.solve(K, e[o])
        var = gp.signal_std_um**2 - ks @ np.linalg.solve(K, ks)
        assert flex.values[k] == pytest.approx(mean, abs=1e-8)
        assert flex.var[k] == pytest.approx(var, rel=1e-6, abs=1e-12)


# ---- report clarity ------------------------------------------------------------------------


@pytest.fixture(scope="module")
def offset_diagnosis():
    from microctl.diagnosis.pipeline import run_diagnosis
    from microctl.testing.plant import simulate

    cfg = load_stage_config(CONFIGS / "stage" / "table1.yaml")
    data = simulate(cfg, Effects(contact_offset=(ContactOffset(2, 1.0, -0.5),), actuator_gain=(ActuatorGain(3, 0.95),)),
                    160, seed=3)
    return run_diagnosis(cfg, data, gp=False, folds=2)


@pytest.mark.slow
def test_report_names_actuators_delta_bic_and_the_equivalence_it_refers_to(offset_diagnosis, tmp_path):
    from microctl.diagnosis.report import render_markdown, summary_lines, write_outputs
    from microctl.diagnosis.selection import DELTA_BIC

    rep = write_outputs(offset_diagnosis, tmp_path, figures=False)
    md = render_markdown(rep)
    assert "actuator_gain[3]" in md and DELTA_BIC in md
    item = next(i for i in rep["identifiability"] if i["cause"] in ("contact_offset", "tool_offset"))
    assert f"**Equivalent to the accepted `{item['key']}`" in md
    lines = summary_lines(rep)
    assert any("actuator_gain[3]" in line for line in lines)
    assert any("dominant noise cause homoscedastic" in line for line in lines)
    assert any("configured model RMSE" in line and "gauge-zero offset" in line for line in lines)
    # one ΔBIC: an accepted cause's value is its step's BIC change
    steps = rep["selection"]["steps"]
    first = next(e for e in rep["mean_causes"] if e.get("accepted"))
    assert first["delta_bic"] == pytest.approx(steps[0]["best_bic"] - steps[0]["current_bic"])


@pytest.mark.slow
def test_every_figure_axis_has_a_unit(offset_diagnosis, tmp_path, monkeypatch):
    pytest.importorskip("matplotlib")
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib.figure import Figure

    from microctl.diagnosis.figures import write_figures

    seen = []
    orig = Figure.savefig

    def spy(self, *a, **k):
        for ax in self.axes:
            if ax.axison:
                seen.append((ax.get_xlabel(), ax.get_ylabel()))
        return orig(self, *a, **k)

    monkeypatch.setattr(Figure, "savefig", spy)
    write_figures(offset_diagnosis, tmp_path)
    assert seen
    for xl, yl in seen:
        # a unit in parentheses, or a categorical axis named as such
        assert "(" in xl or xl in ("model",) or xl.startswith("actuator"), xl
        assert "(" in yl or yl.startswith("cause"), yl
