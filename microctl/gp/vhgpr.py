"""Variational heteroscedastic Gaussian process regression (VHGPR).

The model and the marginalised variational ("MV") bound of Lázaro-Gredilla & Titsias
(ICML 2011), written from the equations in ``notes/vhgpr.md`` (cited below as [N]):

    y_i = f(x_i) + e_i,   e_i ~ N(0, exp(g(x_i))),   f ~ GP(0, K_f),   g ~ GP(mu0, K_g)

    q(g) = N(mu, Sigma),  Sigma = (K_g^-1 + Lambda)^-1,  mu = K_g (Lambda - I/2) 1 + mu0 1     [N q(g)]

    F = log N(y | 0, K_f + R) - KL(N(mu, Sigma) || N(mu0 1, K_g)) - tr(Sigma)/4,
    R = diag(exp(mu_i - Sigma_ii / 2))                                                       [N bound]

:class:`VHGPR` holds the settings and :meth:`VHGPR.fit` maximises ``F`` with analytic
gradients (L-BFGS-B over log Lambda, log kernel hyperparameters and mu0); it returns a
frozen :class:`FittedVHGPR` that holds everything a prediction needs and nothing else
(see ``docs/vhgpr.md``).  Inputs and outputs are standardised; all quantities stored
in the fitted model are in standardised units except where a field says otherwise.
"""

from __future__ import annotations

import hashlib
import json
import math
import time
import zipfile
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import scipy.linalg as sla
from scipy.linalg import lapack
from scipy.optimize import minimize, nnls

from microctl.errors import ConfigError, DataError, MicroctlError
from microctl.gp.kernels import Kernel, KernelSpec
from microctl.gp.noise_prior import LogVarianceMean, NoiseFeatures
from microctl.util.blas import single_thread_blas

__all__ = ["FORMAT_VERSION", "VHGPR", "FittedVHGPR", "VHGPRPrediction", "ard_se"]

#: Version of the ``.npz`` model file written by :meth:`FittedVHGPR.save` (2: optional
#: linear kernel part of f and parametric prior mean of g; version 1 files read unchanged).
FORMAT_VERSION = 2
_READABLE_VERSIONS = (1, 2)

_LOG_2PI = math.log(2.0 * math.pi)

# Box bounds of the optimised parameters, in standardised units (inputs and outputs have
# unit variance), chosen wide enough never to bind on sensible data and narrow enough
# that exp() cannot overflow and B = I + Lambda^1/2 K_g Lambda^1/2 stays well conditioned.
_BOUNDS = {
    "log_lambda": (-10.0, 10.0),
    "log_lengthscale": (-5.0, 6.0),
    "log_signal_var": (-12.0, 5.0),
    "log_bias_var": (-12.0, 5.0),
    "mu0": (-20.0, 5.0),
    "log_linear_var": (-15.0, 5.0),
    "log_feature_coef": (-30.0, 5.0),  # c_j of g's parametric prior mean (noise_prior eq. 1)
    "log_noise_var": (-20.0, 2.0),  # homoscedastic initialisation only
}

#: When the prior variance of g's GP part (signal + bias) is at most this (log-variance
#: units: a standard deviation of 0.01, 1 % on the noise variance), its posterior variance,
#: which lies in [0, that prior variance], is taken as the prior variance itself: the
#: conservative end of the interval, in the NumPy prediction and in the CasADi graph alike,
#: so g's variance costs O(n) instead of O(n^2) per evaluation. Fits whose noise a parametric
#: prior mean explains drive g's signal variance to its lower bound exp(-12), well below.
G_GP_VAR_NEGLIGIBLE = 1e-4

# Largest number of points used by the homoscedastic GP that initialises the fit.
_INIT_SUBSET = 400

def _default_max_iter(n: int) -> int:
    """Iterations per run when ``max_iter`` is None: 100 up to n = 200, then 100 (200/n)^0.6, at least 25.

    Each iteration costs O(n^3), and with more points fewer iterations are needed: on the
    synthetic benchmark (scripts/bench_vhgpr.py) the hold-out NLPD changes by < 1e-3 nats
    after ~40 iterations at n = 500 and is within 0.005 nats of the oracle after 25 at
    n = 2000, against ~100-150 iterations for the 133-point motorcycle data.  This gives
    58 at n = 500, 38 at n = 1000 and 25 at n = 2000.
    """
    return int(max(25, min(100, round(100 * (200 / n) ** 0.6))))


# --------------------------------------------------------------------------- kernels


def ard_se(
    Xa: np.ndarray,
    Xb: np.ndarray,
    log_lengthscales: np.ndarray,
    log_signal_var: float,
    log_bias_var: float | None,
) -> np.ndarray:
    """Squared-exponential kernel with one lengthscale per input (ARD), plus an optional bias.

    ``k(x, x') = exp(log_signal_var) * exp(-0.5 * sum_d ((x_d - x'_d) / exp(log_lengthscales_d))**2)
    + (exp(log_bias_var) if log_bias_var is not None else 0)``; a thin wrapper of
    :class:`microctl.gp.kernels.Kernel`, the one implementation.

    Parameters
    ----------
    Xa : ndarray, shape (m, d)
    Xb : ndarray, shape (n, d)
    log_lengthscales : ndarray, shape (d,)
    log_signal_var : float
    log_bias_var : float or None

    Returns
    -------
    ndarray, shape (m, n)
    """
    k = Kernel(np.asarray(log_lengthscales, dtype=float), float(log_signal_var),
               None if log_bias_var is None else float(log_bias_var))
    return k.matrix(Xa, Xb)


# --------------------------------------------------------------------------- linear algebra


def _chol(A: np.ndarray, *, what: str) -> tuple[np.ndarray, float]:
    """Lower Cholesky factor of symmetric ``A``; diagonal jitter only if plain Cholesky fails.

    Returns the factor and the jitter added (0.0 when none).  Jitter grows from 1e-10 to
    1e-4 times the mean diagonal; beyond that a :class:`numpy.linalg.LinAlgError` is raised.
    """
    L, info = lapack.dpotrf(A, lower=1, clean=1, overwrite_a=0)
    if info == 0:
        return L, 0.0
    scale = float(np.mean(np.diag(A)))
    if not np.isfinite(scale) or scale <= 0:
        raise np.linalg.LinAlgError(f"{what}: non-finite or non-positive diagonal")
    for k in range(-10, -3):
        jitter = scale * 10.0**k
        L, info = lapack.dpotrf(A + jitter * np.eye(A.shape[0]), lower=1, clean=1, overwrite_a=0)
        if info == 0:
            return L, jitter
    raise np.linalg.LinAlgError(f"{what}: not positive definite even with jitter {jitter:.3g}")


def _chol_inverse(L: np.ndarray) -> np.ndarray:
    """Full symmetric inverse of L L^T from its lower Cholesky factor ``L`` (LAPACK potri).

    ``L`` must have a zero upper triangle (``dpotrf(..., clean=1)``); potri writes the
    lower triangle of the inverse, which is then mirrored.
    """
    Ainv, info = lapack.dpotri(L, lower=1)
    if info != 0:
        raise np.linalg.LinAlgError("potri failed")
    Ainv += Ainv.T
    Ainv[np.diag_indices(Ainv.shape[0])] *= 0.5
    return Ainv


# --------------------------------------------------------------------------- parameter layout


@dataclass(frozen=True)
class _Layout:
    """Where each block of parameters sits in the flat optimisation vector.

    ``[log lambda (n), f kernel block, g kernel block, log c_0 (= mu0), log c_1..c_p]``: the
    kernel blocks as :class:`~microctl.gp.kernels.KernelSpec` lays them out, then the prior
    mean of g (:class:`~microctl.gp.noise_prior.LogVarianceMean`; p = 0 is the constant mu0).
    """

    n: int
    f: KernelSpec
    g: KernelSpec
    p: int = 0
    linear_bounds: tuple[tuple[float, float], ...] | None = None  # [bias, per input]: fixed or free log v
    se_off: bool = False  # f's SE part switched off (its hyperparameters fixed, signal variance at the floor)

    @property
    def f_slice(self) -> slice:
        return slice(self.n, self.n + self.f.size)

    @property
    def g_slice(self) -> slice:
        s = self.n + self.f.size
        return slice(s, s + self.g.size)

    @property
    def mean_slice(self) -> slice:
        s = self.n + self.f.size + self.g.size
        return slice(s, s + 1 + self.p)

    @property
    def size(self) -> int:
        return self.n + self.f.size + self.g.size + 1 + self.p

    def bounds(self) -> list[tuple[float, float]]:
        kb = {k: _BOUNDS[v] for k, v in (("ls", "log_lengthscale"), ("sf2", "log_signal_var"),
                                          ("bias", "log_bias_var"), ("linear", "log_linear_var"))}
        fb = self.f.bounds(**kb, affine=self.linear_bounds)
        if self.se_off:
            ls_hi, sf2_lo = _BOUNDS["log_lengthscale"][1], _BOUNDS["log_signal_var"][0]
            fb[: self.f.d + 1] = [(ls_hi, ls_hi)] * self.f.d + [(sf2_lo, sf2_lo)]
        return ([_BOUNDS["log_lambda"]] * self.n + fb + self.g.bounds(**kb)
                + [_BOUNDS["mu0"]] + [_BOUNDS["log_feature_coef"]] * self.p)


def _prior_mean(log_c: np.ndarray, Phi: np.ndarray | None) -> tuple[np.ndarray | float, np.ndarray | None]:
    """Prior mean m of g at the training inputs and dm/dlog c (``noise_prior`` eq. 1).

    Parameters
    ----------
    log_c : ndarray, shape (1 + p,)
    Phi : ndarray, shape (n, p), or None when p = 0

    Returns
    -------
    m : float (p = 0) or ndarray, shape (n,)
    dm : ndarray, shape (n, 1 + p), or None when p = 0 (then dm/dmu0 = 1)
    """
    if Phi is None or Phi.shape[1] == 0:
        return float(log_c[0]), None
    c = np.exp(log_c)
    D = np.hstack([np.full((Phi.shape[0], 1), c[0]), Phi * c[1:]])  # c_j phi_j, with phi_0 = 1
    v = D.sum(axis=1)
    return np.log(v), D / v[:, None]


# --------------------------------------------------------------------------- the bound


def _mv_bound(theta: np.ndarray, X: np.ndarray, y: np.ndarray, layout: _Layout, *, want_grad: bool = True,
              want_state: bool = False, Phi: np.ndarray | None = None
              ) -> tuple[float, np.ndarray | None, dict | None]:
    """The MV bound F and its gradient with respect to the flat parameter vector.

    Parameters
    ----------
    theta : ndarray, shape (layout.size,)
        See :class:`_Layout`.
    X : ndarray, shape (n, d), standardised inputs
    y : ndarray, shape (n,), standardised outputs
    layout : _Layout
    want_grad : bool
    want_state : bool
        Also return the factors a fitted model stores.
    Phi : ndarray, shape (n, p), optional
        Features of g's parametric prior mean at the inputs (None: constant mu0).

    Returns
    -------
    F : float
    grad : ndarray, shape (layout.size,), or None
    state : dict or None

    Raises
    ------
    numpy.linalg.LinAlgError
        If K_f + R is not positive definite even with jitter.
    """
    n = layout.n
    log_lam = theta[:n]
    lam = np.exp(log_lam)
    kf = layout.f.unpack(theta[layout.f_slice])
    kg = layout.g.unpack(theta[layout.g_slice])
    m, dm = _prior_mean(theta[layout.mean_slice], Phi)

    Kf_se = kf.se(X, X)
    Kg_se = kg.se(X, X)
    Kf = kf.matrix(X, X, se=Kf_se)
    Kg = kg.matrix(X, X, se=Kg_se)

    # B = I + Lambda^1/2 K_g Lambda^1/2 [N stable forms]; its eigenvalues are >= 1.
    s = np.sqrt(lam)
    Bm = Kg * np.outer(s, s)
    Bm[np.diag_indices(n)] += 1.0
    LB, info = lapack.dpotrf(Bm, lower=1, clean=1)
    if info != 0:
        raise np.linalg.LinAlgError("B = I + Lambda^1/2 K_g Lambda^1/2 is not positive definite")
    T = _chol_inverse(LB)  # B^-1
    logdet_B = 2.0 * float(np.sum(np.log(np.diag(LB))))

    # Sigma = (K_g^-1 + Lambda)^-1 = Lambda^-1/2 (I - B^-1) Lambda^-1/2  (since
    # Lambda^1/2 Sigma Lambda^1/2 = S (I + S)^-1 = I - B^-1 with S = Lambda^1/2 K_g Lambda^1/2).
    sig_diag = (1.0 - np.diag(T)) / lam
    beta = lam - 0.5  # (Lambda - I/2) 1
    mu = Kg @ beta + m  # [N q(g)], with the prior mean m(x) in place of mu0

    # R = diag(exp(mu_i - Sigma_ii / 2)) [N bound]
    r = np.exp(mu - 0.5 * sig_diag)
    A = Kf.copy()
    A[np.diag_indices(n)] += r
    LA, jitter = _chol(A, what="K_f + R")
    Ainv = _chol_inverse(LA)
    alpha = Ainv @ y

    # log N(y | 0, K_f + R); the jitter (if any) is part of the covariance actually used.
    log_lik = -0.5 * float(y @ alpha) - float(np.sum(np.log(np.diag(LA)))) - 0.5 * n * _LOG_2PI
    # KL(N(mu, Sigma) || N(m, K_g)) = 1/2 [tr(K_g^-1 Sigma) + (mu - m)^T K_g^-1 (mu - m)
    #     - n + log|K_g| - log|Sigma|] with tr(K_g^-1 Sigma) = tr(B^-1),
    # (mu - m)^T K_g^-1 (mu - m) = beta^T K_g beta, log|K_g| - log|Sigma| = log|B|.
    kl = 0.5 * (float(np.trace(T)) + float(beta @ (mu - m)) - n + logdet_B)
    F = log_lik - kl - 0.25 * float(np.sum(sig_diag))

    grad = None
    if want_grad:
        # dF/dR_ii = (alpha_i^2 - [A^-1]_ii)/2, so with w = r * that:
        # dF/dmu = w - beta =: u (the -beta from dKL/dmu = K_g^-1 (mu - m) = beta), and
        # dF/dSigma_ii = -w_i/2 + lambda_i/2 - 1/4 = -u_i/2 (dKL/dSigma = (K_g^-1 - Sigma^-1)/2 = -Lambda/2).
        w = 0.5 * (alpha * alpha - np.diag(Ainv)) * r
        u = w - beta
        # dmu/dlambda_j = K_g[:, j]; dSigma_ii/dlambda_j = -Sigma_ij^2, so
        # dF/dlambda = K_g u + (Sigma o Sigma) u / 2; times lambda for log lambda.
        # Sigma o Sigma = (I - B^-1)^2 / (lambda lambda^T) elementwise: off-diagonal T_ij^2,
        # diagonal (1 - T_ii)^2, both over lambda_i lambda_j.
        tdiag = np.diag(T).copy()
        Sig2u = (T * T) @ (u / lam)
        Sig2u += ((1.0 - tdiag) ** 2 - tdiag**2) * u / lam
        Sig2u /= lam
        g_lam = lam * (Kg @ u + 0.5 * Sig2u)

        # f hyperparameters: d log N / dtheta = tr(Gf dK_f/dtheta), Gf = (alpha alpha^T - A^-1)/2.
        Gf = np.outer(0.5 * alpha, alpha)
        Gf -= 0.5 * Ainv
        g_f = kf.grad_traces(Gf, Kf_se, X)
        del Gf

        # g hyperparameters: dF = tr(Gg dK_g) with, for fixed Lambda and m,
        #  via mu = K_g beta + m:              sym(u beta^T)
        #  via Sigma, dSigma = M^T dK_g M with M = (I + Lambda K_g)^-1 = Lambda^1/2 B^-1 Lambda^-1/2:
        #                                      M C M^T, C = diag(-u/2)
        #  directly through KL's K_g:          -1/2 (K_g^-1 - K_g^-1 Sigma K_g^-1 - beta beta^T)
        #                                      = -1/2 Lambda^1/2 B^-1 Lambda^1/2 + beta beta^T / 2
        c_over_lam = -0.5 * u / lam
        Gg = T * c_over_lam[None, :]
        Gg = Gg @ T  # B^-1 diag(c / lambda) B^-1
        Gg -= 0.5 * T
        Gg *= np.outer(s, s)
        a = 0.5 * u + 0.25 * beta  # sym(u beta^T) + beta beta^T / 2 = a beta^T + beta a^T
        Gg += np.outer(a, beta)
        Gg += np.outer(beta, a)
        g_g = kg.grad_traces(Gg, Kg_se, X)
        del Gg

        # The prior mean m enters only through mu (KL depends on mu - m = K_g beta):
        # dF/dm_i = w_i, so dF/dlog c = dm^T w (dF/dmu0 = sum(w) for the constant mean).
        g_m = np.array([float(np.sum(w))]) if dm is None else dm.T @ w
        grad = np.concatenate([g_lam, g_f, g_g, g_m])

    state = None
    if want_state:
        state = {
            "f_alpha": alpha,
            "f_chol": LA,
            "g_beta": beta,
            # K_g + Lambda^-1 = Lambda^-1/2 B Lambda^-1/2, so its lower factor is Lambda^-1/2 L_B.
            "g_chol": LB / s[:, None],
            "jitter": jitter,
            "mu": mu,
            "sigma_diag": sig_diag,
            "r": r,
            "A_inv": Ainv,
        }
    return F, grad, state


def _mean_coef_covariance(state: dict, log_c: np.ndarray, Phi: np.ndarray | None) -> np.ndarray:
    """Laplace covariance of c = (c_0, .., c_p) of g's prior mean (``noise_prior`` eq. 1).

    The Gaussian likelihood ``y ~ N(0, K_f + R)`` with ``R_ii = r_i`` and ``dr_i/dc_j =
    r_i J_ij``, ``J_ij = dm_i/dc_j = phi_ij / exp(m_i)`` (phi_0 = 1), has Fisher information
    ``I_jk = 1/2 tr(A^-1 dA_j A^-1 dA_k) = 1/2 sum_il P_il^2 r_i r_l J_ij J_lk`` with
    ``P = A^-1`` (the variational posterior of g held fixed). The covariance is taken in c
    itself, not in log c: a friction coefficient can be zero, and its uncertainty then has
    a scale of its own (log c would tie it to the estimate). A weak Gaussian prior, under
    which each term ``c_j mean(phi_j)`` has standard deviation 1 (the output's variance in
    standardised units), keeps a feature the data never exercised uncertain.

    Returns
    -------
    ndarray, shape (1 + p, 1 + p)
    """
    r = state["r"]
    P = state["A_inv"]
    M = P * P * np.outer(r, r)  # tr(P D_j P D_k) = sum_il P_il^2 r_i r_l J_ij J_lk, D_j = diag(r J_:j)
    c = np.exp(log_c)
    D = np.ones((r.size, 1)) if Phi is None or Phi.shape[1] == 0 else np.hstack([np.ones((r.size, 1)), Phi])
    J = D / (D @ c)[:, None]
    info = 0.5 * J.T @ M @ J
    info[np.diag_indices_from(info)] += np.mean(D, axis=0) ** 2  # prior: c_j mean(phi_j) ~ N(0, 1)
    return np.linalg.inv(info)


# --------------------------------------------------------------------------- homoscedastic GP


def _gp_loglik(theta: np.ndarray, X: np.ndarray, y: np.ndarray, spec: KernelSpec,
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
    L, _ = _chol(A, what="homoscedastic GP covariance")
    Ainv = _chol_inverse(L)
    alpha = Ainv @ y
    ll = -0.5 * float(y @ alpha) - float(np.sum(np.log(np.diag(L)))) - 0.5 * n * _LOG_2PI
    G = np.outer(0.5 * alpha, alpha) - 0.5 * Ainv
    grad = np.concatenate([k.grad_traces(G, Kse, X), [sn2 * float(np.trace(G))]])
    if want_alpha:
        return ll, grad, alpha, np.diag(Ainv).copy()
    return ll, grad


def _fit_homoscedastic(X: np.ndarray, y: np.ndarray, spec: KernelSpec, rng: np.random.Generator,
                       linear_bounds: tuple[tuple[float, float], ...] | None = None
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Maximum-likelihood homoscedastic GP on (a random subset of at most 400 of) the data.

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
    if n > _INIT_SUBSET:
        idx = np.sort(rng.choice(n, _INIT_SUBSET, replace=False))
        X, y = X[idx], y[idx]
    bounds = spec.bounds(_BOUNDS["log_lengthscale"], _BOUNDS["log_signal_var"], _BOUNDS["log_bias_var"],
                         _BOUNDS["log_linear_var"], affine=linear_bounds) + [_BOUNDS["log_noise_var"]]
    best = None
    # Two starts: "smooth, little noise" and "rough, more noise" (standardised units).
    for ls0, sn0 in ((0.0, -2.0), (-1.5, -1.0)):
        x0 = np.concatenate([np.full(d, ls0), [0.0], [-4.0] if spec.bias else [],
                             np.full(d, -2.0) if spec.linear else [], [sn0]])
        x0 = np.clip(x0, [b[0] for b in bounds], [b[1] for b in bounds])

        def fun(t: np.ndarray) -> tuple[float, np.ndarray]:
            try:
                with np.errstate(all="ignore"):
                    ll, g = _gp_loglik(t, X, y, spec)
            except np.linalg.LinAlgError:
                return 1e10, np.zeros_like(t)
            if not (np.isfinite(ll) and np.all(np.isfinite(g))):
                return 1e10, np.zeros_like(t)
            return -ll, -g

        res = minimize(fun, x0, jac=True, method="L-BFGS-B", bounds=bounds, options={"maxiter": 200})
        if np.isfinite(res.fun) and (best is None or res.fun < best.fun):
            best = res
    if best is None or best.fun >= 1e10:
        raise MicroctlError("VHGPR: the homoscedastic GP that initialises the fit failed on these data")
    theta = np.asarray(best.x, dtype=float)
    with np.errstate(all="ignore"):
        _, _, alpha, adiag = _gp_loglik(theta, X, y, spec, want_alpha=True)
    return theta, alpha / adiag, idx


def _init_mean_coef(loo: np.ndarray, Phi: np.ndarray | None, log_noise: float) -> np.ndarray:
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


# --------------------------------------------------------------------------- fitted model and prediction


@dataclass(frozen=True, eq=False)
class VHGPRPrediction:
    """Predictive distribution at m test inputs, in the ORIGINAL units of y.

    Attributes
    ----------
    f_mean : ndarray, shape (m,)
        ``y_mean + y_scale * a*``.
    f_var : ndarray, shape (m,)
        ``y_scale**2 * c*^2`` (epistemic variance of f).
    g_mean : ndarray, shape (m,)
        Mean of the log noise variance: ``mu* + 2 log(y_scale)``.
    g_var : ndarray, shape (m,)
        ``s*^2``, variance of the log noise variance.
    y_mean : ndarray, shape (m,)
        Equal to ``f_mean``.
    y_var : ndarray, shape (m,)
        ``f_var + exp(g_mean + g_var / 2)``.
    """

    f_mean: np.ndarray
    f_var: np.ndarray
    g_mean: np.ndarray
    g_var: np.ndarray
    y_mean: np.ndarray
    y_var: np.ndarray


_ARRAY_FIELDS = (
    "x_mean", "x_scale", "X", "f_log_lengthscales", "g_log_lengthscales",
    "log_lambda", "f_alpha", "f_chol", "g_beta", "g_chol",
)
_FLOAT_FIELDS = ("y_mean", "y_scale", "f_log_signal_var", "g_log_signal_var", "g_mu0", "bound")
_OPTIONAL_FLOAT_FIELDS = ("f_log_bias_var", "g_log_bias_var")
# Optional arrays (format 2): absent = the part is not used. Shapes checked at load.
_OPTIONAL_ARRAY_FIELDS = ("f_log_linear_vars", "g_feature_matrix", "g_feature_offset", "g_log_feature_coef",
                          "g_mean_coef_cov")


@dataclass(frozen=True, eq=False)
class FittedVHGPR:
    """A fitted VHGPR: everything a prediction needs (standardised units unless stated).

    Attributes
    ----------
    x_mean, x_scale : ndarray, shape (d,)
        Input standardisation ``xs = (x - x_mean) / x_scale``.
    y_mean, y_scale : float
        Output standardisation ``ys = (y - y_mean) / y_scale``.
    X : ndarray, shape (n, d)
        Standardised training inputs.
    f_log_lengthscales, f_log_signal_var, f_log_bias_var
        Kernel of f (see :func:`ard_se`); the bias is None when not used.
    g_log_lengthscales, g_log_signal_var, g_log_bias_var
        Kernel of g.
    g_mu0 : float
        Prior mean of g (standardised units).
    log_lambda : ndarray, shape (n,)
        Variational parameters log Lambda.
    f_alpha : ndarray, shape (n,)
        ``(K_f + R)^-1 ys``.
    f_chol : ndarray, shape (n, n)
        Lower Cholesky factor of ``K_f + R``.
    g_beta : ndarray, shape (n,)
        ``(Lambda - I/2) 1``.
    g_chol : ndarray, shape (n, n)
        Lower Cholesky factor of ``K_g + Lambda^-1``.
    bound : float
        The MV bound at the optimum (standardised data).
    training_hash : str
        sha256 hex of the original X and y as float64 bytes.
    geometry_hash : str or None
        Set by callers (``dataclasses.replace``) for residual models.
    x_names : tuple of str
        Input column names, if known.
    y_name : str
        Output column name, if known.
    info : dict
        Fit diagnostics: jitter, restarts tried/failed, iterations, time.
    f_log_linear_vars : ndarray, shape (d,), or None
        ARD linear part of f's kernel (:mod:`microctl.gp.kernels`); None when not used.
    g_feature_matrix, g_feature_offset : ndarray, shapes (p, d) and (p,), or None
        Features of g's parametric prior mean (:mod:`microctl.gp.noise_prior` eq. 1) in
        standardised units; None: the constant prior mean ``g_mu0``.
    g_log_feature_coef : ndarray, shape (p,), or None
        log c_j of that mean (``g_mu0`` is log c_0).
    g_mean_coef_cov : ndarray, shape (p + 1, p + 1), or None
        Laplace covariance of (c_0, .., c_p), propagated into g's posterior variance.
    g_feature_names : tuple of str
        Names of the features (``dq1``, ...).
    """

    x_mean: np.ndarray
    x_scale: np.ndarray
    y_mean: float
    y_scale: float
    X: np.ndarray
    f_log_lengthscales: np.ndarray
    f_log_signal_var: float
    f_log_bias_var: float | None
    g_log_lengthscales: np.ndarray
    g_log_signal_var: float
    g_log_bias_var: float | None
    g_mu0: float
    log_lambda: np.ndarray
    f_alpha: np.ndarray
    f_chol: np.ndarray
    g_beta: np.ndarray
    g_chol: np.ndarray
    bound: float
    training_hash: str
    geometry_hash: str | None = None
    x_names: tuple[str, ...] = ()
    y_name: str = ""
    info: dict = field(default_factory=dict)
    f_log_linear_vars: np.ndarray | None = None
    g_feature_matrix: np.ndarray | None = None
    g_feature_offset: np.ndarray | None = None
    g_log_feature_coef: np.ndarray | None = None
    g_mean_coef_cov: np.ndarray | None = None
    g_feature_names: tuple[str, ...] = ()

    @property
    def n_inputs(self) -> int:
        """Number of input dimensions d."""
        return int(self.X.shape[1])

    @property
    def f_kernel(self) -> Kernel:
        """The kernel of f (:class:`~microctl.gp.kernels.Kernel`)."""
        return Kernel(self.f_log_lengthscales, self.f_log_signal_var, self.f_log_bias_var, self.f_log_linear_vars)

    @property
    def g_kernel(self) -> Kernel:
        """The kernel of g."""
        return Kernel(self.g_log_lengthscales, self.g_log_signal_var, self.g_log_bias_var)

    @property
    def g_prior_mean(self) -> LogVarianceMean:
        """The prior mean of g (constant ``g_mu0``, or :mod:`microctl.gp.noise_prior` eq. 1)."""
        d = self.n_inputs
        if self.g_feature_matrix is None:
            return LogVarianceMean(np.zeros((0, d)), np.zeros(0), self.g_mu0, np.zeros(0), self.g_mean_coef_cov)
        return LogVarianceMean(self.g_feature_matrix, self.g_feature_offset, self.g_mu0, self.g_log_feature_coef,
                               self.g_mean_coef_cov)

    @property
    def g_prior_mean_with_uncertainty(self) -> LogVarianceMean:
        """g's prior mean carrying its parameters' covariance whether or not the model propagates
        it into g's variance (from ``info["noise_parameters"]``): for questions of evidence (is a
        pose credibly quieter, where is the noise model least certain), not for the objective."""
        gm = self.g_prior_mean
        params = self.info.get("noise_parameters") or {}
        if gm.coef_cov is not None or self.g_feature_matrix is None or "c_cov" not in params:
            return gm
        return replace(gm, coef_cov=np.asarray(params["c_cov"], dtype=float))

    @property
    def g_gp_var_negligible(self) -> bool:
        """g's GP part has prior variance <= :data:`G_GP_VAR_NEGLIGIBLE` (its variance is then that bound)."""
        k = self.g_kernel
        return k.signal_var + k.bias_var <= G_GP_VAR_NEGLIGIBLE

    @property
    def noise_model(self) -> str:
        """``"physical"`` when g has a parametric prior mean, else ``"hgp"`` (the paper's)."""
        return "physical" if self.g_feature_matrix is not None else "hgp"

    def _check_X(self, X: Any) -> np.ndarray:
        X = _as_float_array(X, "X")
        d = self.n_inputs
        if X.ndim == 1 and d == 1:
            X = X[:, None]
        if X.ndim != 2 or X.shape[1] != d:
            raise DataError(f"X has shape {X.shape}; this model expects shape (m, {d})")
        _check_finite(X, "X")
        return X

    def predict(self, X: Any) -> VHGPRPrediction:
        """Predictive distribution at the rows of ``X``.

        Parameters
        ----------
        X : array_like, shape (m, d), original units

        Returns
        -------
        VHGPRPrediction
            All fields of shape (m,), in original units of y.
        """
        X = self._check_X(X)
        xs = (X - self.x_mean) / self.x_scale
        m = xs.shape[0]
        a = np.empty(m)
        c2 = np.empty(m)
        mu = np.empty(m)
        s2 = np.empty(m)
        kf, kg, gm = self.f_kernel, self.g_kernel, self.g_prior_mean
        chunk = max(1, 4_000_000 // max(1, self.X.shape[0]))
        for start in range(0, m, chunk):
            sl = slice(start, min(m, start + chunk))
            Kf = kf.matrix(xs[sl], self.X)
            Kg = kg.matrix(xs[sl], self.X)
            # [N prediction] a* = k_f*^T (K_f + R)^-1 y,  c*^2 = k_f** - ||f_chol^-1 k_f*||^2
            a[sl] = Kf @ self.f_alpha
            v = sla.solve_triangular(self.f_chol, Kf.T, lower=True, check_finite=False)
            c2[sl] = kf.diag(xs[sl]) - np.einsum("ij,ij->j", v, v)
            # [N prediction] mu* = k_g*^T (Lambda - I/2) 1 + m(x*),  s*^2 = k_g** - ||g_chol^-1 k_g*||^2
            # (+ the prior mean's parameter uncertainty, noise_prior)
            mu[sl] = Kg @ self.g_beta + gm.value(xs[sl])
            if self.g_gp_var_negligible:  # the bound of the interval [0, k**] (G_GP_VAR_NEGLIGIBLE)
                s2[sl] = kg.diag(xs[sl]) + gm.variance(xs[sl])
            else:
                v = sla.solve_triangular(self.g_chol, Kg.T, lower=True, check_finite=False)
                s2[sl] = kg.diag(xs[sl]) - np.einsum("ij,ij->j", v, v) + gm.variance(xs[sl])
        np.maximum(c2, 0.0, out=c2)
        np.maximum(s2, 0.0, out=s2)
        f_mean = self.y_mean + self.y_scale * a
        f_var = self.y_scale**2 * c2
        g_mean = mu + 2.0 * math.log(self.y_scale)
        g_var = s2
        y_var = f_var + np.exp(g_mean + 0.5 * g_var)
        return VHGPRPrediction(f_mean=f_mean, f_var=f_var, g_mean=g_mean, g_var=g_var,
                               y_mean=f_mean.copy(), y_var=y_var)

    def nlpd(self, X: Any, y: Any) -> float:
        """Mean negative log predictive density (nats) under the Gaussian N(y_mean, y_var).

        Parameters
        ----------
        X : array_like, shape (m, d)
        y : array_like, shape (m,)
        """
        X = self._check_X(X)
        y = _as_float_array(y, "y")
        if y.ndim != 1 or y.shape[0] != X.shape[0]:
            raise DataError(f"y has shape {y.shape}; expected ({X.shape[0]},) to match X")
        _check_finite(y, "y")
        p = self.predict(X)
        return float(np.mean(0.5 * (_LOG_2PI + np.log(p.y_var)) + 0.5 * (y - p.y_mean) ** 2 / p.y_var))

    # ----------------------------------------------------------------------- persistence

    def save(self, path: str | Path) -> None:
        """Write the model to a ``.npz`` file readable with ``np.load(allow_pickle=False)``.

        Arrays and floats are stored as float64 arrays; optional floats as arrays of length
        0 (None) or 1; ``x_names``, ``info``, ``training_hash``, ``geometry_hash`` and
        ``y_name`` as JSON text.

        Raises
        ------
        DataError
            If the file cannot be written.
        """
        arrays: dict[str, np.ndarray] = {"format_version": np.array(FORMAT_VERSION, dtype=np.int64)}
        for name in _ARRAY_FIELDS:
            arrays[name] = np.asarray(getattr(self, name), dtype=np.float64)
        for name in _FLOAT_FIELDS:
            arrays[name] = np.array(float(getattr(self, name)), dtype=np.float64)
        for name in _OPTIONAL_FLOAT_FIELDS:
            v = getattr(self, name)
            arrays[name] = np.array([] if v is None else [float(v)], dtype=np.float64)
        meta = {
            "training_hash": self.training_hash,
            "geometry_hash": self.geometry_hash,
            "x_names": list(self.x_names),
            "y_name": self.y_name,
            "info": _jsonable(self.info),
        }
        meta["g_feature_names"] = list(self.g_feature_names)
        arrays["meta_json"] = np.array(json.dumps(meta))
        for name in _OPTIONAL_ARRAY_FIELDS:
            v = getattr(self, name)
            if v is not None:
                arrays[name] = np.asarray(v, dtype=np.float64)
        path = Path(path)
        try:
            with path.open("wb") as fh:
                np.savez(fh, **arrays)
        except OSError as exc:
            raise DataError(f"{path}: cannot write the model file: {exc.strerror or exc}") from None

    @classmethod
    def load(cls, path: str | Path) -> "FittedVHGPR":
        """Read a model written by :meth:`save`.

        Raises
        ------
        DataError
            Naming the file: unreadable, not an ``.npz``, unknown format version, missing or
            malformed arrays.
        """
        path = Path(path)
        try:
            npz = _open_model_file(path)
        except FileNotFoundError:
            raise DataError(f"{path}: no such model file") from None
        except (OSError, ValueError, zipfile.BadZipFile, EOFError) as exc:
            raise DataError(f"{path}: not a VHGPR model file (.npz): {exc}") from None
        if not isinstance(npz, np.lib.npyio.NpzFile):
            raise DataError(f"{path}: not a VHGPR model file (.npz archive expected, found a single array)")
        with npz:
            try:
                data = {k: npz[k] for k in npz.files}
            except (ValueError, OSError, zipfile.BadZipFile) as exc:
                raise DataError(f"{path}: not a VHGPR model file (.npz): {exc}") from None
        if "format_version" not in data:
            raise DataError(f"{path}: not a VHGPR model file (no 'format_version' array)")
        try:
            version = int(data["format_version"])
        except (TypeError, ValueError):
            raise DataError(f"{path}: malformed 'format_version'") from None
        if version not in _READABLE_VERSIONS:
            raise DataError(f"{path}: model format version {version} is not supported (this microctl reads "
                            f"versions {', '.join(map(str, _READABLE_VERSIONS))})")
        if "mean_coef" in data:
            raise DataError(f"{path}: the model uses the plug-in linear prior mean of microctl 0.1, which is no "
                            f"longer supported (the linear trend is now part of f's kernel); retrain it")
        needed = _ARRAY_FIELDS + _FLOAT_FIELDS + _OPTIONAL_FLOAT_FIELDS + ("meta_json",)
        missing = [k for k in needed if k not in data]
        if missing:
            raise DataError(f"{path}: model file is missing array(s) {', '.join(repr(m) for m in missing)}")
        kw: dict[str, Any] = {}
        try:
            for name in _ARRAY_FIELDS:
                kw[name] = np.asarray(data[name], dtype=np.float64)
            for name in _FLOAT_FIELDS:
                kw[name] = float(data[name])
            for name in _OPTIONAL_FLOAT_FIELDS:
                v = np.asarray(data[name], dtype=np.float64).ravel()
                if v.size > 1:
                    raise ValueError(f"'{name}' has {v.size} values")
                kw[name] = float(v[0]) if v.size else None
            meta = json.loads(str(data["meta_json"]))
            kw["training_hash"] = str(meta["training_hash"])
            gh = meta.get("geometry_hash")
            kw["geometry_hash"] = None if gh is None else str(gh)
            kw["x_names"] = tuple(str(s) for s in meta.get("x_names", []))
            kw["y_name"] = str(meta.get("y_name", ""))
            kw["info"] = dict(meta.get("info", {}))
            kw["g_feature_names"] = tuple(str(s) for s in meta.get("g_feature_names", []))
            for name in _OPTIONAL_ARRAY_FIELDS:
                if name in data:
                    kw[name] = np.asarray(data[name], dtype=np.float64)
        except (TypeError, ValueError, KeyError) as exc:
            raise DataError(f"{path}: malformed model file: {exc}") from None
        X = kw["X"]
        if X.ndim != 2 or X.shape[0] < 1:
            raise DataError(f"{path}: malformed model file: 'X' has shape {X.shape}")
        n, d = X.shape
        shapes = {
            "x_mean": (d,), "x_scale": (d,), "f_log_lengthscales": (d,), "g_log_lengthscales": (d,),
            "log_lambda": (n,), "f_alpha": (n,), "g_beta": (n,), "f_chol": (n, n), "g_chol": (n, n),
        }
        p = kw["g_feature_matrix"].shape[0] if kw.get("g_feature_matrix") is not None and kw["g_feature_matrix"].ndim == 2 else 0
        optional_shapes = {"f_log_linear_vars": (d,), "g_feature_matrix": (p, d), "g_feature_offset": (p,),
                           "g_log_feature_coef": (p,), "g_mean_coef_cov": (p + 1, p + 1)}
        shapes.update({k: s for k, s in optional_shapes.items() if kw.get(k) is not None})
        features = [k for k in ("g_feature_matrix", "g_feature_offset", "g_log_feature_coef") if kw.get(k) is not None]
        if features and len(features) != 3:
            raise DataError(f"{path}: malformed model file: g's prior-mean features need g_feature_matrix, "
                            f"g_feature_offset and g_log_feature_coef together (found {', '.join(features)})")
        for name, shape in shapes.items():
            if kw[name].shape != shape:
                raise DataError(f"{path}: malformed model file: '{name}' has shape {kw[name].shape}, expected {shape}")
        for name in _ARRAY_FIELDS + _OPTIONAL_ARRAY_FIELDS:
            if kw.get(name) is not None:
                _freeze(kw[name])
        model = cls(**kw)
        _check_model_values(path, kw, model)
        return model


# --------------------------------------------------------------------------- the trainer


class VHGPR:
    """Settings of the VHGPR trainer (scikit-learn style); :meth:`fit` returns a :class:`FittedVHGPR`.

    Parameters
    ----------
    bias : bool
        Add a constant (bias) term to both kernels.
    linear : bool or sequence of int
        Add a linear part to f's kernel (:mod:`microctl.gp.kernels`): Bayesian linear
        regression inside the GP, so the mean extrapolates along a fitted trend and its
        variance includes the trend's uncertainty. The noise model weights every point, so
        noisy points do not dominate the trend. True: on every input; a sequence: on those
        input columns (0-based) only.
    linear_prior_var : float or None
        None: the linear part's variances are fitted (ARD, log space). A number: the prior
        variance of every linear coefficient, fixed (standardised units; a large value is
        the vague-prior limit of R&W 2.7, where the trend is estimated by generalised least
        squares and no hyperparameter can switch it off).
    noise_features : NoiseFeatures, optional
        Features of a parametric prior mean of g (:mod:`microctl.gp.noise_prior` eq. 1), in the
        units of the inputs and of y. None (default): the paper's constant mu0.
    n_restarts : int
        Number of optimisation runs in total (>= 1).  The first starts from the
        homoscedastic GP fit; the others from seeded random perturbations of it.  The run
        with the largest bound wins; runs that fail numerically are recorded and skipped.
    max_iter : int or None
        L-BFGS-B iterations per run (function evaluations are capped at 1.25 times this).
        None (default): 100 for n <= 200, then 100 (200/n)^0.6 but at least 25 (58 at
        n = 500, 25 at n = 2000), since each iteration costs O(n^3) and more data need fewer.
    random_state : int or None
        Seed of the perturbations and of the initialisation subset (None: fresh entropy).
    tol : float
        L-BFGS-B ``ftol`` (relative decrease of the negative bound).
    max_time : float or None
        Wall-clock budget in seconds for all runs together; a run that reaches it stops
        and keeps its best point so far.  None: no budget.
    se : {"on", "off", "auto"}
        f's squared-exponential (nonlinear) part. ``"auto"`` (with a linear trend): fit f
        with and without it and keep it only if it raises the MV bound by more than its
        d + 1 hyperparameters cost, ``(d + 1)/2 log n`` (the BIC penalty): on data whose
        mean the trend explains, a free SE part with d lengthscales fits the noise (measured
        on simulated rigs: 0.5-5.5 nats of bound for 2-3 times the error at the workspace's
        faces), while a real nonlinear effect (backlash, contact loss) pays hundreds of nats.
        ``"off"`` needs a linear trend.
    propagate_noise_parameter_uncertainty : bool
        Add the Laplace variance of g's parametric prior mean (``noise_prior`` eq. 2) to g's
        posterior variance. Default False: the covariance is always computed and kept in
        ``info["noise_parameters"]`` (standard errors), but g's variance is the GP's alone.
        Measured on 24 simulated rigs (scripts/bench_rigs.py, docs/controller.md): a
        Gaussian approximation cannot tell a small friction from zero on an actuator the data
        barely isolate, and the quantile objective then avoids the truly quietest poses.
    """

    def __init__(
        self,
        *,
        bias: bool = False,
        linear: bool | tuple[int, ...] = False,
        linear_prior_var: float | None = None,
        noise_features: NoiseFeatures | None = None,
        n_restarts: int = 2,
        max_iter: int | None = None,
        random_state: int | None = 0,
        tol: float = 1e-9,
        max_time: float | None = None,
        se: str = "on",
        propagate_noise_parameter_uncertainty: bool = False,
    ) -> None:
        if int(n_restarts) != n_restarts or n_restarts < 1:
            raise ConfigError(f"VHGPR: n_restarts must be an integer >= 1, got {n_restarts!r}")
        if max_iter is not None and (int(max_iter) != max_iter or max_iter < 1):
            raise ConfigError(f"VHGPR: max_iter must be an integer >= 1, got {max_iter!r}")
        if not (tol > 0):
            raise ConfigError(f"VHGPR: tol must be positive, got {tol!r}")
        if max_time is not None and not (max_time > 0):
            raise ConfigError(f"VHGPR: max_time must be positive or None, got {max_time!r}")
        if noise_features is not None and not isinstance(noise_features, NoiseFeatures):
            raise ConfigError(f"VHGPR: noise_features must be a NoiseFeatures or None, got {type(noise_features).__name__}")
        if linear_prior_var is not None and not (isinstance(linear_prior_var, (int, float))
                                                 and math.isfinite(linear_prior_var) and linear_prior_var > 0):
            raise ConfigError(f"VHGPR: linear_prior_var must be a positive number or None, got {linear_prior_var!r}")
        if not isinstance(linear, bool):
            linear = tuple(int(i) for i in linear)
            if not linear or min(linear) < 0:
                raise ConfigError(f"VHGPR: linear must be a bool or non-empty input indices, got {linear!r}")
        if se not in ("on", "off", "auto"):
            raise ConfigError(f"VHGPR: se must be 'on', 'off' or 'auto', got {se!r}")
        if se != "on" and linear is False:
            raise ConfigError(f"VHGPR: se={se!r} needs a linear trend (linear=True or input indices); "
                              "without it f would be a constant")
        self.se = se
        self.propagate = bool(propagate_noise_parameter_uncertainty)
        self.bias = bool(bias)
        self.linear = linear
        self.linear_prior_var = None if linear_prior_var is None else float(linear_prior_var)
        self.noise_features = noise_features
        self.n_restarts = int(n_restarts)
        self.max_iter = None if max_iter is None else int(max_iter)
        self.random_state = random_state
        self.tol = float(tol)
        self.max_time = max_time

    def __repr__(self) -> str:
        nf = None if self.noise_features is None else list(self.noise_features.names)
        return (f"VHGPR(bias={self.bias}, linear={self.linear}, linear_prior_var={self.linear_prior_var}, se={self.se!r}, "
                f"noise_features={nf}, n_restarts={self.n_restarts}, "
                f"max_iter={self.max_iter}, random_state={self.random_state}, tol={self.tol}, max_time={self.max_time})")

    def fit(self, X: Any, y: Any) -> FittedVHGPR:
        """Maximise the MV bound on (X, y).

        Parameters
        ----------
        X : array_like, shape (n, d)  (a 1-D array is taken as one input column)
        y : array_like, shape (n,)

        Returns
        -------
        FittedVHGPR

        Raises
        ------
        DataError
            Non-finite values, wrong shapes, n < 2, mismatched lengths, constant y, noise
            features of the wrong width.
        MicroctlError
            Every optimisation run failed numerically.
        """
        t0 = time.perf_counter()
        X, y = _validate_training(X, y)
        nf = self.noise_features
        if not isinstance(self.linear, bool) and max(self.linear) >= X.shape[1]:
            raise DataError(f"linear trend on input column {max(self.linear)}; X has {X.shape[1]} columns")
        if nf is not None and np.asarray(nf.matrix).shape[1] != X.shape[1]:
            raise DataError(f"noise features act on {np.asarray(nf.matrix).shape[1]} inputs; X has {X.shape[1]} columns")
        with single_thread_blas():
            return self._fit(X, y, t0)

    def _fit(self, X: np.ndarray, y: np.ndarray, t0: float) -> FittedVHGPR:
        n, d = X.shape
        training_hash = hashlib.sha256(
            np.ascontiguousarray(X, dtype=np.float64).tobytes() + np.ascontiguousarray(y, dtype=np.float64).tobytes()
        ).hexdigest()

        x_mean = X.mean(axis=0)
        x_scale = X.std(axis=0)
        x_scale[x_scale <= 1e-12 * np.maximum(1.0, np.abs(x_mean))] = 1.0  # constant input column
        y_mean = float(y.mean())
        y_scale = float(y.std())
        Xs = (X - x_mean) / x_scale
        ys = (y - y_mean) / y_scale
        nf = self.noise_features
        Phi = As = bs = None
        if nf is not None and nf.p > 0:
            As, bs = nf.standardised(x_mean, x_scale, y_scale)
            lin = Xs @ As.T + bs
            Phi = lin * lin

        rng = np.random.default_rng(self.random_state)
        # a linear trend is affine: f's kernel gets the constant (bias) term with it
        f_spec = KernelSpec(d=d, bias=self.bias or self.linear is not False, linear=self.linear is not False)
        g_spec = KernelSpec(d=d, bias=self.bias)
        lin_bounds = self._linear_bounds(d)
        p = 0 if Phi is None else Phi.shape[1]
        gp, loo, used = _fit_homoscedastic(Xs, ys, f_spec, rng, lin_bounds)
        kern = gp[:-1]
        # Initial point [N]: f's kernel from the homoscedastic GP, Lambda = 1/2 (so mu = m);
        # g's prior mean from its leave-one-out residuals (mu0 = its log noise without features);
        # g's kernel: f's lengthscales, unit signal variance.
        g_kern = np.concatenate([kern[:d], [0.0], [-4.0] if self.bias else []])
        mean0 = _init_mean_coef(loo, None if Phi is None else Phi[used], float(gp[-1]))
        x_init = np.concatenate([np.full(n, math.log(0.5)), kern, g_kern, mean0])

        max_iter = self.max_iter if self.max_iter is not None else _default_max_iter(n)
        deadline = None if self.max_time is None else t0 + float(self.max_time)
        variants = {"on": (False,), "off": (True,), "auto": (True, False)}[self.se]
        fits = []
        for se_off in variants:
            layout = _Layout(n=n, f=f_spec, g=g_spec, p=p, linear_bounds=lin_bounds, se_off=se_off)
            best, runs = self._optimise(x_init, Xs, ys, layout, rng, deadline, max_iter, Phi)
            fits.append((layout, best, runs))
        selection = None
        if len(fits) == 2:  # "auto": the SE part must pay for its d + 1 hyperparameters (BIC)
            penalty = 0.5 * (d + 1) * math.log(n)
            gain = fits[1][1][0] - fits[0][1][0]
            selection = {"bound_affine": fits[0][1][0], "bound_with_se": fits[1][1][0], "penalty": penalty,
                         "kept_se": bool(gain > penalty)}
            layout, best, runs = fits[1] if gain > penalty else fits[0]
            runs = fits[0][2] + fits[1][2]
        else:
            layout, best, runs = fits[0]

        theta = best[1]
        F, _, state = _mv_bound(theta, Xs, ys, layout, want_grad=False, want_state=True, Phi=Phi)
        kf = f_spec.unpack(theta[layout.f_slice])
        kg = g_spec.unpack(theta[layout.g_slice])
        log_c = theta[layout.mean_slice]
        coef_cov = _mean_coef_covariance(state, log_c, Phi) if Phi is not None else None
        noise_parameters = None
        if coef_cov is not None:
            noise_parameters = {"names": ["constant"] + list(nf.names), "c": np.exp(log_c).tolist(),
                                "c_std": np.sqrt(np.diag(coef_cov)).tolist(), "c_cov": coef_cov.tolist(),
                                "units": "standardised (y_scale^2)", "propagated": self.propagate}
        info = {
            "jitter": float(state["jitter"]),
            "restarts_tried": len(runs),
            "restarts_failed": sum(r["status"] == "failed" for r in runs),
            "runs": runs,
            "iterations": int(sum(r.get("iterations", 0) for r in runs)),
            "evaluations": int(sum(r.get("evaluations", 0) for r in runs)),
            "homoscedastic_init": {"log_noise_var": float(gp[-1]), "kernel": [float(v) for v in kern]},
            "se_selection": selection,
            "noise_parameters": noise_parameters,
            "time_s": time.perf_counter() - t0,
            "settings": {"bias": self.bias, "linear": self.linear, "linear_prior_var": self.linear_prior_var,
                         "se": self.se, "propagate_noise_parameter_uncertainty": self.propagate,
                         "n_restarts": self.n_restarts,
                         "max_iter": max_iter, "random_state": self.random_state, "tol": self.tol,
                         "max_time": self.max_time,
                         "noise_features": None if nf is None else list(nf.names)},
        }
        arrays = {
            "x_mean": x_mean, "x_scale": x_scale, "X": Xs,
            "f_log_lengthscales": np.array(kf.log_lengthscales), "g_log_lengthscales": np.array(kg.log_lengthscales),
            "log_lambda": theta[:n].copy(), "f_alpha": state["f_alpha"], "f_chol": state["f_chol"],
            "g_beta": state["g_beta"], "g_chol": state["g_chol"],
        }
        optional = {
            "f_log_linear_vars": None if kf.log_linear_vars is None else np.array(kf.log_linear_vars),
            "g_feature_matrix": As, "g_feature_offset": bs,
            "g_log_feature_coef": None if Phi is None else np.array(log_c[1:]),
            "g_mean_coef_cov": coef_cov if self.propagate else None,
        }
        for a in list(arrays.values()) + [v for v in optional.values() if v is not None]:
            _freeze(a)
        return FittedVHGPR(
            **arrays, **optional,
            y_mean=y_mean, y_scale=y_scale,
            f_log_signal_var=kf.log_signal_var, f_log_bias_var=kf.log_bias_var,
            g_log_signal_var=kg.log_signal_var, g_log_bias_var=kg.log_bias_var,
            g_mu0=float(log_c[0]), bound=float(F), training_hash=training_hash, info=info,
            g_feature_names=() if nf is None else tuple(nf.names),
        )

    def _optimise(self, x_init: np.ndarray, Xs: np.ndarray, ys: np.ndarray, layout: _Layout,
                  rng: np.random.Generator, deadline: float | None, max_iter: int, Phi: np.ndarray | None
                  ) -> tuple[tuple[float, np.ndarray], list[dict]]:
        """``n_restarts`` L-BFGS-B runs from ``x_init`` (then perturbed); the best (bound, theta) and the runs."""
        n = layout.n
        lo, hi = (np.array(b) for b in zip(*layout.bounds()))
        x_init = np.clip(x_init, lo, hi)
        runs: list[dict] = []
        best: tuple[float, np.ndarray] | None = None
        for k in range(self.n_restarts):
            if k == 0:
                x0 = x_init
            else:
                x0 = x_init.copy()
                x0[:n] += 0.1 * rng.standard_normal(n)
                x0[n:] += 0.5 * rng.standard_normal(x0.size - n)
                x0 = np.clip(x0, lo, hi)
            if deadline is not None and time.perf_counter() >= deadline and best is not None:
                runs.append({"start": k, "status": "skipped", "reason": "time budget exhausted"})
                continue
            run = self._run(x0, Xs, ys, layout, deadline, max_iter, Phi)
            run["start"] = k
            run["se"] = not layout.se_off
            x_run = run.pop("x", None)
            runs.append(run)
            if run["status"] == "ok" and (best is None or run["bound"] > best[0]):
                best = (run["bound"], x_run)
        if best is None:
            reasons = "; ".join(f"run {r['start']}: {r.get('reason', r['status'])}" for r in runs)
            raise MicroctlError(f"VHGPR: every optimisation run failed ({reasons})")
        return best, runs

    def _linear_bounds(self, d: int) -> tuple[tuple[float, float], ...] | None:
        """Box bounds of f's [log bias var, log linear variances (d)]: free, fixed at the prior,
        or off (an input without a trend)."""
        if self.linear is False:
            return None
        on = set(range(d)) if self.linear is True else set(self.linear)
        free = _BOUNDS["log_linear_var"]
        fixed = free if self.linear_prior_var is None else (math.log(self.linear_prior_var),) * 2
        off = (free[0], free[0])
        return (fixed,) + tuple(fixed if i in on else off for i in range(d))

    def _run(self, x0: np.ndarray, Xs: np.ndarray, ys: np.ndarray, layout: _Layout, deadline: float | None,
             max_iter: int, Phi: np.ndarray | None = None) -> dict:
        """One L-BFGS-B run from ``x0``; returns a record (status, bound, iterations, x)."""
        t0 = time.perf_counter()
        n = layout.n
        best: list[Any] = [np.inf, None]  # lowest negative bound seen, and where
        counter = {"evals": 0, "failed_evals": 0}
        eval_times: list[float] = []

        class _OutOfTime(Exception):
            pass

        def fun(theta: np.ndarray) -> tuple[float, np.ndarray]:
            if deadline is not None and time.perf_counter() > deadline and best[1] is not None:
                raise _OutOfTime
            counter["evals"] += 1
            te = time.perf_counter()
            try:
                with np.errstate(all="ignore"):
                    F, g, st = _mv_bound(theta, Xs, ys, layout, want_state=False, Phi=Phi)
            except np.linalg.LinAlgError:
                F, g = np.nan, None
            if not np.isfinite(F) or g is None or not np.all(np.isfinite(g)):
                # A numerically impossible point: report a huge value so the line search backs off.
                counter["failed_evals"] += 1
                return 1e25, np.zeros_like(theta)
            eval_times.append(time.perf_counter() - te)
            if -F < best[0]:
                best[0], best[1] = -F, theta.copy()
            # Minimise -F/n: per-point scaling keeps L-BFGS-B's first (unit, projected) step
            # small whatever n is, and makes ``tol`` mean the same for every n.
            return -F / n, -g / n

        record: dict[str, Any] = {}
        try:
            res = minimize(fun, x0, jac=True, method="L-BFGS-B", bounds=layout.bounds(),
                           options={"maxiter": max_iter, "maxfun": int(1.25 * max_iter) + 10,
                                    "ftol": self.tol, "gtol": 1e-6})
            record.update(iterations=int(res.nit), message=str(res.message), converged=bool(res.success))
        except _OutOfTime:
            record.update(iterations=None, message="stopped: time budget reached", converged=False)
        record.update(evaluations=counter["evals"], failed_evaluations=counter["failed_evals"],
                      time_s=time.perf_counter() - t0,
                      eval_time_median_s=float(np.median(eval_times)) if eval_times else None,
                      eval_time_max_s=float(np.max(eval_times)) if eval_times else None)
        if best[1] is None:
            record.update(status="failed", reason="no finite bound at any evaluated point")
            return record
        # Re-evaluate the winner without error suppression, to make sure it is sound.
        try:
            F, _, _ = _mv_bound(best[1], Xs, ys, layout, want_grad=False, Phi=Phi)
        except np.linalg.LinAlgError as exc:
            record.update(status="failed", reason=f"final point not positive definite: {exc}")
            return record
        if not np.isfinite(F):
            record.update(status="failed", reason="non-finite bound at the final point")
            return record
        if record["iterations"] is None:
            record["iterations"] = counter["evals"]
        record.update(status="ok", bound=float(F), x=best[1])
        return record


# --------------------------------------------------------------------------- helpers


def _as_float_array(a: Any, name: str) -> np.ndarray:
    try:
        arr = np.asarray(a, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise DataError(f"{name} is not numeric: {exc}") from None
    return arr


def _check_finite(a: np.ndarray, name: str) -> None:
    bad = ~np.isfinite(a)
    if bad.any():
        idx = tuple(int(i) for i in np.argwhere(bad)[0])
        where = f"row {idx[0]}" + (f", column {idx[1]}" if len(idx) > 1 else "")
        raise DataError(f"{name} has a non-finite value ({a[idx]}) at {where} (0-based); NaN and inf are not allowed")


def _validate_training(X: Any, y: Any) -> tuple[np.ndarray, np.ndarray]:
    """Check and convert training data; DataError with a clear message otherwise."""
    X = _as_float_array(X, "X")
    y = _as_float_array(y, "y")
    if X.ndim == 1:
        X = X[:, None]
    if X.ndim != 2:
        raise DataError(f"X has {X.ndim} dimensions (shape {X.shape}); expected a 2-D array of shape (n, d)")
    if X.shape[1] < 1:
        raise DataError(f"X has shape {X.shape}; it needs at least one input column")
    if y.ndim != 1:
        raise DataError(f"y has shape {y.shape}; expected a 1-D array of shape (n,)")
    if X.shape[0] != y.shape[0]:
        raise DataError(f"X has {X.shape[0]} rows but y has {y.shape[0]} values; they must match")
    if X.shape[0] < 2:
        raise DataError(f"{X.shape[0]} training point(s); at least 2 are needed")
    _check_finite(X, "X")
    _check_finite(y, "y")
    if not float(np.std(y)) > 1e-12 * max(1.0, float(np.max(np.abs(y)))):
        raise DataError(f"y is constant (every value is {y[0]:g}); there is nothing to regress")
    return np.array(X, dtype=np.float64), np.array(y, dtype=np.float64)


def _freeze(a: np.ndarray) -> None:
    a.setflags(write=False)


def _jsonable(obj: Any) -> Any:
    if isinstance(obj, dict):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _jsonable(obj.tolist())
    if isinstance(obj, np.generic):
        return _jsonable(obj.item())
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj



# --------------------------------------------------------------------------- model-file checks (load)

#: Largest predictive variance (units of y²) a loaded model may produce, far from the data or
#: at its training inputs. Beyond it the controller's arithmetic overflows (OverflowError in
#: ``solve``); no fitted model comes near it.
_MAX_MODEL_VARIANCE = 1e100

#: Largest |value| of a log-parameter (log variances, log lengthscales, mu0, log Lambda) in a
#: model file; the fit keeps them within ±20 and exp(300) is still a finite float.
_MAX_LOG_PARAMETER = 300.0

#: Training rows at which a loaded model's factors and predictions are checked (evenly spaced).
_N_CHECK_ROWS = 16

#: Relative tolerance of the factor checks (rounding of a Cholesky factor of size n ≤ 1e5).
_FACTOR_RTOL = 1e-8

#: Tolerance of the standardisation checks (column mean 0, standard deviation 1 or 0).
_STANDARD_TOL = 1e-5


def _open_model_file(path: Path) -> Any:
    """``np.load`` of a model file, once it is known to be a file holding a zip (.npz) archive.

    A ValueError here becomes ``"<path>: not a VHGPR model file (.npz): <message>"`` in
    :meth:`FittedVHGPR.load`, so its message is the reason only.
    """
    if path.is_dir():
        raise ValueError("it is a directory; give the .npz file written by `microctl train` or `microctl gp fit`")
    with path.open("rb") as fh:  # FileNotFoundError: load says "no such model file"
        head = fh.read(64)
    if not head:
        raise ValueError("the file is empty")
    if not head.startswith((b"PK\x03\x04", b"PK\x05\x06")):
        try:
            first = head.decode("utf-8").splitlines()[0]
            what = f"it is a text file starting with {first[:40]!r} (a CSV or YAML file?)"
        except (UnicodeDecodeError, IndexError):
            what = f"it starts with the bytes {head[:8]!r}, not a zip archive"
        raise ValueError(f"{what}; a model file is the .npz archive written by `microctl train` or `microctl gp fit`")
    npz = np.load(path, allow_pickle=False)
    if isinstance(npz, np.lib.npyio.NpzFile):
        try:
            for name in npz.files:  # read once here, so that a wrong dtype is refused, not cast with a warning
                try:
                    a = npz[name]
                except ValueError as exc:
                    if "pickle" in str(exc):
                        raise ValueError(f"array '{name}' holds Python objects (pickled data), which a model "
                                         "file never does") from None
                    raise
                if name != "meta_json" and a.dtype.kind not in "biuf":
                    raise ValueError(f"array '{name}' has dtype {a.dtype}; a model file holds real numbers")
        except BaseException:
            npz.close()
            raise
    return npz


def _check_model_values(path: Path, kw: dict, model: FittedVHGPR) -> None:
    """Refuse a loaded model (``model``, built from the arrays ``kw``) whose numbers cannot come
    from a fit (called at the end of load).

    Checked, each failure one :class:`DataError` naming the file and the array:

    - every array and parameter finite (``bound`` excepted: a record of the fit, NaN for a
      model not fitted by optimisation); ``x_scale`` and ``y_scale`` > 0; every
      log-parameter within ±:data:`_MAX_LOG_PARAMETER`;
    - ``training_hash`` a SHA-256 hex digest;
    - the stored arrays belong together: ``X`` standardised (column mean 0, standard
      deviation 1, or 0 for a constant column); the outputs ``f_chol f_cholᵀ f_alpha``
      standardised likewise (mean 0 only, with a linear prior mean); ``f_chol f_cholᵀ`` equal to K_f(X, X) off the
      diagonal and above it on the diagonal; ``g_chol g_cholᵀ`` equal to K_g(X, X) + Λ⁻¹
      (checked on :data:`_N_CHECK_ROWS` rows). The training hash itself cannot be recomputed
      (the original y is not stored), but arrays edited or taken from two files fail here;
    - the predictive variance far from the data and at the checked training inputs finite
      and at most :data:`_MAX_MODEL_VARIANCE` (a huge variance overflows later, in solve).
    """
    with np.errstate(over="ignore", invalid="ignore", divide="ignore", under="ignore"):
        _check_model_arrays(path, kw, model)  # inf/nan from absurd values fail the checks; no RuntimeWarning


def _check_model_arrays(path: Path, kw: dict, model: FittedVHGPR) -> None:
    """The checks of :func:`_check_model_values` (NumPy floating-point warnings silenced)."""
    import re

    def fail(message: str) -> DataError:
        return DataError(f"{path}: {message}")

    for name in _ARRAY_FIELDS + _OPTIONAL_ARRAY_FIELDS:
        a = kw.get(name)
        if a is None:
            continue
        bad = ~np.isfinite(a)
        if bad.any():
            idx = [int(i) for i in np.argwhere(bad)[0]]
            raise fail(f"array '{name}' has a non-finite value ({a[tuple(idx)]}) at index {idx}; the model file is "
                       "corrupt, retrain it")
    for name in _FLOAT_FIELDS + _OPTIONAL_FLOAT_FIELDS:
        v = kw[name]
        if name != "bound" and v is not None and not math.isfinite(v):
            raise fail(f"'{name}' = {v} is not finite; the model file is corrupt, retrain it")
    if not kw["y_scale"] > 0:
        raise fail(f"'y_scale' = {kw['y_scale']:g} must be > 0 (the standard deviation of the training outputs)")
    if not np.all(kw["x_scale"] > 0):
        raise fail(f"'x_scale' = {kw['x_scale'].tolist()} must be > 0 in every column")
    logs = {n: np.atleast_1d(kw[n]) for n in ("f_log_lengthscales", "g_log_lengthscales", "log_lambda")}
    logs.update({n: np.atleast_1d(kw[n]) for n in ("f_log_signal_var", "g_log_signal_var", "f_log_bias_var",
                                                   "g_log_bias_var", "g_mu0", "f_log_linear_vars",
                                                   "g_log_feature_coef") if kw.get(n) is not None})
    for name, v in logs.items():
        if v.size and np.max(np.abs(v)) > _MAX_LOG_PARAMETER:
            raise fail(f"log-parameter '{name}' = {float(v[np.argmax(np.abs(v))]):g} is beyond "
                       f"±{_MAX_LOG_PARAMETER:g}; the model file is corrupt, retrain it")
    if not re.fullmatch(r"[0-9a-f]{64}", kw["training_hash"]):
        raise fail(f"training_hash {kw['training_hash'][:24]!r} is not a SHA-256 hex digest (64 hex digits)")

    X = kw["X"]
    n, d = X.shape
    col_mean, col_std = X.mean(axis=0), X.std(axis=0)
    for j in range(d):
        const_tol = _STANDARD_TOL * max(1.0, abs(float(kw["x_mean"][j])))
        if abs(col_mean[j]) > _STANDARD_TOL or not (abs(col_std[j] - 1.0) <= _STANDARD_TOL or col_std[j] <= const_tol):
            raise fail(f"the stored arrays do not belong together: column {j} of 'X' has mean {col_mean[j]:.3g} and "
                       f"standard deviation {col_std[j]:.3g}, not the standardised 0 and 1 of a fit; the file was "
                       "edited or assembled from two models, retrain it")
    Lf, Lg = kw["f_chol"], kw["g_chol"]
    if n > 1:
        ys = Lf @ (Lf.T @ kw["f_alpha"])
        if abs(float(ys.mean())) > _STANDARD_TOL or abs(float(ys.std()) - 1.0) > _STANDARD_TOL:
            raise fail(f"the stored arrays do not belong together: the training outputs they encode "
                       f"(f_chol f_cholᵀ f_alpha) have mean {ys.mean():.3g} and standard deviation {ys.std():.3g}, "
                       "not the standardised 0 and 1 of a fit; the file was edited or assembled from two models, "
                       "retrain it")
    rows = np.unique(np.linspace(0, n - 1, min(n, _N_CHECK_ROWS)).astype(int))
    kernels = {"f": model.f_kernel, "g": model.g_kernel}
    for label, L in (("f", Lf), ("g", Lg)):
        G = L[rows] @ L.T  # rows of L Lᵀ
        Kr = kernels[label].matrix(X[rows], X)
        diag_all = np.einsum("ij,ij->i", L, L)
        tol = _FACTOR_RTOL * np.sqrt(np.outer(diag_all[rows], diag_all)) + 1e-300
        off = np.ones_like(G, dtype=bool)
        off[np.arange(len(rows)), rows] = False
        diff = np.where(off, np.abs(G - Kr), 0.0)
        excess = G[np.arange(len(rows)), rows] - Kr[np.arange(len(rows)), rows]
        if label == "g":
            want = np.exp(-kw["log_lambda"][rows])
            diag_bad = np.abs(excess - want) > _FACTOR_RTOL * np.maximum(diag_all[rows], 1.0) * 1e2
        else:
            diag_bad = excess < -tol[np.arange(len(rows)), rows]
        if (diff > tol).any() or diag_bad.any():
            raise fail(f"the stored arrays do not belong together: {label}_chol is not the factor of the kernel of "
                       f"'X' with the stored {label} hyperparameters (K_{label}(X, X)"
                       f"{' + Λ⁻¹' if label == 'g' else ' + noise'}); the file was edited or assembled from two "
                       "models, retrain it")

    two_log_ys = 2.0 * math.log(kw["y_scale"])
    log_kff = np.logaddexp(kw["f_log_signal_var"], kw["f_log_bias_var"] if kw["f_log_bias_var"] is not None else -np.inf)
    kgg = math.exp(kw["g_log_signal_var"]) + (math.exp(kw["g_log_bias_var"]) if kw["g_log_bias_var"] is not None else 0.0)
    log_max = math.log(_MAX_MODEL_VARIANCE)
    for what, log_var in (("epistemic", two_log_ys + float(log_kff)),
                          ("noise", kw["g_mu0"] + two_log_ys + 0.5 * kgg)):
        if log_var > log_max:
            raise fail(f"the model's {what} variance far from the data is e^{log_var:.4g} (units of y²), beyond "
                       f"{_MAX_MODEL_VARIANCE:g} (y_scale = {kw['y_scale']:g}); later arithmetic would overflow: the "
                       "file is corrupt or the fit diverged, retrain it")
    X_orig = X[rows] * kw["x_scale"] + kw["x_mean"]
    try:
        with np.errstate(over="raise", invalid="raise"):
            pred = model.predict(X_orig)
    except (OverflowError, FloatingPointError, DataError) as exc:
        raise fail(f"predicting at the training inputs overflows ({exc}); the file is corrupt or the fit "
                   "diverged, retrain it") from None
    worst = float(np.max(pred.y_var))
    if not (np.all(np.isfinite(pred.y_mean)) and np.isfinite(worst)) or worst > _MAX_MODEL_VARIANCE:
        raise fail(f"the model's predictive variance at its training inputs reaches {worst:.3g} (units of y²), beyond "
                   f"{_MAX_MODEL_VARIANCE:g}; later arithmetic would overflow: the file is corrupt or the fit "
                   "diverged, retrain it")
