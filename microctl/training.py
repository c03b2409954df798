"""Residual data set of the EAFM (paper eq. 3), the fit, and binding the model to a stage.

``x = [s_prev; u]`` and ``y = t' - T_t f_a(s_prev, u)`` for every row of a measurement log
(``shared/spec/measurement-log.md``); :func:`train_residual_model` fits the VHGPR and
records ``geometry_hash = stage.geometry_hash()`` and the input names, so that the model is
refused for another stage geometry (:class:`~microctl.eafm.EAFM`).

:func:`fixed_hyperparameter_model` builds a :class:`~microctl.vhgpr.FittedVHGPR` directly
from chosen hyperparameters and a chosen (planted) log-noise function, with no fitting: a
fixture for tests and benchmarks whose noise landscape is known exactly.
"""

from __future__ import annotations

import hashlib
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import scipy.linalg as sla

from microctl.afm import AnalyticForwardModel
from microctl.eafm import bind_to_stage
from microctl.errors import DataError
from microctl.vhgpr import VHGPR, FittedVHGPR, ard_se

__all__ = ["ResidualData", "residual_dataset", "train_residual_model", "fixed_hyperparameter_model", "save_model"]


@dataclass(frozen=True)
class ResidualData:
    """The training set of eq. 3.

    Attributes
    ----------
    X : ndarray, shape (n, n_s + n_p)
        ``[s_prev; u]`` per row.
    y : ndarray, shape (n,)
        ``t' - T_t f_a(s_prev, u)`` (µm).
    x_names : tuple of str
    """

    X: np.ndarray
    y: np.ndarray
    x_names: tuple[str, ...]


def residual_dataset(log: Any, afm: AnalyticForwardModel) -> ResidualData:
    """Residual data of eq. 3 from a :class:`~microctl.measurement_log.MeasurementLog`.

    Parameters
    ----------
    log : MeasurementLog
        With arrays ``u`` (n, n_p), ``t`` (n,), ``s_prev`` (n, n_s).
    afm : AnalyticForwardModel
    """
    u = np.asarray(log.u, dtype=float)
    s = np.asarray(log.s_prev, dtype=float)
    t = np.asarray(log.t, dtype=float)
    if u.ndim != 2 or u.shape[1] != afm.n_p or s.shape != (u.shape[0], afm.n_s) or t.shape != (u.shape[0],):
        raise DataError(f"measurement log arrays have shapes u {u.shape}, s_prev {s.shape}, t {t.shape}; "
                        f"expected (n, {afm.n_p}), (n, {afm.n_s}), (n,)")
    y = t - np.asarray(afm.t_of(u))  # eq. 3: y = t' - T_t f_a(s, u)
    names = tuple(f"{n}_prev" for n in afm.state_names) + tuple(f"u_{n}" for n in afm.dof)
    return ResidualData(X=np.hstack([s, u]), y=y, x_names=names)


def train_residual_model(data: ResidualData, afm: AnalyticForwardModel, *, n_restarts: int = 2,
                         seed: int | None = 0, max_iter: int = 500, max_time: float | None = None,
                         mean: str = "constant") -> FittedVHGPR:
    """Fit the VHGPR to the residual data and bind it to the stage geometry.

    ``mean`` is the GP's prior mean (:class:`~microctl.vhgpr.VHGPR`): ``"constant"``
    (default, the paper's) or ``"linear"`` (unweighted least-squares trend; measured on
    sim_paper it hurt, because stick-slip makes the residuals strongly heteroscedastic and
    ordinary least squares is then dominated by the noisiest moves).

    Returns
    -------
    FittedVHGPR
        With ``geometry_hash = afm.stage.geometry_hash()``, ``x_names`` = state (``*_prev``)
        and ``u_*`` names, ``y_name = "residual_um"``.
    """
    model = VHGPR(n_restarts=n_restarts, max_iter=max_iter, random_state=seed, max_time=max_time,
                  mean=mean).fit(data.X, data.y)
    return bind_to_stage(model, afm)


def fixed_hyperparameter_model(
    X: np.ndarray,
    y: np.ndarray,
    log_noise_var: np.ndarray,
    *,
    f_log_lengthscales: np.ndarray,
    f_log_signal_var: float = 0.0,
    g_log_lengthscales: np.ndarray | None = None,
    g_log_signal_var: float = 0.0,
    log_lambda: float = 3.0,
    jitter: float = 1e-8,
) -> FittedVHGPR:
    """A :class:`FittedVHGPR` from fixed hyperparameters and a planted log-noise function (no fit).

    Inputs and outputs are standardised as :meth:`VHGPR.fit` does; lengthscales and signal
    variances are in standardised units. The posterior mean of g interpolates the planted
    values: ``g_beta = (K_g + jitter I)^-1 (h - mu0)`` with ``h`` the planted log noise
    variance in standardised units and ``mu0`` its mean; ``g_chol`` uses ``Lambda =
    exp(log_lambda) I``; ``R = diag(exp(h))`` in ``K_f + R``. The prediction formulas of
    ``notes/vhgpr.md`` then apply unchanged; this is a fixture, not a variational optimum.

    Parameters
    ----------
    X : ndarray, shape (n, d)
    y : ndarray, shape (n,)
    log_noise_var : ndarray, shape (n,)
        Planted log noise variance at the training inputs, in units of y².
    f_log_lengthscales : ndarray, shape (d,)
    g_log_lengthscales : ndarray, shape (d,), optional (default: f's)
    """
    X = np.asarray(X, dtype=float)
    y = np.asarray(y, dtype=float)
    n, d = X.shape
    x_mean = X.mean(axis=0)
    x_scale = X.std(axis=0)
    x_scale[x_scale <= 1e-12] = 1.0
    y_mean, y_scale = float(y.mean()), float(y.std())
    Xs = (X - x_mean) / x_scale
    ys = (y - y_mean) / y_scale
    h = np.asarray(log_noise_var, dtype=float) - 2.0 * math.log(y_scale)
    f_ls = np.asarray(f_log_lengthscales, dtype=float)
    g_ls = f_ls if g_log_lengthscales is None else np.asarray(g_log_lengthscales, dtype=float)
    Kf = ard_se(Xs, Xs, f_ls, f_log_signal_var, None)
    Kg = ard_se(Xs, Xs, g_ls, g_log_signal_var, None)
    f_chol = np.linalg.cholesky(Kf + np.diag(np.exp(h)))
    f_alpha = sla.cho_solve((f_chol, True), ys)
    mu0 = float(h.mean())
    g_beta = sla.solve(Kg + jitter * np.eye(n), h - mu0, assume_a="pos")
    lam = math.exp(log_lambda)
    g_chol = np.linalg.cholesky(Kg + np.eye(n) / lam)
    th = hashlib.sha256(X.tobytes() + y.tobytes()).hexdigest()
    return FittedVHGPR(
        x_mean=x_mean, x_scale=x_scale, y_mean=y_mean, y_scale=y_scale, X=Xs,
        f_log_lengthscales=f_ls, f_log_signal_var=float(f_log_signal_var), f_log_bias_var=None,
        g_log_lengthscales=g_ls, g_log_signal_var=float(g_log_signal_var), g_log_bias_var=None,
        g_mu0=mu0, log_lambda=np.full(n, float(log_lambda)), f_alpha=f_alpha, f_chol=f_chol,
        g_beta=g_beta, g_chol=g_chol, bound=float("nan"), training_hash=th,
        info={"fixture": "fixed_hyperparameter_model"},
    )


def save_model(model: FittedVHGPR, path: str | Path) -> None:
    """Write the model (``.npz``)."""
    model.save(path)

