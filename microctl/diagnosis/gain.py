"""Question 4, "what is the gain?": held-out prediction error of the four models.

Models compared on readings they were not fitted to:

- ``afm``: the analytic forward model of the configured stage (eq. 14, no fit);
- ``afm_gp``: AFM + VHGPR on its residual with x = [s; u] (the paper's EAFM, eq. 1-3);
- ``extended``: the stage model with the accepted causes through the contact physics
  (:class:`~microctl.models.extended.ExtendedForwardModel`), cause parameters refitted on the
  training part;
- ``extended_gp``: extended + VHGPR on *its* residual (the extended EAFM).

Held-out: 5-fold cross-validation over the moves (seeded permutation), or a separate
``--holdout`` log (fitted on the whole diagnosis log). Every move is predicted once;
RMSE per model; paired t-tests on the squared errors, one-sided (the second model has
the smaller mean squared error, :func:`microctl.util.stats.paired_t`); the negative log
predictive density (Gaussian with the predictive mean and variance) of the probabilistic
variants (``extended`` with its physical noise model: the accepted noise causes refitted
on the training part).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Sequence

import numpy as np

from microctl.diagnosis.causes import CauseSpec, fit_mean
from microctl.diagnosis.data import DiagnosisData
from microctl.diagnosis.noise import fit_noise
from microctl.gp.vhgpr import VHGPR
from microctl.models.afm import AnalyticForwardModel
from microctl.stage.geometry import Stage
from microctl.util.stats import paired_t

MODELS = ("afm", "afm_gp", "extended", "extended_gp")

#: Pairs tested, (baseline, improved).
COMPARISONS = (("afm", "extended_gp"), ("afm_gp", "extended_gp"), ("afm", "extended"), ("afm", "afm_gp"))


@dataclass(frozen=True, eq=False)
class GainResult:
    """Held-out comparison.

    Attributes
    ----------
    method : str
    rmse_um : dict of str -> float
    p_value : dict of str -> float
        ``"<improved>_vs_<baseline>"``: one-sided paired t-test p-value.
    nlpd : dict of str -> float
        Mean negative log predictive density per move (nats).
    errors : dict of str -> ndarray (m,)
        Held-out errors (measured − predicted), µm.
    t : ndarray (m,)
        The held-out readings.
    """

    method: str
    rmse_um: dict
    p_value: dict
    nlpd: dict
    errors: dict
    t: np.ndarray
    notes: list = field(default_factory=list)

    def to_dict(self) -> dict:
        """Report form."""
        return {"method": self.method, "rmse_um": self.rmse_um, "p_value": self.p_value, "nlpd": self.nlpd,
                "held_out_moves": int(self.t.size), "notes": self.notes}


def _nlpd(y: np.ndarray, mean: np.ndarray, var: np.ndarray) -> float:
    var = np.maximum(var, 1e-12)
    return float(np.mean(0.5 * np.log(2 * np.pi * var) + 0.5 * (y - mean) ** 2 / var))


def _fold_predictions(stage, afm, train, test, specs, theta0, nuisance0, friction, gp, gp_kw):
    """Predictions (mean, var) of the models for one train/test split."""
    out = {}
    t_afm_tr, t_afm_te = afm.t_of(train.u), afm.t_of(test.u)
    base = stage.corrections
    f = fit_mean(stage, base, specs, train, theta0=theta0, nuisance0=nuisance0)  # also the gauge zero
    ext = f.model()
    ext_tr = f.pred
    pe = ext.predict_data(test)
    ext_te = pe.t + f.zero_um
    # extended noise model: the accepted noise causes refitted on the training residual
    J_tr = ext.predict_data(train).sensitivity
    nf = fit_noise(train.t - ext_tr, J_tr, train.dq, tuple(friction))
    var_ext = nf.variance(pe.sensitivity, test.dq)
    var_afm = float(np.mean((train.t - t_afm_tr) ** 2))
    out["afm"] = (t_afm_te, np.full(test.n, var_afm))
    out["extended"] = (ext_te, var_ext)
    if gp:
        for name, tr_pred, te_pred in (("afm_gp", t_afm_tr, t_afm_te), ("extended_gp", ext_tr, ext_te)):
            model = VHGPR(**gp_kw).fit(train.gp_inputs(), train.t - tr_pred)
            pr = model.predict(test.gp_inputs())
            out[name] = (te_pred + pr.f_mean, pr.y_var)
    return out


def prediction_gain(
    stage: Stage,
    data: DiagnosisData,
    specs: Sequence[CauseSpec],
    theta: np.ndarray,
    *,
    nuisance: dict | None = None,
    holdout: DiagnosisData | None = None,
    friction: Sequence[int] = (),
    folds: int = 5,
    seed: int = 0,
    gp: bool = True,
    gp_max_iter: int = 150,
    gp_max_time: float | None = 4.0,
    progress: Callable[[str], None] | None = None,
) -> GainResult:
    """Held-out RMSE, paired tests and NLPD of the four models.

    Parameters
    ----------
    stage : Stage
        The configured model (its corrections are the baseline of every fit).
    data : DiagnosisData
    specs : sequence of CauseSpec
        Accepted mean causes (may be empty: extended = the configured physics).
    theta : ndarray, shape (k,)
        Their parameters fitted on the whole of ``data`` (warm start of the refits).
    nuisance : dict, optional
        Their stage-physics nuisances fitted on the whole of ``data`` (warm start).
    holdout : DiagnosisData, optional
        Separate test data; then the models are fitted on all of ``data``.
    friction : sequence of int
        Actuators with accepted ``actuator_friction`` (the extended model's variance,
        refitted on each training part, for its NLPD).
    folds : int
    seed : int
        Seed of the fold permutation and of the VHGPR fits.
    gp : bool
        Also fit the GP variants (VHGPR with one restart, ``gp_max_iter`` iterations,
        ``gp_max_time`` s per fit).
    progress : callable(str), optional

    Returns
    -------
    GainResult
    """
    afm = AnalyticForwardModel(stage)
    gp_kw = dict(n_restarts=1, max_iter=gp_max_iter, random_state=seed, max_time=gp_max_time)
    names = MODELS if gp else ("afm", "extended")
    if holdout is not None:
        method = "holdout log"
        parts = [(np.arange(data.n), None)]
        y = holdout.t
    else:
        method = f"{folds}-fold cross-validation"
        perm = np.random.default_rng(seed).permutation(data.n)
        parts = [(np.setdiff1d(np.arange(data.n), chunk), chunk) for chunk in np.array_split(perm, folds)]
        y = data.t
    mean = {k: np.zeros(y.size) for k in names}
    var = {k: np.zeros(y.size) for k in names}
    for tr_idx, te_idx in parts:
        train = data.subset(tr_idx)
        test = holdout if te_idx is None else data.subset(te_idx)
        sl = slice(None) if te_idx is None else te_idx
        preds = _fold_predictions(stage, afm, train, test, list(specs), theta if len(specs) else None, nuisance,
                                  friction, gp, gp_kw)
        for k in names:
            mean[k][sl], var[k][sl] = preds[k]
        if progress is not None:
            progress("fold")
    errors = {k: y - mean[k] for k in names}
    rmse = {k: float(np.sqrt(np.mean(errors[k] ** 2))) for k in names}
    pv = {}
    for a, b in COMPARISONS:
        if a in errors and b in errors:
            pv[f"{b}_vs_{a}"] = float(paired_t(errors[a] ** 2, errors[b] ** 2).p_one_sided)
    nlpd = {k: _nlpd(y, mean[k], var[k]) for k in names if k != "afm"}
    notes = [] if gp else ["GP variants skipped"]
    return GainResult(method, rmse, pv, nlpd, errors, y, notes)
