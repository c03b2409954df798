"""Fixtures for tests and benchmarks (not used by the package at run time).

:mod:`microctl.testing.plant` simulates runs of the package's stage with a planted cause (the
diagnosis's own hidden-effect tests; the independent generator is ``tests/independent_stage.py``).

:func:`fixed_hyperparameter_model` builds a :class:`~microctl.gp.fitted.FittedVHGPR` directly
from chosen hyperparameters and a chosen (planted) log-noise function, with no fitting: a
model whose noise landscape is known exactly, so the controller's tests and
``scripts/bench_solve.py`` do not depend on what an optimiser finds.
"""

from __future__ import annotations

import hashlib
import math

import numpy as np
import scipy.linalg as sla

from microctl.gp.fitted import FittedVHGPR
from microctl.gp.kernels import ard_se

__all__ = ["fixed_hyperparameter_model"]


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
