"""The flexible discrepancy term F, so that no cause is named for structure it does not explain.

F knows nothing about the vocabulary: the generic basis B of
:func:`~microctl.diagnosis.residuals.generic_basis` (least squares: cubic in the pose u, each
actuator's direction of approach and its products with u, cubic in time) plus a homoscedastic
SE-ARD GP on the pose, the time and the directions of approach
(:func:`~microctl.diagnosis.residuals.gp_inputs`; hyperparameters by marginal likelihood,
:func:`~microctl.diagnosis.residuals.fit_gp`) for smooth structure a cubic misses (a bump, a
periodic error, a warm-up with a time constant, a direction-dependent curvature). It is used three ways:

1. :func:`leftover` — after the accepted causes, is structure left? The F-test of the residual
   against B and the GP likelihood ratio against white noise (Bonferroni over the two). If so,
   the diagnosis names ``unexplained``.
2. :func:`guard` — when structure is left, every accepted cause is fitted again *alongside F*:
   the generalised least-squares F-test of the model with the cause against the model without
   it (refitted), both with B among the regressors and, as the residual covariance
   Σ = K_GP + σ²I, the GP fitted to what the model *without* the cause leaves beyond B (so that
   F has its chance to explain what the cause was fitted to). A cause whose contribution F explains as well (e.g. an
   actuator gain fitted to the linear part of a smooth bump) does not pay and is withdrawn:
   the structure it was fitted to is ``unexplained``, not that cause. When no structure is left
   F is not needed (its F-test is not significant), and each cause has paid its way against the
   model without it in the selection.
3. :meth:`Flexible.smooth` — F's fit to the leftover at every row (rows left out of the fit
   included), taken out of the residual before the outlier test, so that structure is not
   mistaken for outliers.

Linearisation: the causes enter the GLS test through their Jacobian at the fit (parameters and
nuisances), which :func:`~microctl.diagnosis.causes.fit_mean` returns; the model without the
cause is a full nonlinear refit.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property
from typing import Callable

import numpy as np
from scipy import stats
from scipy.linalg import cho_factor, cho_solve, solve_triangular

from microctl.diagnosis.causes import MeanFit, fit_mean
from microctl.diagnosis.data import DiagnosisData
from microctl.diagnosis.history import extra_basis
from microctl.diagnosis.residuals import (
    GPFit,
    Test,
    fit_gp,
    generic_basis,
    gp_inputs,
    gp_lr_test,
    structure_f_test,
)


@dataclass(frozen=True, eq=False)
class Leftover:
    """Structure left in a residual after the accepted causes.

    Attributes
    ----------
    significant : bool
        Bonferroni p-value of the two tests below the level.
    p_value : float
        2 × the smaller p-value (Bonferroni).
    f_test, gp_test : Test
        F-test against the generic basis; GP likelihood ratio against white noise.
    gp : GPFit or None
        When significant, the GP fitted to the residual after the basis (F's smooth part);
        fitted on first use (several L-BFGS starts, O(n^3)), as most leftovers are only tested.
    """

    significant: bool
    p_value: float
    f_test: Test
    gp_test: Test
    fit_gp: Callable[[], GPFit] | None = field(default=None, repr=False)

    @cached_property
    def gp(self) -> GPFit | None:
        return None if self.fit_gp is None else self.fit_gp()

    def tests(self) -> list[dict]:
        """Report form of the two tests."""
        return [self.f_test.to_dict(), self.gp_test.to_dict()]


def _ols_resid(X: np.ndarray, y: np.ndarray) -> np.ndarray:
    coef, *_ = np.linalg.lstsq(X, y, rcond=None)
    return y - X @ coef


def leftover(resid: np.ndarray, data: DiagnosisData, k_fitted: int, weights: np.ndarray | None, *,
             alpha: float, seed: int = 0, reading: np.ndarray | None = None) -> Leftover:
    """Test a (weighted) residual for structure F explains (:func:`structure_f_test`, :func:`gp_lr_test`).

    Parameters
    ----------
    resid : ndarray, shape (n,)
        Residual of the accepted causes, already multiplied by ``weights`` if given.
    data : DiagnosisData
    k_fitted : int
        Mean parameters fitted (gauge zero and nuisances included).
    weights : ndarray (n,), optional
        1/std per row.
    alpha : float
        Level of the combined test.
    seed : int
        Seeds the GP's subset (above :data:`~microctl.diagnosis.residuals.GP_MAX_POINTS` rows).
    reading : ndarray (n,), optional
        The model's predicted reading (the periodic scan of :func:`structure_f_test`).
    """
    f = structure_f_test(resid, data, k_fitted, weights, reading=reading)
    gp_t, _ = gp_lr_test(resid, gp_inputs(data), seed=seed)
    p = float(min(1.0, 2 * min(f.p_value, gp_t.p_value)))

    def fit_smooth_part() -> GPFit:
        B = generic_basis(data) * (1.0 if weights is None else weights[:, None])
        return fit_gp(gp_inputs(data), _ols_resid(B, resid), seed=seed)

    return Leftover(p < alpha, p, f, gp_t, fit_smooth_part if p < alpha else None)


@dataclass(frozen=True, eq=False)
class Flexible:
    """F fitted to a leftover, at every row of the run, as a row's prediction from the *other* rows.

    Attributes
    ----------
    data : DiagnosisData
        The whole run (rows left out of the fit included).
    fitted : ndarray of bool, shape (n,)
        Rows F was fitted on.
    values : ndarray, shape (n,)
        F at every row, µm: leave-one-out for the fitted rows, the fit's prediction for the others
        (so a row cannot explain itself, which matters for the outlier test).
    var : ndarray, shape (n,)
        Variance of that prediction (F's own uncertainty, noise excluded), µm².
    """

    data: DiagnosisData
    fitted: np.ndarray
    values: np.ndarray
    var: np.ndarray

    @classmethod
    def fit(cls, data: DiagnosisData, fitted: np.ndarray, resid: np.ndarray, gp: GPFit | None,
            extra: np.ndarray | None = None) -> "Flexible":
        """Fit F to ``resid`` (unweighted, µm) on the rows ``fitted`` of ``data``; evaluate everywhere.

        The basis is built on the whole run (its span does not depend on the standardisation)
        and fitted by least squares on ``fitted``; with a GP (hyperparameters ``gp``, from
        :func:`leftover`) the basis residual is conditioned on the GP. Leave-one-out values for
        the fitted rows: the GP's closed form (Rasmussen & Williams eq. 5.12) with the basis
        held, or the hat-matrix form e_k/(1 − h_kk) without a GP. ``extra`` (n, p): columns
        added to the basis (:func:`~microctl.diagnosis.history.extra_basis`: the history or
        periodic regressors whose leftover test is significant).
        """
        fitted = np.asarray(fitted, dtype=bool)
        B = generic_basis(data) if extra is None else np.hstack([generic_basis(data), extra])
        Bf = B[fitted]
        coef, *_ = np.linalg.lstsq(Bf, resid, rcond=None)
        values = B @ coef
        var = np.zeros(data.n)
        e = resid - values[fitted]
        if gp is None:
            # OLS leave-one-out: e_k / (1 − h_kk); F's variance there σ² h/(1 − h) (σ² from e)
            h = np.einsum("ij,ij->i", Bf, np.linalg.pinv(Bf).T)
            h = np.minimum(h, 0.99)
            s2 = float(e @ e) / max(fitted.sum() - np.linalg.matrix_rank(Bf), 1)
            loo = resid - e / (1.0 - h)
            values[fitted] = loo
            var[fitted] = s2 * h / (1.0 - h)
            return cls(data, fitted, values, var)
        X = gp_inputs(data)
        Xf = X[fitted]
        sn2 = gp.noise_std_um**2
        Kinv = cho_solve(cho_factor(gp.kernel(Xf) + sn2 * np.eye(int(fitted.sum())), lower=True),
                         np.eye(int(fitted.sum())))
        alpha = Kinv @ e
        Ks = gp.kernel(X, Xf)
        values = values + Ks @ alpha
        var = np.maximum(gp.signal_std_um**2 - np.einsum("ij,jk,ik->i", Ks, Kinv, Ks), 0.0)
        d = np.diag(Kinv)
        values[fitted] = resid - alpha / d  # e_k − (e_k − μ_−k) with the basis part held
        var[fitted] = np.maximum(1.0 / d - sn2, 0.0)
        return cls(data, fitted, values, var)


@dataclass(frozen=True, eq=False)
class GuardResult:
    """Each accepted cause re-tested alongside F.

    Attributes
    ----------
    tests : dict of str -> Test
        Per cause key: GLS F-test of the cause alongside F (p-value Bonferroni over the causes).
    withdrawn : list of str
        Keys of the causes F explains as well (not named).
    """

    tests: dict = field(default_factory=dict)
    withdrawn: list = field(default_factory=list)

    def to_dict(self) -> dict:
        """Report form."""
        return {"tests": {k: t.to_dict() for k, t in self.tests.items()}, "withdrawn": list(self.withdrawn)}


def _whitener(gp: GPFit | None, X: np.ndarray):
    """Lower Cholesky factor L of Σ = K_GP + σ²I (identity without a GP): solve(L, ·) whitens."""
    if gp is None:
        return None
    S = gp.kernel(X) + max(gp.noise_std_um, 1e-12) ** 2 * np.eye(len(X))
    return np.linalg.cholesky(S)


def _gls_rss(L: np.ndarray | None, X: np.ndarray, y: np.ndarray) -> tuple[float, int]:
    if L is not None:
        X = solve_triangular(L, X, lower=True)
        y = solve_triangular(L, y, lower=True)
    coef, _, rank, _ = np.linalg.lstsq(X, y, rcond=None)
    r = y - X @ coef
    return float(r @ r), int(rank)


def _alongside(stage, data: DiagnosisData, B: np.ndarray, w: np.ndarray, X_gp: np.ndarray, full: MeanFit,
               without: list, weights: np.ndarray | None) -> tuple[float, float, tuple, MeanFit]:
    """GLS F-test of ``full`` against the model with only the causes ``without`` (refitted), both
    with the basis B and the covariance of F's GP fitted to what the smaller model leaves beyond B.

    Returns (F, p, df, the smaller model's fit)."""
    split = {s.key: th for s, th, _ in full.split()}
    theta0 = np.concatenate([split[s.key] for s in without]) if without else None
    f0 = fit_mean(stage, stage.corrections, without, data, theta0=theta0, nuisance0=full.nuisance, weights=weights)
    r0, r1 = w * (data.t - f0.pred), w * (data.t - full.pred)
    X0 = np.hstack([B, w[:, None] * f0.jac])
    X1 = np.hstack([B, w[:, None] * full.jac])
    # F's GP fitted to what the smaller model leaves beyond the basis: F gets its chance to explain
    # what the extra causes were fitted to
    L = _whitener(fit_gp(X_gp, _ols_resid(X0, r0)), X_gp)
    q0, p0 = _gls_rss(L, X0, r0)
    q1, p1 = _gls_rss(L, X1, r1)
    df2 = data.n - p1
    if df2 < 5 or q1 <= 0:
        return float("nan"), 1.0, (0, df2), f0
    dk = max(p1 - p0, full.k - f0.k, 1)
    F = max(q0 - q1, 0.0) / dk / (q1 / df2)
    return float(F), float(stats.f.sf(F, dk, df2)), (dk, df2), f0


def guard(stage, data: DiagnosisData, final: MeanFit, left: Leftover, *, weights: np.ndarray | None,
          alpha: float) -> GuardResult:
    """Re-test the causes of ``final`` alongside F (see the module docstring).

    First all of them together against none (if they do not pay together, all are withdrawn);
    then each against the others (refitted), withdrawing the worst that does not pay and testing
    the rest again. Each test: :func:`_alongside`, at ``alpha`` (Bonferroni over the causes).

    Parameters
    ----------
    stage : Stage
        The configured stage (its corrections are the base of every fit).
    data : DiagnosisData
    final : MeanFit
        The accepted causes fitted jointly.
    left : Leftover
        The significant leftover of ``final`` (the reason F is needed).
    weights : ndarray (n,), optional
        1/std per row (the fits' weights).
    alpha : float
        Level of each test.

    Returns
    -------
    GuardResult
    """
    if not final.specs:
        return GuardResult()
    w = np.ones(data.n) if weights is None else weights
    # F with the history / periodic regressors whose leftover test is significant: a cause fitted to
    # part of a hysteresis loop or a gauge ripple is withheld if F explains it as well
    extra = extra_basis(data, left.f_test.details.get("tests", []), final.pred, alpha / 2)
    B = np.hstack([generic_basis(data), extra]) * w[:, None]
    X_gp = gp_inputs(data)
    out = GuardResult()
    name = "GLS F-test alongside the flexible term (generic basis + GP)"
    F, p, df, _ = _alongside(stage, data, B, w, X_gp, final, [], weights)
    out.tests["all"] = Test(name + ": all accepted causes against none", F, p, df)
    if p >= alpha:
        out.withdrawn.extend(s.key for s in final.specs)
        return out
    current = final
    while len(current.specs) > 1:
        m = len(current.specs)
        worst, worst_p, worst_fit = None, -1.0, None
        for spec in current.specs:
            F, p, df, f0 = _alongside(stage, data, B, w, X_gp, current, [s for s in current.specs if s is not spec],
                                      weights)
            p = float(min(1.0, p * m))
            out.tests[spec.key] = Test(name + ": the cause against the others", F, p, df)
            if p > worst_p:
                worst, worst_p, worst_fit = spec, p, f0
        if worst_p < alpha:
            break
        out.withdrawn.append(worst.key)
        current = worst_fit
    return out
