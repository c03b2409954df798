"""``microctl diagnose`` end to end: show, name, extend, measure the gain.

:func:`run_diagnosis` answers the four questions of shared/spec/diagnosis.md on one
measurement run and returns a :class:`Diagnosis` (the report as plain data, the extended
config, and the arrays the figures need). Every decision uses the same per-test level
α/4 (α = 1e-3 by default), so that the discrepancy p-value — the Bonferroni minimum over
its four tests — is below α whenever a cause is accepted, and the false-positive rate on
clean data is at most α per run.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from typing import Callable

import numpy as np

from microctl.diagnosis.causes import fit_mean
from microctl.diagnosis.control import control_comparison
from microctl.diagnosis.data import DiagnosisData
from microctl.diagnosis.flexible import Flexible, GuardResult, Leftover, guard, leftover
from microctl.diagnosis.gain import GainResult, prediction_gain
from microctl.diagnosis.history import (
    extra_basis,
    history_findings,
    hysteresis_estimate,
)
from microctl.diagnosis.noise import NoiseSelection, select_noise
from microctl.diagnosis.outliers import (
    RowTest,
    extreme_rows,
    row_test,
    screen,
    suspect_cells,
)
from microctl.diagnosis.residuals import (
    Test,
    breusch_pagan,
    gp_inputs,
    gp_lr_test,
    where_analysis,
)
from microctl.diagnosis.selection import (
    Selection,
    backward,
    select_mean_causes,
    withdraw,
)
from microctl.diagnosis.separate import MAX_SEPARATED, separating_design
from microctl.models.afm import AnalyticForwardModel
from microctl.stage.causes import ActuatorFriction
from microctl.stage.config import StageConfig
from microctl.util.blas import single_thread_blas

#: Overall significance level of a diagnosis (per run).
ALPHA = 1e-3

#: Number of tests the discrepancy p-value combines (Bonferroni).
N_DISCREPANCY_TESTS = 4


@dataclass(frozen=True, eq=False)
class Diagnosis:
    """Everything a diagnosis found.

    Attributes
    ----------
    report : dict
        report.json content (shared/spec/diagnosis.md fields and more).
    extended_config : StageConfig
        The input config with the accepted causes in ``stage.corrections`` (mean causes, and
        the accepted stick-slip actuators as ``actuator_friction``).
    data : DiagnosisData
    afm_residual, model_residual, final_residual : ndarray (n,)
        Residual of the AFM, of the configured model through the physics, and of the
        extended model.
    selection : Selection
    noise : NoiseSelection
    gain : GainResult or None
    """

    report: dict
    extended_config: StageConfig
    data: DiagnosisData
    afm_residual: np.ndarray
    model_residual: np.ndarray
    final_residual: np.ndarray
    selection: Selection
    noise: NoiseSelection
    gain: GainResult | None
    extras: dict = field(default_factory=dict)


def _sensitivity(fit, data: DiagnosisData) -> np.ndarray:
    return fit.model().predict_data(data).sensitivity


#: Most rounds of "name causes on the rows kept, test every row" before the outlier set is taken as it is.
MAX_OUTLIER_PASSES = 3


@dataclass(frozen=True, eq=False)
class Named:
    """Question 2 on one set of rows: the causes, the noise model and what is left.

    Attributes
    ----------
    sel : Selection
        Mean causes (after the guard's withdrawals).
    noise : NoiseSelection
    weights : ndarray (n,) or None
        1/std per row when friction was accepted (weighted least squares).
    left : Leftover
        Structure left after the causes (``unexplained`` when significant).
    guard : GuardResult or None
        The causes re-tested alongside the flexible term (run when structure is left).
    """

    sel: Selection
    noise: NoiseSelection
    weights: np.ndarray | None
    left: Leftover
    guard: GuardResult | None


def _leftover(sel, data, w0, weights, a_each, seed) -> Leftover:
    """Structure left after ``sel``'s causes (the periodic scan on their predicted reading)."""
    return leftover((data.t - sel.final.pred) * w0, data, sel.final.k, weights, alpha=a_each, seed=seed,
                    reading=sel.final.pred)


def _name(stage, data: DiagnosisData, a_each: float, seed: int, progress) -> Named:
    """Mean causes, noise causes, leftover structure and the guard, on ``data``."""
    sel = select_mean_causes(stage, data, alpha=a_each, progress=progress)
    noise = select_noise(data.t - sel.final.pred, _sensitivity(sel.final, data), data.dq, data.u, alpha=a_each)
    weights = None
    if noise.fit.friction:  # heteroscedastic: feasible weighted least squares, pass 2
        weights = 1.0 / np.sqrt(noise.fit.var)
        sel = select_mean_causes(stage, data, alpha=a_each, weights=weights, progress=progress)
        noise = select_noise(data.t - sel.final.pred, _sensitivity(sel.final, data), data.dq, data.u, alpha=a_each)
    # every cause must still pay once the others are in the model (greedy forward steps can leave
    # an early small one redundant)
    drop = backward(sel, stage, data, weights=weights, alpha=a_each)
    if drop:
        sel = withdraw(sel, drop, stage, data, weights=weights,
                       reason="does not pay once the other accepted causes are in the model")
    w0 = np.ones(data.n) if weights is None else weights
    left = _leftover(sel, data, w0, weights, a_each, seed)
    grd = None
    if left.significant and sel.accepted:
        # structure is left: a cause must still pay alongside the flexible term, or it is withdrawn
        grd = guard(stage, data, sel.final, left, weights=weights, alpha=a_each)
        if grd.withdrawn:
            sel = withdraw(sel, grd.withdrawn, stage, data, weights=weights,
                           reason="the flexible term (generic basis, the significant history or periodic regressors, GP) "
                                  "explains its contribution as well")
            left = _leftover(sel, data, w0, weights, a_each, seed)
    if sel.final.unphysical:
        # after a withdrawal the others lift a ball, which none of them may: they are not these causes
        sel = withdraw(sel, [sp.key for sp in sel.accepted], stage, data, weights=weights,
                       reason="without the withdrawn causes, these lift a ball off, which none of them may")
        left = _leftover(sel, data, w0, weights, a_each, seed)
    if left.significant:
        # the noise causes are fitted on what the mean model *and* the flexible term leave: structure
        # is not scatter
        r = data.t - sel.final.pred
        extra = extra_basis(data, left.f_test.details.get("tests", []), sel.final.pred, a_each / 2)
        r = r - Flexible.fit(data, np.ones(data.n, dtype=bool), r, left.gp if weights is None else None, extra).values
        noise = select_noise(r, _sensitivity(sel.final, data), data.dq, data.u, alpha=a_each)
    return Named(sel, noise, weights, left, grd)


def _test_rows(named: Named, data: DiagnosisData, keep: np.ndarray, a_each: float) -> tuple[RowTest, np.ndarray]:
    """The outlier test on every row of ``data`` for a model named on the rows ``keep``.

    Returns the test and the flexible term's values (zero when no structure is left)."""
    fit = named.sel.final
    pred = fit.model().predict_data(data)
    r = data.t - (pred.t + fit.zero_um)
    smooth, var_f = np.zeros(data.n), np.zeros(data.n)
    if named.left.significant:
        gp = named.left.gp if named.weights is None else None  # a weighted GP is in other units: basis only
        extra = extra_basis(data, named.left.f_test.details.get("tests", []), pred.t + fit.zero_um, a_each / 2)
        flex = Flexible.fit(data, keep, r[keep], gp, extra)
        smooth, var_f = flex.values, flex.var
    std = np.sqrt(named.noise.fit.variance(pred.sensitivity, data.dq) + var_f)
    test = row_test(r - smooth, std, keep, a_each)
    if named.left.significant:
        # the flexible term only approximates structure no cause names (it extrapolates poorly at
        # the corners of the workspace): a row is an outlier only if it is also extreme against the
        # spread of that structure (robust z of the residual itself)
        test = replace(test, outlier=test.outlier & extreme_rows(r[keep], r, a_each))
    return test, smooth


def run_diagnosis(
    config: StageConfig,
    data: DiagnosisData,
    *,
    holdout: DiagnosisData | None = None,
    seed: int = 0,
    alpha: float = ALPHA,
    gain: bool = True,
    gp: bool = True,
    folds: int = 5,
    progress: Callable[[str], None] | None = None,
    set_aside: np.ndarray | None = None,
) -> Diagnosis:
    """Diagnose one run.

    Parameters
    ----------
    config : StageConfig
        The stage model the data is compared with (its corrections are kept).
    data : DiagnosisData
    holdout : DiagnosisData, optional
        Separate data for the gain (default: cross-validation).
    seed : int
        Seeds the folds and the GP fits.
    alpha : float
        Overall significance level (each test and acceptance uses α/4).
    gain : bool
        Measure the held-out gain (question 4).
    gp : bool
        Include the GP variants in the gain.
    folds : int
    progress : callable(str), optional
        Called after each unit of work.
    set_aside : ndarray of bool, shape (n,), optional
        Rows known to be corrupt before any fit (a log's implausible rows,
        :func:`microctl.measurement.log.implausible_rows`): always outliers, never fitted.

    Returns
    -------
    Diagnosis
    """
    with single_thread_blas():
        return _run(config, data, holdout=holdout, seed=seed, alpha=alpha, gain=gain, gp=gp, folds=folds,
                    progress=progress, set_aside=set_aside)


def _run(config, data, *, holdout, seed, alpha, gain, gp, folds, progress, set_aside=None) -> Diagnosis:
    t_start = time.perf_counter()
    timing = {}
    stage = config.stage
    a_each = alpha / N_DISCREPANCY_TESTS
    afm = AnalyticForwardModel(stage)
    all_data = data

    op = _outlier_passes(stage, all_data, set_aside, a_each, seed, progress)
    data, named = op.data, op.named
    sel, noise, weights, left = named.sel, named.noise, named.weights, named.left
    afm_resid = data.t - afm.t_of(data.u)
    model_resid = data.t - sel.baseline.pred
    resid = data.t - sel.final.pred
    timing["name_s"] = time.perf_counter() - t_start

    tests0, p_disc, significant = _show(data, named, model_resid, alpha, seed)

    # ---- unexplained structure left over ---------------------------------------------------------
    p_left = left.p_value
    unexplained = bool(significant and left.significant)
    timing["show_s"] = time.perf_counter() - t_start - timing["name_s"]
    findings = _findings(left, unexplained, data, sel, a_each)
    accepted_mean, mean_entries = _mean_causes(sel, left, unexplained, findings)

    ext_cfg = _extend(config, sel, noise)

    separation = _separation(stage, sel, noise.fit.std_um, seed, timing)
    g, control = None, None
    if gain:
        g, control = _gain(config, ext_cfg, data, named, timing, holdout=holdout, folds=folds, seed=seed, gp=gp,
                           progress=progress)
    timing["total_s"] = time.perf_counter() - t_start

    where = where_analysis(afm_resid, data, stage.actuator_names, stage.dof, stage.tool.name)
    report = {
        "rows": all_data.n,
        "rows_fitted": data.n,
        "source": data.source,
        "discrepancy": {
            "significant": significant,
            "afm_rmse_um": float(np.sqrt(np.mean(afm_resid**2))),
            "model_rmse_um": float(np.sqrt(np.mean(model_resid**2))),
            "extended_rmse_um": float(np.sqrt(np.mean(resid**2))),
            "noise_std_um": float(noise.fit.std_um),
            "p_value": p_disc,
            "alpha": alpha,
            "test": ("Bonferroni minimum of: F-tests of the model residual against generic bases, "
                     "best-cause likelihood ratio, GP-vs-white-noise likelihood ratio, Breusch-Pagan on abs(Δq)"),
            "tests": [t.to_dict() for t in tests0],
            "where": where,
            "heteroscedasticity": tests0[3].to_dict(),
        },
        "accepted": {"mean": accepted_mean, "noise": list(noise.accepted)},
        "mean_causes": mean_entries,
        "noise_causes": noise.entries,
        "noise_summary": _noise_summary(sel, noise, data),
        "selection": _selection_section(sel, weights),
        "unexplained": {"significant": unexplained, "p_value": p_left, "tests": left.tests(),
                        "depends_on": findings["depends_on"] if unexplained else None,
                        "history": bool(unexplained and findings["history"]),
                        "periodic": bool(unexplained and findings["periodic"]),
                        "history_tests": findings["tests"], "hysteresis": findings.get("hysteresis"),
                        "guard": None if named.guard is None else named.guard.to_dict()},
        "outliers": _outliers_section(op, all_data, afm, stage),
        "separation": separation,
        "noise_tests": {"heteroscedasticity": noise.heteroscedasticity.to_dict(), "leftover": noise.leftover.to_dict()},
        "nuisance": _nuisance_section(sel),
        "corrections": ext_cfg.stage.corrections.to_dict(),
        "physics_nuisance": ({k: float(v) for k, v in sel.final.nuisance.items()} if sel.final.nuisance else None),
        "timing_s": timing,
    }
    if g is not None:
        report["gain"] = g.to_dict()
    if control is not None:
        report["control"] = control
    return Diagnosis(report, ext_cfg, data, afm_resid, model_resid, resid, sel, noise, g,
                     {"all_data": all_data, "outliers": op.out_mask, "named": named, "smooth": op.smooth})


@dataclass(frozen=True)
class _OutlierPasses:
    """What :func:`_outlier_passes` found: the fitted rows, the named model on them, the row tests."""

    data: DiagnosisData
    named: Named
    rows: RowTest
    smooth: np.ndarray
    out_mask: np.ndarray
    passes: list
    converged: bool


def _outlier_passes(stage, all_data, set_aside, a_each, seed, progress) -> _OutlierPasses:
    """Outliers: set aside by a robust screen, then name on the rest and test every row, until
    the outlier set repeats (at most :data:`MAX_OUTLIER_PASSES` passes)."""
    forced = np.zeros(all_data.n, dtype=bool) if set_aside is None else np.asarray(set_aside, dtype=bool)
    sane = all_data.subset(np.flatnonzero(~forced))  # rows set aside never enter a fit
    configured = fit_mean(stage, stage.corrections, [], sane)
    out_mask = forced.copy()
    out_mask[~forced] = screen(sane.t - configured.pred, sane, a_each)
    passes = []
    for _ in range(MAX_OUTLIER_PASSES):
        keep = ~out_mask
        data = all_data.subset(np.flatnonzero(keep))
        named = _name(stage, data, a_each, seed, progress)
        rows, smooth = _test_rows(named, all_data, keep, a_each)
        passes.append(int(out_mask.sum()))
        converged = bool(np.array_equal(rows.outlier | forced, out_mask))
        if converged:
            break
        out_mask = rows.outlier | forced
    return _OutlierPasses(data, named, rows, smooth, out_mask, passes, converged)


def _show(data, named, model_resid, alpha, seed) -> tuple[list, float, bool]:
    """1. show: significance of the discrepancy (Bonferroni minimum of the four tests).

    Returns the tests (structure F-test, best-cause LR, GP LR, Breusch-Pagan), the p-value and
    whether the discrepancy is significant."""
    sel, noise, weights = named.sel, named.noise, named.weights
    w0 = np.ones(data.n) if weights is None else weights
    f_test0 = sel.steps[0].structure
    lr_best0 = Test("best candidate likelihood ratio (Bonferroni over candidates)",
                    float("nan"), float(sel.steps[0].p_value), ())
    het0 = breusch_pagan(model_resid, np.abs(data.dq), "Breusch-Pagan (Koenker) of r² on abs(Δq_i)")
    if min(f_test0.p_value, lr_best0.p_value, het0.p_value) < 1e-12:
        # already conclusive: the GP test could only lower the minimum (saves a GP fit)
        gp0 = Test("GP likelihood ratio against white noise (not run: other tests conclusive)", float("nan"), 1.0)
    else:
        gp0, _ = gp_lr_test(model_resid * w0, gp_inputs(data), seed=seed)
    tests0 = [f_test0, lr_best0, gp0, het0]
    p_disc = float(min(1.0, N_DISCREPANCY_TESTS * min(t.p_value for t in tests0)))
    significant = bool(p_disc < alpha or sel.accepted or noise.fit.friction)
    return tests0, p_disc, significant


def _mean_causes(sel, left, unexplained: bool, findings: dict) -> tuple[list, list]:
    """The accepted mean causes and the report's entries, with ``unexplained`` after the accepted ones
    (with ``depends_on``: the sentence of :func:`~microctl.diagnosis.history.history_findings`)."""
    mean_entries = list(sel.entries)
    accepted_mean = [s.cause for s in sel.accepted]
    if unexplained:
        accepted_mean.append("unexplained")
        mean_entries.insert(len(sel.accepted), {
            "cause": "unexplained", "params": {}, "stderr": {}, "delta_bic": None, "p_value": left.p_value,
            "equivalent": [], "accepted": True, "tests": left.tests(),
            "depends_on": findings["depends_on"], "history": findings["history"], "periodic": findings["periodic"],
        })
    return accepted_mean, mean_entries


def _extend(config, sel, noise):
    """3. extend: the extended stage config.

    The accepted causes, and the stage-physics nuisances fitted with them (e.g. the preload
    compression of a contact loss): the extended model needs both to reproduce the fit; and the
    accepted noise causes (stick-slip per actuator): the residual model's noise features
    (microctl.models.training.noise_features_for), so the extended EAFM's controller uses them.
    """
    friction = tuple(ActuatorFriction(actuator=int(a), std_per_um=float(sd))
                     for a, sd in zip(noise.fit.friction, noise.fit.std_per_um))
    ext_effects = sel.final.effects.with_(*friction) if friction else sel.final.effects
    return replace(config, stage=replace(sel.final.stage, corrections=ext_effects))


def _gain(config, ext_cfg, data, named, timing: dict, *, holdout, folds, seed, gp, progress):
    """4. gain: the held-out prediction gain, and (when the extension changes the stage) what it
    changes in control terms. Adds ``gain_s`` (and ``control_s``) to ``timing``."""
    sel, noise = named.sel, named.noise
    t0 = time.perf_counter()
    g = prediction_gain(config.stage, data, sel.accepted, sel.final.theta, nuisance=sel.final.nuisance,
                        holdout=holdout, friction=noise.fit.friction,
                        folds=folds, seed=seed, gp=gp, progress=progress)
    timing["gain_s"] = time.perf_counter() - t0
    control = None
    if not ext_cfg.stage.corrections.is_empty():
        # what the extension changes in control terms: plain vs extended EAFM controller
        t0 = time.perf_counter()
        control = control_comparison(config, ext_cfg, data, seed=seed)
        timing["control_s"] = time.perf_counter() - t0
    return g, control


def _findings(left, unexplained: bool, data, sel, a_each: float) -> dict:
    """What the leftover depends on (:func:`~microctl.diagnosis.history.history_findings`), with the
    hysteresis loop it would be when the history is significant and ``unexplained`` is named."""
    findings = history_findings(left.f_test.details.get("tests", []), a_each / 2)
    return _with_loop(findings, data, sel) if unexplained and findings["history"] else findings


def _with_loop(findings: dict, data, sel) -> dict:
    """``findings`` with the hysteresis loop a history-dependent leftover would be
    (:func:`~microctl.diagnosis.history.hysteresis_estimate`) and a sentence on it."""
    est = hysteresis_estimate(data.t - sel.final.pred, data, _sensitivity(sel.final, data))
    if not est["actuators"]:
        return findings
    hw = ", ".join(f"{est['half_width_um'][str(a)]:.2f} µm on actuator {a}" for a in est["actuators"])
    return {**findings, "hysteresis": est,
            "depends_on": findings["depends_on"] + f" A Prandtl-Ishlinskii loop fitted to it has a half-width of {hw}"
                          f" (held-out RMSE {est['heldout_rmse_um']['without']:.3f} → "
                          f"{est['heldout_rmse_um']['with']:.3f} µm)."}


def _separation(stage, sel, sigma_um: float, seed: int, timing: dict) -> list[dict]:
    """Per accepted cause with equivalents: the recommended ``collect`` run that separates it from
    its nearest equivalents (:func:`~microctl.diagnosis.separate.separating_design`). Adds
    ``separation_s`` to ``timing``."""
    t0 = time.perf_counter()
    out = []
    for spec in sel.accepted:
        step = next((s for s in sel.steps if s.accepted and s.best == spec.key), None)
        if step is None or not step.equivalent:
            continue
        near = sorted(step.equivalent, key=lambda k: step.fits[k].rss)[:MAX_SEPARATED]
        for k in near:
            out.append({"cause": spec.key, "against": k,
                        **separating_design(stage, step.fits[spec.key], step.fits[k], sigma_um, seed=seed)})
    timing["separation_s"] = time.perf_counter() - t0
    return out


def _noise_summary(sel, noise, data) -> dict:
    """Share of the mean reading variance of each accepted noise cause (the printed noise line)."""
    J = _sensitivity(sel.final, data)
    share = {"homoscedastic": noise.fit.std_um**2}
    for j, a in enumerate(noise.fit.friction):
        share[f"actuator_friction[{a}]"] = float(np.mean((J[:, a - 1] * noise.fit.std_per_um[j] * data.dq[:, a - 1]) ** 2))
    tot = sum(share.values()) or 1.0
    share = {k: float(v / tot) for k, v in share.items()}
    return {"dominant": max(share, key=share.get), "variance_share": share,
            "note": "share of the mean reading variance over the moves (friction through the contact "
                    "sensitivity)"}


def _selection_section(sel, weights) -> dict:
    """The report's ``selection``: why the forward selection stopped and its steps."""
    return {
        "stop_reason": sel.stop_reason,
        "weighted": weights is not None,
        "steps": [
            {"best": s.best, "p_value": s.p_value, "accepted": s.accepted, "equivalent": list(s.equivalent),
             "structure_p_value": s.structure.p_value, "current_bic": s.current.bic,
             "best_bic": (s.fits[s.best].bic if s.best else None)}
            for s in sel.steps
        ],
    }


def _outliers_section(op: _OutlierPasses, all_data, afm, stage) -> dict:
    """The report's ``outliers``: every outlier row with its suspect cell, and the test."""
    out_mask, rows = op.out_mask, op.rows
    return {
        "rows": [{**ids, **cell, "z": float(rows.z[ids["index"]])} for ids, cell in
                 zip(all_data.row_ids(np.flatnonzero(out_mask)),
                     suspect_cells(all_data, afm.K, out_mask, stage.actuator_names, stage.tool.name))],
        "count": int(out_mask.sum()),
        "test": ("residual of the named model (less the flexible term where structure is left), "
                 "standardised by the noise model and the robust scale of the fitted rows; "
                 "Bonferroni over rows"),
        "critical_z": rows.critical,
        "passes": len(op.passes),
        "converged": op.converged,
        "note": "left out of every fit and of the RMSEs and tests below; index is 0-based, line is the "
                "CSV line (header = line 1)",
    }


def _nuisance_section(sel) -> dict:
    """The report's ``nuisance``: the gauge zero and the stage-physics nuisances with their errors."""
    return {
        "gauge_zero_um": float(sel.final.zero_um),
        "stderr": {"gauge_zero_um": float(sel.final.zero_se_um),
                   **{k: (float(v) if np.isfinite(v) else None) for k, v in sel.final.nuisance_se.items()}},
        **{k: float(v) for k, v in sel.final.nuisance.items()},
        "note": ("gauge_zero_um: constant offset of the readings (the gauge zero is one noisy reading at the "
                 "zero state); fitted in every mean model, not a stage cause, not written to extended.yaml. "
                 "Stage-physics nuisances fitted with a cause (preload_compression_um with contact_loss) are "
                 "written to extended.yaml's stage.physics"),
    }
