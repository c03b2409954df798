"""The homoscedastic GP that initialises the VHGPR fit, and the starting prior mean of g.

A maximum-likelihood GP with one noise variance (on at most :data:`INIT_SUBSET` points) gives
f's kernel hyperparameters, the log noise level (the constant prior mean mu0 of g) and
leave-one-out residuals, whose squares start the parametric prior mean of g
(:mod:`microctl.gp.noise_prior` eq. 1) by non-negative least squares.
"""

from __future__ import annotations

import math
import time

import numpy as np
from scipy.optimize import minimize, nnls

from microctl.errors import MicroctlError
from microctl.gp.bound import BOUNDS
from microctl.gp.kernels import KernelSpec
from microctl.gp.linalg import LOG_2PI, chol, chol_inverse

__all__ = ["INIT_SUBSET", "INIT_STARTS", "gp_loglik", "fit_homoscedastic", "init_mean_coef"]

#: Largest number of points used by the homoscedastic GP that initialises the fit.
INIT_SUBSET = 400
#: Its optimiser's starts, (log lengthscale, log noise variance) in standardised units:
#: "smooth, little noise" and "rough, more noise".
INIT_STARTS = ((0.0, -2.0), (-1.5, -1.0))


def gp_loglik(theta: np.ndarray, X: np.ndarray, y: np.ndarray, spec: KernelSpec,
              want_alpha: bool = False) -> tuple[float, np.ndarray] | tuple[float, np.ndarray, np.ndarray, np.ndarray]:
    """Log marginal likelihood of a homoscedastic GP and its gradient.

    ``theta = [kernel block (spec.size), log noise var]``. With ``want_alpha`` also
    ``alpha = A^-1 y`` and ``diag(A^-1)`` (for leave-one-out residuals ``alpha / diag``).
    """
    n = X.shape[0]
    k = spec.unpack(theta[:-1])
    sn2 = math.exp(float(theta[-1]))
    Kse = k.se(X, X)
    A = k.matrix(X, X, se=Kse)
    A[np.diag_indices(n)] += sn2
    L, _ = chol(A, what="homoscedastic GP covariance")
    Ainv = chol_inverse(L)
    alpha = Ainv @ y
    ll = -0.5 * float(y @ alpha) - float(np.sum(np.log(np.diag(L)))) - 0.5 * n * LOG_2PI
    G = np.outer(0.5 * alpha, alpha) - 0.5 * Ainv
    grad = np.concatenate([k.grad_traces(G, Kse, X), [sn2 * float(np.trace(G))]])
    if want_alpha:
        return ll, grad, alpha, np.diag(Ainv).copy()
    return ll, grad


def fit_homoscedastic(X: np.ndarray, y: np.ndarray, spec: KernelSpec, rng: np.random.Generator,
                      linear_bounds: tuple[tuple[float, float], ...] | None = None,
                      record: dict | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Maximum-likelihood homoscedastic GP on (a random subset of at most 400 of) the data.

    Parameters
    ----------
    X : ndarray, shape (n, d)
    y : ndarray, shape (n,)
    spec : KernelSpec
    rng : numpy.random.Generator
        Draws the subset when n > :data:`INIT_SUBSET`.
    linear_bounds : tuple of (float, float), optional
        Box bounds of the linear part's log variances (``spec.bounds``' ``affine``).
    record : dict, optional
        Filled with what the fit cost: ``starts`` (optimiser starts), ``evaluations`` (likelihood
        evaluations over all starts, and the last one for the leave-one-out residuals) and
        ``time_s`` (wall clock). The fit itself is the same.

    Returns
    -------
    theta : ndarray, shape (spec.size + 1,)
        ``[kernel block, log noise var]``.
    loo : ndarray, shape (m,)
        Leave-one-out residuals of the points used (``alpha_i / [A^-1]_ii``).
    idx : ndarray, shape (m,)
        Which rows of X were used.
    """
    n, d = X.shape
    idx = np.arange(n)
    if n > INIT_SUBSET:
        idx = np.sort(rng.choice(n, INIT_SUBSET, replace=False))
        X, y = X[idx], y[idx]
    bounds = spec.bounds(BOUNDS["log_lengthscale"], BOUNDS["log_signal_var"], BOUNDS["log_bias_var"],
                         BOUNDS["log_linear_var"], affine=linear_bounds) + [BOUNDS["log_noise_var"]]
    best = None
    t0, evaluations = time.perf_counter(), 0
    for ls0, sn0 in INIT_STARTS:
        x0 = np.concatenate([np.full(d, ls0), [0.0], [-4.0] if spec.bias else [],
                             np.full(d, -2.0) if spec.linear else [], [sn0]])
        x0 = np.clip(x0, [b[0] for b in bounds], [b[1] for b in bounds])

        def fun(t: np.ndarray) -> tuple[float, np.ndarray]:
            try:
                with np.errstate(all="ignore"):
                    ll, g = gp_loglik(t, X, y, spec)
            except np.linalg.LinAlgError:
                return 1e10, np.zeros_like(t)
            if not (np.isfinite(ll) and np.all(np.isfinite(g))):
                return 1e10, np.zeros_like(t)
            return -ll, -g

        res = minimize(fun, x0, jac=True, method="L-BFGS-B", bounds=bounds, options={"maxiter": 200})
        evaluations += int(res.nfev)
        if np.isfinite(res.fun) and (best is None or res.fun < best.fun):
            best = res
    if best is None or best.fun >= 1e10:
        raise MicroctlError("VHGPR: the homoscedastic GP that initialises the fit failed on these data")
    theta = np.asarray(best.x, dtype=float)
    with np.errstate(all="ignore"):
        _, _, alpha, adiag = gp_loglik(theta, X, y, spec, want_alpha=True)
    if record is not None:
        record.update(starts=len(INIT_STARTS), evaluations=evaluations + 1, time_s=time.perf_counter() - t0)
    return theta, alpha / adiag, idx


def init_mean_coef(loo: np.ndarray, Phi: np.ndarray | None, log_noise: float) -> np.ndarray:
    """Starting log c of g's prior mean: non-negative least squares of the squared
    leave-one-out residuals on ``[1, phi]`` (``noise_prior`` eq. 1), floored.

    Returns
    -------
    ndarray, shape (1 + p,)
    """
    if Phi is None or Phi.shape[1] == 0:
        return np.array([log_noise])
    D = np.hstack([np.ones((Phi.shape[0], 1)), Phi])
    scale = np.maximum(np.sqrt(np.mean(D * D, axis=0)), 1e-12)
    coef, _ = nnls(D / scale, loo * loo)
    coef = coef / scale
    total = float(np.mean(loo * loo))
    c0 = max(coef[0], 0.05 * total)
    # a feature NNLS drops starts at a small share of the variance it could carry
    cj = np.maximum(coef[1:], 1e-3 * total / np.maximum(np.mean(Phi, axis=0), 1e-12))
    return np.log(np.concatenate([[c0], cj]))

