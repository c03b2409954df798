"""Mean causes of the registry fitted as physical changes of the stage model, by NLS.

Every mean cause of :data:`microctl.stage.causes.REGISTRY` (kinds ``static`` and ``dynamic``) is a
candidate, per actuator for per-actuator causes: a :class:`CauseSpec` wraps the registry class
with the actuator, its search bounds for the stage and its starting grid. A set of causes with
parameters θ gives a prediction t̂(θ) by the stage model
(:class:`~microctl.models.extended.ExtendedForwardModel`, the simulator's own model object): a cause is
never a curve fitted to the AFM residual. θ is fitted by nonlinear least squares
(``scipy.optimize.least_squares``, trust-region reflective, bounds), optionally weighted by
1/std of a fitted noise model.

Nuisances: a cause may declare stage-physics numbers its prediction depends on that the config
may have wrong (:attr:`microctl.stage.causes.Cause.nuisance`; ``contact_loss``: the preload compression,
because where a lowered ball unloads depends on the gap relative to it). They are fitted with the
cause, shared by every cause that declares them, counted as parameters, and reported apart.

Standard errors are from the Jacobian at the optimum: Cov θ = σ̂² (JᵀJ)⁻¹, σ̂² = RSS/(n − k);
a Fisher matrix JᵀJ whose smallest singular value is below 1e-10 of the largest is rank
deficient (the parameters are not identifiable from this data) and gets infinite standard
errors for the parameters in its null space.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Sequence

import numpy as np
from scipy.optimize import least_squares

from microctl.diagnosis.data import DiagnosisData
from microctl.errors import SolveError
from microctl.models.extended import ExtendedForwardModel
from microctl.stage.causes import (
    MEAN_KINDS,
    REGISTRY,
    Cause,
    Effects,
    Nuisance,
    nuisances,
)
from microctl.stage.geometry import Stage

#: Relative tolerances of the least-squares fits (parameters to ~1e-8 of their scale: far below
#: any standard error).
FIT_TOL = 1e-8

#: Smallest singular value ratio of JᵀJ treated as full rank.
RANK_TOL = 1e-10


@dataclass(frozen=True)
class CauseSpec:
    """One candidate mean cause: a registry class on one actuator (if per-actuator), for a stage.

    Attributes
    ----------
    cls : type of Cause
        The registry class.
    actuator : int or None
        1-based actuator for per-actuator causes.
    lower, upper : tuple of float
        Search bounds of the parameters for this stage.
    grid : tuple of tuple of float
        Starting points (parameters then nuisances) tried when the fit is not warm-started.
    """

    cls: type[Cause]
    actuator: int | None
    lower: tuple[float, ...]
    upper: tuple[float, ...]
    grid: tuple[tuple[float, ...], ...] = ()

    @classmethod
    def of(cls, cause: type[Cause], stage: Stage, actuator: int | None = None) -> "CauseSpec":
        """The candidate ``cause`` (on ``actuator``) for ``stage``."""
        lo, hi = cause.fit_bounds(stage)
        return cls(cause, actuator, tuple(lo), tuple(hi), tuple(cause.start_grid(stage)))

    @property
    def cause(self) -> str:
        """Vocabulary name."""
        return self.cls.name

    @property
    def params(self) -> tuple[str, ...]:
        """Names of the fitted parameters (report names)."""
        return tuple(p.name for p in self.cls.params)

    @property
    def x0(self) -> tuple[float, ...]:
        """Parameters of a healthy stage (the default start)."""
        return self.cls.healthy()

    @property
    def nuisance(self) -> tuple[Nuisance, ...]:
        """Stage-physics nuisances fitted with this cause."""
        return self.cls.nuisance

    @property
    def key(self) -> str:
        """``cause`` or ``cause[actuator]``."""
        return self.cause if self.actuator is None else f"{self.cause}[{self.actuator}]"

    @property
    def k(self) -> int:
        """Number of parameters (nuisances not counted)."""
        return len(self.cls.params)

    def effect(self, theta: Sequence[float]) -> Cause:
        """The registry entry for parameters ``theta``."""
        return self.cls.make(self.actuator, theta)

    def params_dict(self, theta: Sequence[float]) -> dict:
        """Report form: ``{"actuator": i, name: value, ...}``."""
        return self.effect(theta).report_params()

    def start_from(self, base: Effects) -> tuple[float, ...]:
        """Starting values: the value already in ``base`` (a previous correction) or :attr:`x0`."""
        existing = next((e for e in base.items(MEAN_KINDS) if e.name == self.cause
                         and (self.actuator is None or e.actuator == self.actuator)), None)
        return self.x0 if existing is None else existing.theta()


def candidate_specs(stage: Stage, has: Sequence[str] = ("time_s",)) -> list[CauseSpec]:
    """Every mean cause of the registry, per-actuator ones once per actuator.

    Parameters
    ----------
    stage : Stage
    has : sequence of str
        Optional data the log has (``"time_s"``); a cause that needs missing data is left out.

    Returns
    -------
    list of CauseSpec
        In vocabulary order, with each cause's search bounds for ``stage``
        (:meth:`microctl.stage.causes.Cause.fit_bounds`).
    """
    out: list[CauseSpec] = []
    for c in REGISTRY.values():
        if c.kind not in MEAN_KINDS or any(need not in has for need in c.needs):
            continue
        acts = range(1, stage.n_act + 1) if c.per_actuator else [None]
        out += [CauseSpec.of(c, stage, a) for a in acts]
    return out


def merge_effects(base: Effects, items: Sequence[tuple[CauseSpec, Sequence[float]]]) -> Effects:
    """``base`` with the causes ``items`` added (replacing the same cause/actuator)."""
    return base.with_(*(spec.effect(theta) for spec, theta in items))


def with_nuisance(stage: Stage, values: dict[str, float]) -> Stage:
    """``stage`` with fitted nuisance values (name -> value) applied."""
    for nu in nuisances():
        if nu.name in values:
            stage = nu.apply(stage, values[nu.name])
    return stage


def _prediction(stage: Stage, effects: Effects, data: DiagnosisData):
    """The extended model's prediction of the moves in ``data`` (readings ``.t``, contacts ``.active``)."""
    return ExtendedForwardModel(stage, effects).predict_data(data)


def predict(stage: Stage, effects: Effects, data: DiagnosisData) -> np.ndarray:
    """Expected readings of the moves in ``data`` under ``effects``, shape (n,)."""
    return _prediction(stage, effects, data).t


@dataclass(frozen=True, eq=False)
class MeanFit:
    """A fitted set of mean causes.

    Attributes
    ----------
    specs : tuple of CauseSpec
    theta : ndarray, shape (k,)
        Parameters, concatenated in ``specs`` order (nuisances not included).
    stderr : ndarray, shape (k,)
        Standard errors (inf where not identifiable).
    rss : float
        (Weighted) residual sum of squares.
    n : int
        Number of moves.
    pred : ndarray, shape (n,)
        Predicted readings, µm (gauge zero included).
    effects : Effects
        ``base`` with the fitted causes.
    rank_deficient : bool
        Whether JᵀJ was singular at the optimum.
    zero_um, zero_se_um : float
        Fitted gauge-zero offset (a nuisance of the data, see :func:`fit_mean`) and its error.
    zero_fitted : bool
        Whether the gauge zero was fitted.
    nuisance, nuisance_se : dict of str -> float
        Fitted stage-physics nuisances and their standard errors.
    stage : Stage or None
        The stage with the fitted nuisances (the model the prediction used).
    jac : ndarray, shape (n, k + len(nuisance)) or None
        Unweighted Jacobian of the prediction at the optimum (parameters then nuisances).
    unphysical : bool
        The fitted causes lift a ball off somewhere though none of them may
        (:attr:`microctl.stage.causes.Cause.lifts_balls`): not the causes they claim to be.
    """

    specs: tuple[CauseSpec, ...]
    theta: np.ndarray
    stderr: np.ndarray
    rss: float
    n: int
    pred: np.ndarray
    effects: Effects
    rank_deficient: bool = False
    message: str = field(default="")
    zero_um: float = 0.0
    zero_se_um: float = 0.0
    zero_fitted: bool = False
    nuisance: dict = field(default_factory=dict)
    nuisance_se: dict = field(default_factory=dict)
    stage: Stage | None = None
    jac: np.ndarray | None = None
    unphysical: bool = False

    @property
    def k(self) -> int:
        """Number of fitted parameters (nuisances and the gauge zero included when fitted)."""
        return int(self.theta.size) + len(self.nuisance) + int(self.zero_fitted)

    @property
    def sigma2(self) -> float:
        """Residual variance estimate RSS/(n − k)."""
        return self.rss / max(self.n - self.k, 1)

    @property
    def loglik(self) -> float:
        """Gaussian profile log-likelihood −n/2 (log(2π RSS/n) + 1) (weights' constant dropped)."""
        return -0.5 * self.n * (np.log(2 * np.pi * max(self.rss, 1e-300) / self.n) + 1.0)

    @property
    def bic(self) -> float:
        """BIC = −2 log L + k log n (the noise variance is common to all models: not counted)."""
        return -2.0 * self.loglik + self.k * np.log(self.n)

    def split(self) -> list[tuple[CauseSpec, np.ndarray, np.ndarray]]:
        """Per cause (spec, θ, stderr)."""
        out, j = [], 0
        for s in self.specs:
            out.append((s, self.theta[j:j + s.k], self.stderr[j:j + s.k]))
            j += s.k
        return out

    def model(self) -> ExtendedForwardModel:
        """The fitted stage model (causes and nuisances)."""
        return ExtendedForwardModel(self.stage, self.effects)


def _stderr(jac: np.ndarray, sigma2: float) -> tuple[np.ndarray, bool]:
    """Cov = σ² (JᵀJ)⁻¹ by SVD; inf where JᵀJ is (numerically) singular."""
    k = jac.shape[1]
    if k == 0:
        return np.zeros(0), False
    _, sv, vt = np.linalg.svd(jac, full_matrices=False)
    ok = sv > np.sqrt(RANK_TOL) * sv[0] if sv[0] > 0 else np.zeros_like(sv, dtype=bool)
    if ok.all():
        cov = (vt.T / sv**2) @ vt * sigma2
        return np.sqrt(np.maximum(np.diag(cov), 0.0)), False
    se = np.full(k, np.inf)
    # parameters untouched by the null space keep a finite error
    null = vt[~ok]
    good = np.all(np.abs(null) < 1e-6, axis=0)
    if good.any():
        vt_ok, sv_ok = vt[ok], sv[ok]
        cov = (vt_ok.T / sv_ok**2) @ vt_ok * sigma2
        se[good] = np.sqrt(np.maximum(np.diag(cov)[good], 0.0))
    return se, True


def fit_mean(
    stage: Stage,
    base: Effects,
    specs: Sequence[CauseSpec],
    data: DiagnosisData,
    *,
    theta0: Sequence[float] | None = None,
    nuisance0: dict | None = None,
    weights: np.ndarray | None = None,
    zero: bool = True,
) -> MeanFit:
    """Fit the parameters of ``specs`` (added to ``base``) to the readings by NLS.

    Parameters
    ----------
    stage : Stage
    base : Effects
        Corrections already in the model (kept fixed).
    specs : sequence of CauseSpec
        Causes whose parameters are fitted jointly (may be empty: the base model).
    data : DiagnosisData
    theta0 : sequence of float, optional
        Starting parameters, concatenated (default each spec's :meth:`CauseSpec.start_from`).
        A spec whose start is its healthy value and that has a starting grid
        (``contact_loss``: gaps relative to the preload compression, and compressions) is
        started from the best grid point instead.
    nuisance0 : dict, optional
        Starting nuisance values (default the config's).
    weights : ndarray, shape (n,), optional
        1/std of each reading (feasible weighted least squares); default 1.
    zero : bool
        Also fit a constant offset of the readings (the gauge zero): readings are relative to
        one gauge reading at the zero state (measurement-log spec), which on a rig carries that
        reading's noise. It is a nuisance of the data, not a cause of the stage: profiled out
        (variable projection: for every θ the offset is the weighted mean residual), so the
        cause parameters' Jacobian and standard errors already account for it.

    Returns
    -------
    MeanFit
    """
    pb = _Problem.of(stage, base, tuple(specs), data, weights, zero)
    if not pb.specs:
        return pb.base_fit()
    specs, nuis, k_par, w = pb.specs, pb.nuis, pb.k_par, pb.w
    lo = np.concatenate([np.concatenate([s.lower for s in specs]), [nu.lo for nu in nuis]])
    hi = np.concatenate([np.concatenate([s.upper for s in specs]), [nu.hi for nu in nuis]])
    x0 = pb.start(theta0, nuisance0, lo, hi)
    res = least_squares(pb.resid, x0, bounds=(lo, hi), method="trf", x_scale="jac", xtol=FIT_TOL, ftol=FIT_TOL,
                        gtol=FIT_TOL, max_nfev=200 * len(x0))
    x = res.x
    r = res.fun
    rss = float(r @ r)
    k = x.size + int(zero)
    sigma2 = rss / max(data.n - k, 1)
    se, deficient = _stderr(res.jac, sigma2)
    eff, st, nv = pb.split_x(x)
    fitted = _prediction(st, eff, data)  # one equilibrium solve for the readings and the contacts
    pred = fitted.t
    z = pb.zero_of(pred)
    jac = res.jac / np.where(w > 0, w, 1.0)[:, None]
    # a ball out of contact at some move, with no cause that lifts balls: not a physical explanation
    unphysical = (not any(s.cls.lifts_balls for s in specs)) and not bool(fitted.active.all())
    return MeanFit(specs, x[:k_par], se[:k_par], rss, data.n, pred + z, eff, deficient, res.message, z,
                   pb.zero_se(rss, k), zero, nv, {nu.name: float(se[k_par + j]) for j, nu in enumerate(nuis)}, st,
                   jac, unphysical)


@dataclass(frozen=True)
class _Problem:
    """The least-squares problem of :func:`fit_mean`: the parameter vector x = [θ of every spec; nuisances].

    Attributes
    ----------
    w, w2 : ndarray, shape (n,)
        Weights (1/std of each reading) and their squares.
    cuts : ndarray, shape (len(specs) + 1,)
        Spec j's parameters are ``x[cuts[j]:cuts[j + 1]]``.
    nuis : tuple
        The stage-physics nuisances fitted with the specs (after the k_par cause parameters).
    """

    stage: Stage
    base: Effects
    specs: tuple
    data: DiagnosisData
    zero: bool
    w: np.ndarray
    w2: np.ndarray
    cuts: np.ndarray
    nuis: tuple
    k_par: int

    @classmethod
    def of(cls, stage, base, specs, data, weights, zero) -> "_Problem":
        w = np.ones(data.n) if weights is None else np.asarray(weights, dtype=float)
        w2 = w * w
        cuts = np.cumsum([0, *[s.k for s in specs]])
        nuis = nuisances(specs)
        k_par = int(cuts[-1])
        return cls(stage, base, specs, data, zero, w, w2, cuts, nuis, k_par)

    def zero_of(self, pred: np.ndarray) -> float:
        """The profiled gauge zero: the weighted mean residual (0 when not fitted)."""
        return float(self.w2 @ (self.data.t - pred) / self.w2.sum()) if self.zero else 0.0

    def split_x(self, x: np.ndarray) -> tuple[Effects, Stage, dict]:
        """x -> (effects, stage with the nuisances, nuisance values)."""
        cuts, k_par = self.cuts, self.k_par
        eff = merge_effects(self.base, [(s, x[cuts[j]:cuts[j + 1]]) for j, s in enumerate(self.specs)])
        nv = {nu.name: float(x[k_par + j]) for j, nu in enumerate(self.nuis)}
        return eff, with_nuisance(self.stage, nv), nv

    def pred_of(self, x: np.ndarray) -> np.ndarray:
        eff, st, _ = self.split_x(x)
        return predict(st, eff, self.data)

    def resid(self, x: np.ndarray) -> np.ndarray:
        """Weighted residuals, shape (n,)."""
        try:
            pred = self.pred_of(x)
        except SolveError:  # pragma: no cover - a pathological parameter: make it unattractive
            return self.w * np.full(self.data.n, 1e3)
        return self.w * (pred + self.zero_of(pred) - self.data.t)

    def zero_se(self, rss: float, k: int) -> float:
        return float(np.sqrt(rss / max(self.data.n - k, 1) / self.w2.sum())) if self.zero else 0.0

    def base_fit(self) -> MeanFit:
        """No spec: the base model with only the gauge zero fitted."""
        data, w, zero = self.data, self.w, self.zero
        pred = predict(self.stage, self.base, data)
        z = self.zero_of(pred)
        r = w * (pred + z - data.t)
        rss = float(r @ r)
        return MeanFit((), np.zeros(0), np.zeros(0), rss, data.n, pred + z, self.base, zero_um=z,
                       zero_se_um=self.zero_se(rss, int(zero)), zero_fitted=zero, stage=self.stage,
                       jac=np.zeros((data.n, 0)))

    def start(self, theta0, nuisance0, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
        """The starting x (clipped to [lo, hi]); a spec started at its healthy value with a
        starting grid starts from the best grid point."""
        specs, nuis, cuts, k_par, stage = self.specs, self.nuis, self.cuts, self.k_par, self.stage
        starts = np.concatenate([s.start_from(self.base) for s in specs]).astype(float)
        x_par = starts if theta0 is None else np.asarray(theta0, dtype=float).copy()
        nu0 = {nu.name: nu.value(stage) for nu in nuis}
        nu0.update({k: v for k, v in (nuisance0 or {}).items() if k in nu0})
        x0 = np.concatenate([x_par, [nu0[nu.name] for nu in nuis]])
        for j, s in enumerate(specs):
            if len(s.grid) <= 1 or not np.allclose(x0[cuts[j]:cuts[j + 1]], s.x0):
                continue
            slots = list(range(cuts[j], cuts[j + 1])) + [k_par + nuis.index(nu) for nu in s.nuisance]
            best, best_rss = x0[slots].copy(), np.inf
            for g in s.grid:
                x0[slots] = g
                r = self.resid(np.clip(x0, lo, hi))
                if r @ r < best_rss:
                    best, best_rss = np.array(g, dtype=float), float(r @ r)
            x0[slots] = best
        return np.clip(x0, lo, hi)
