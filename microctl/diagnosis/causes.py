"""Mean causes of the vocabulary as physical changes of the stage model, fitted by NLS.

Each cause (shared/spec/diagnosis.md) is a change of the elastic contact model of
:mod:`microctl.physics`, never a curve fitted to the AFM residual:

============================  ===========================================================
``actuator_gain[i]``          ball i rises gain·(n·d)·q_i (the actuator moves gain × command)
``contact_offset[i]``         contact point c_i moved by (dx, dy) mm: new height row a_i (eq. 6, 9)
``tool_offset``               tool point t0 moved by (dx, dy) mm: new w (eq. 13)
``sensor_scale``              reading = scale · d
``sensor_nonlinearity``       reading = d + quad · d²
``contact_loss[i]``           ball i lowered by gap µm: one-sided contact may open (a kink)
``backlash[i]``               q_act,i = q_i − lag · direction_i
``drift``                     reading += rate · time
============================  ===========================================================

A set of causes with parameters θ gives a prediction t̂(θ) by
:class:`~microctl.extended.ExtendedForwardModel`; θ is fitted by nonlinear least squares
(``scipy.optimize.least_squares``, trust-region reflective, bounds from the config's
validity rules), optionally weighted by 1/std of a fitted noise model. Standard errors are
from the Jacobian at the optimum: Cov θ = σ̂² (JᵀJ)⁻¹, σ̂² = RSS/(n − k); a Fisher matrix
JᵀJ whose smallest singular value is below 1e-10 of the largest is rank deficient (the
parameters are not identifiable from this data) and gets infinite standard errors.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Sequence

import numpy as np
from scipy.optimize import least_squares

from microctl.config import (
    ActuatorGain,
    Backlash,
    ContactLoss,
    ContactOffset,
    Drift,
    Effects,
    SensorNonlinearity,
    SensorScale,
    Stage,
    ToolOffset,
)
from microctl.diagnosis.data import DiagnosisData
from microctl.errors import SolveError
from microctl.extended import ExtendedForwardModel

#: Mean causes in vocabulary order (report names).
MEAN_CAUSES = (
    "actuator_gain",
    "contact_offset",
    "tool_offset",
    "sensor_scale",
    "sensor_nonlinearity",
    "contact_loss",
    "backlash",
    "drift",
)

#: Grid of starting gaps for ``contact_loss``, as offsets (µm) from the stage's preload
#: compression (preload / contact stiffness, 5 µm with the default physics): below it a
#: lowered ball still carries load and the prediction hardly depends on the gap (zero
#: gradient), so the fit starts from the best grid point instead of from 0.
GAP_GRID_OFFSETS_UM = (-3.0, -1.0, 0.0, 1.0, 2.0, 3.0, 5.0, 7.0, 10.0, 15.0, 21.0, 28.0)


def preload_compression_um(stage: Stage) -> float:
    """Total contact compression the preload makes up, µm (preload / contact stiffness)."""
    return stage.physics.preload_n / stage.physics.contact_stiffness_n_per_um

#: Smallest singular value ratio of JᵀJ treated as full rank.
RANK_TOL = 1e-10


@dataclass(frozen=True)
class CauseSpec:
    """One candidate mean cause (a vocabulary entry, for one actuator if per-actuator).

    Attributes
    ----------
    cause : str
        Vocabulary name, e.g. ``"actuator_gain"``.
    actuator : int or None
        1-based actuator for per-actuator causes.
    params : tuple of str
        Names of the fitted parameters (report names).
    x0 : tuple of float
        Default starting values (the healthy stage).
    lower, upper : tuple of float
        Bounds of the parameters.
    """

    cause: str
    actuator: int | None
    params: tuple[str, ...]
    x0: tuple[float, ...]
    lower: tuple[float, ...]
    upper: tuple[float, ...]

    @property
    def key(self) -> str:
        """``cause`` or ``cause[actuator]``."""
        return self.cause if self.actuator is None else f"{self.cause}[{self.actuator}]"

    @property
    def k(self) -> int:
        """Number of parameters."""
        return len(self.params)

    def effect(self, theta: Sequence[float]):
        """The config cause dataclass (:mod:`microctl.config`) for parameters ``theta``."""
        v = [float(x) for x in theta]
        a = self.actuator
        return {
            "actuator_gain": lambda: ActuatorGain(a, v[0]),
            "contact_offset": lambda: ContactOffset(a, v[0], v[1]),
            "tool_offset": lambda: ToolOffset(v[0], v[1]),
            "sensor_scale": lambda: SensorScale(v[0]),
            "sensor_nonlinearity": lambda: SensorNonlinearity(v[0]),
            "contact_loss": lambda: ContactLoss(a, max(v[0], 0.0)),
            "backlash": lambda: Backlash(a, max(v[0], 0.0)),
            "drift": lambda: Drift(v[0]),
        }[self.cause]()

    def params_dict(self, theta: Sequence[float]) -> dict:
        """Report form: ``{"actuator": i, name: value, ...}``."""
        out: dict = {} if self.actuator is None else {"actuator": self.actuator}
        out.update({n: float(x) for n, x in zip(self.params, theta)})
        return out

    def start_from(self, base: Effects) -> tuple[float, ...]:
        """Starting values: the value already in ``base`` (a previous correction) or :attr:`x0`."""
        existing = getattr(base, self.cause)
        if isinstance(existing, tuple):
            existing = next((e for e in existing if e.actuator == self.actuator), None)
        if existing is None:
            return self.x0
        return tuple(float(getattr(existing, p)) for p in self.params)


def candidate_specs(stage: Stage, has_time: bool = True) -> list[CauseSpec]:
    """Every mean cause of the vocabulary, per-actuator ones once per actuator.

    Parameters
    ----------
    stage : Stage
    has_time : bool
        Whether the data has ``time_s`` (``drift`` needs it).

    Returns
    -------
    list of CauseSpec
        Bounds: gains and scale in [0.2, 5] (the config requires > 0), offsets within
        ±20 mm, quad within ±0.1 /µm, gap in [0, c + 35] µm with c the preload compression
        (:func:`preload_compression_um`), lag in [0, 5] µm, drift ±1 µm/s.
    """
    acts = range(1, stage.n_act + 1)
    c = preload_compression_um(stage)
    out: list[CauseSpec] = []
    out += [CauseSpec("actuator_gain", i, ("gain",), (1.0,), (0.2,), (5.0,)) for i in acts]
    out += [CauseSpec("contact_offset", i, ("dx_mm", "dy_mm"), (0.0, 0.0), (-20.0, -20.0), (20.0, 20.0)) for i in acts]
    out.append(CauseSpec("tool_offset", None, ("dx_mm", "dy_mm"), (0.0, 0.0), (-20.0, -20.0), (20.0, 20.0)))
    out.append(CauseSpec("sensor_scale", None, ("scale",), (1.0,), (0.2,), (5.0,)))
    out.append(CauseSpec("sensor_nonlinearity", None, ("quad_per_um",), (0.0,), (-0.1,), (0.1,)))
    out += [CauseSpec("contact_loss", i, ("gap_um",), (c,), (0.0,), (c + 35.0,)) for i in acts]
    out += [CauseSpec("backlash", i, ("lag_um",), (0.05,), (0.0,), (5.0,)) for i in acts]
    if has_time:
        out.append(CauseSpec("drift", None, ("rate_um_per_s",), (0.0,), (-1.0,), (1.0,)))
    return out


def merge_effects(base: Effects, items: Sequence[tuple[CauseSpec, Sequence[float]]]) -> Effects:
    """``base`` with the causes ``items`` added (replacing the same cause/actuator)."""
    kw = {name: getattr(base, name) for name in Effects.__dataclass_fields__}
    for spec, theta in items:
        eff = spec.effect(theta)
        cur = kw[spec.cause]
        if spec.actuator is None:
            kw[spec.cause] = eff
        else:
            kept = [c for c in cur if c.actuator != spec.actuator]
            kw[spec.cause] = tuple(sorted([*kept, eff], key=lambda c: c.actuator))
    return Effects(**kw)


def predict(stage: Stage, effects: Effects, data: DiagnosisData) -> np.ndarray:
    """Expected readings of the moves in ``data`` under ``effects``, shape (n,)."""
    return ExtendedForwardModel(stage, effects).predict_q(data.q, direction=data.direction, time_s=data.time_s).t


@dataclass(frozen=True, eq=False)
class MeanFit:
    """A fitted set of mean causes.

    Attributes
    ----------
    specs : tuple of CauseSpec
    theta : ndarray, shape (k,)
        Parameters, concatenated in ``specs`` order.
    stderr : ndarray, shape (k,)
        Standard errors (inf where not identifiable).
    rss : float
        (Weighted) residual sum of squares.
    n : int
        Number of moves.
    pred : ndarray, shape (n,)
        Predicted readings, µm.
    effects : Effects
        ``base`` with the fitted causes.
    rank_deficient : bool
        Whether JᵀJ was singular at the optimum.
    zero_um, zero_se_um : float
        Fitted gauge-zero offset (a nuisance of the data, see :func:`fit_mean`) and its error.
    zero_fitted : bool
        Whether the gauge zero was fitted.
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

    @property
    def k(self) -> int:
        """Number of fitted parameters (the gauge zero included when fitted)."""
        return int(self.theta.size) + int(self.zero_fitted)

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
        Starting parameters, concatenated (default each spec's start; ``contact_loss``
        without a given start is started from the best point of :data:`GAP_GRID_OFFSETS_UM`).
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
    specs = tuple(specs)
    w = np.ones(data.n) if weights is None else np.asarray(weights, dtype=float)
    sizes = [s.k for s in specs]
    cuts = np.cumsum([0, *sizes])

    def effects_of(theta: np.ndarray) -> Effects:
        return merge_effects(base, [(s, theta[cuts[j]:cuts[j + 1]]) for j, s in enumerate(specs)])

    w2 = w * w

    def zero_of(pred: np.ndarray) -> float:
        return float(w2 @ (data.t - pred) / w2.sum()) if zero else 0.0

    def resid(theta: np.ndarray) -> np.ndarray:
        try:
            pred = predict(stage, effects_of(theta), data)
        except SolveError:  # pragma: no cover - a pathological parameter: make it unattractive
            return w * np.full(data.n, 1e3)
        return w * (pred + zero_of(pred) - data.t)

    def zero_se(rss: float, k: int) -> float:
        return float(np.sqrt(rss / max(data.n - k, 1) / w2.sum())) if zero else 0.0

    if not specs:
        pred = predict(stage, base, data)
        z = zero_of(pred)
        r = w * (pred + z - data.t)
        rss = float(r @ r)
        return MeanFit((), np.zeros(0), np.zeros(0), rss, data.n, pred + z, base, zero_um=z,
                       zero_se_um=zero_se(rss, int(zero)), zero_fitted=zero)

    lo = np.concatenate([s.lower for s in specs])
    hi = np.concatenate([s.upper for s in specs])
    if theta0 is None:
        x0 = np.concatenate([s.start_from(base) for s in specs]).astype(float)
    else:
        x0 = np.asarray(theta0, dtype=float).copy()
    # contact_loss not warm-started: start from the best gap of a coarse grid
    grid_specs = [j for j, s in enumerate(specs) if s.cause == "contact_loss" and x0[cuts[j]] == s.x0[0]]
    for j in grid_specs:  # coarse grid for the gap (zero gradient below the preload compression)
        best, best_rss = x0[cuts[j]], np.inf
        for g in GAP_GRID_OFFSETS_UM:
            x0[cuts[j]] = max(0.0, preload_compression_um(stage) + g)
            r = resid(x0)
            if r @ r < best_rss:
                best, best_rss = g, float(r @ r)
        x0[cuts[j]] = best
    x0 = np.clip(x0, lo, hi)
    res = least_squares(resid, x0, bounds=(lo, hi), method="trf", x_scale="jac", xtol=1e-10, ftol=1e-10,
                        gtol=1e-10, max_nfev=200 * len(x0))
    theta = res.x
    r = res.fun
    rss = float(r @ r)
    k = theta.size + int(zero)
    sigma2 = rss / max(data.n - k, 1)
    se, deficient = _stderr(res.jac, sigma2)
    eff = effects_of(theta)
    pred = predict(stage, eff, data)
    z = zero_of(pred)
    return MeanFit(specs, theta, se, rss, data.n, pred + z, eff, deficient, res.message, z, zero_se(rss, k), zero)
