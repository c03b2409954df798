"""The marginalised variational ("MV") bound of the VHGPR and its analytic gradient.

From ``notes/vhgpr.md`` (cited as [N]), Lázaro-Gredilla & Titsias (ICML 2011):

    F = log N(y | 0, K_f + R) - KL(N(mu, Sigma) || N(m 1, K_g)) - tr(Sigma)/4,
    R = diag(exp(mu_i - Sigma_ii / 2))                                                       [N bound]

:func:`mv_bound` evaluates F in named steps: the variational posterior q(g)
(:func:`_q_g`), the Gaussian likelihood of y under K_f + R (:func:`_likelihood`), the bound
itself, and its gradient (:func:`_gradient`) over the flat parameter vector (:class:`Layout`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.linalg import lapack

from microctl.gp.kernels import Kernel, KernelSpec
from microctl.gp.linalg import LOG_2PI, chol, chol_inverse

__all__ = ["BOUNDS", "F_LOG_LENGTHSCALE_MAX", "Layout", "prior_mean_terms", "mv_bound", "mean_coef_covariance"]

# Box bounds of the optimised parameters, in standardised units (inputs and outputs have
# unit variance), chosen wide enough never to bind on sensible data and narrow enough
# that exp() cannot overflow and B = I + Lambda^1/2 K_g Lambda^1/2 stays well conditioned.
BOUNDS = {
    "log_lambda": (-10.0, 10.0),
    "log_lengthscale": (-5.0, 6.0),
    "log_signal_var": (-12.0, 5.0),
    "log_bias_var": (-12.0, 5.0),
    "mu0": (-20.0, 5.0),
    "log_linear_var": (-15.0, 5.0),
    "log_feature_coef": (-30.0, 5.0),  # c_j of g's parametric prior mean (noise_prior eq. 1)
    "log_noise_var": (-20.0, 2.0),  # homoscedastic initialisation only
}

#: Upper bound of f's SE log-lengthscales (standardised inputs), below BOUNDS' 6.0. On a
#: few hundred moves ML-II often drives a lengthscale of f to the wide bound (ell ~ 400 input
#: standard deviations): along that input the SE part is then a near-constant of large signal
#: variance, f's posterior variance stops growing away from the data, and f is confidently
#: wrong where the training moves are thin (the absolute experiment's moves from the zero
#: state). At ell = e^1.5 ~ 4.5 standard deviations the correlation across the data (about
#: +-2 sd) is still >= exp(-16 / (2 * 4.5^2)) ~ 0.67, so an input the data do not need stays
#: nearly ignored, but f keeps an honest variance along it. g (the log-variance) keeps the
#: wide bound: a flat noise direction is a claim the variational bound can check.
#: tests/models/test_mean_shift.py checks f's coverage of an independent truth's mean at moves
#: from the zero state, this bound against the wide one.
F_LOG_LENGTHSCALE_MAX = 1.5

# --------------------------------------------------------------------------- parameter layout


def _switched_off(d: int, bias: bool = False) -> list[tuple[float, float]]:
    """Bounds that switch a kernel's SE part off (f's ``se_off``, g's ``g_off``): its d lengthscales
    pinned at the wide bound, its signal variance (and its bias variance, if it has one) at the floor."""
    ls_hi, sf2_lo, bias_lo = BOUNDS["log_lengthscale"][1], BOUNDS["log_signal_var"][0], BOUNDS["log_bias_var"][0]
    return [(ls_hi, ls_hi)] * d + [(sf2_lo, sf2_lo)] + [(bias_lo, bias_lo)] * bias


@dataclass(frozen=True)
class Layout:
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
    g_off: bool = False  # g's GP switched off (likewise): g is its prior mean

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
        kb = {k: BOUNDS[v] for k, v in (("ls", "log_lengthscale"), ("sf2", "log_signal_var"),
                                          ("bias", "log_bias_var"), ("linear", "log_linear_var"))}
        # f's lengthscales capped at F_LOG_LENGTHSCALE_MAX (see there); g keeps BOUNDS'.
        fb = self.f.bounds(**{**kb, "ls": (kb["ls"][0], F_LOG_LENGTHSCALE_MAX)}, affine=self.linear_bounds)
        if self.se_off:
            fb[: self.f.d + 1] = _switched_off(self.f.d)
        gb = self.g.bounds(**kb)
        if self.g_off:
            gb[: self.g.d + 1 + self.g.bias] = _switched_off(self.g.d, bool(self.g.bias))
        return ([BOUNDS["log_lambda"]] * self.n + fb + gb
                + [BOUNDS["mu0"]] + [BOUNDS["log_feature_coef"]] * self.p)


def prior_mean_terms(log_c: np.ndarray, Phi: np.ndarray | None) -> tuple[np.ndarray | float, np.ndarray | None]:
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


@dataclass(frozen=True, eq=False)
class _QG:
    """The variational posterior q(g) = N(mu, Sigma) at the training inputs [N q(g)] and the
    factors of B = I + Lambda^1/2 K_g Lambda^1/2 it is computed from (shapes (n,) or (n, n))."""

    lam: np.ndarray
    s: np.ndarray  # Lambda^1/2
    LB: np.ndarray  # lower Cholesky factor of B
    T: np.ndarray  # B^-1
    logdet_B: float
    sig_diag: np.ndarray  # diag(Sigma)
    beta: np.ndarray  # (Lambda - I/2) 1
    mu: np.ndarray


@dataclass(frozen=True, eq=False)
class _Lik:
    """The Gaussian likelihood N(y | 0, A), A = K_f + R [N bound] (shapes (n,) or (n, n))."""

    r: np.ndarray  # diag(R)
    LA: np.ndarray  # lower Cholesky factor of A (with its jitter)
    jitter: float
    Ainv: np.ndarray
    alpha: np.ndarray  # A^-1 y
    log_lik: float


def _q_g(log_lam: np.ndarray, Kg: np.ndarray, m: np.ndarray | float) -> _QG:
    """q(g) from log Lambda, K_g and g's prior mean m at the training inputs [N q(g)]."""
    n = log_lam.shape[0]
    lam = np.exp(log_lam)
    # B = I + Lambda^1/2 K_g Lambda^1/2 [N stable forms]; its eigenvalues are >= 1.
    s = np.sqrt(lam)
    Bm = Kg * np.outer(s, s)
    Bm[np.diag_indices(n)] += 1.0
    LB, info = lapack.dpotrf(Bm, lower=1, clean=1)
    if info != 0:
        raise np.linalg.LinAlgError("B = I + Lambda^1/2 K_g Lambda^1/2 is not positive definite")
    T = chol_inverse(LB)  # B^-1
    logdet_B = 2.0 * float(np.sum(np.log(np.diag(LB))))

    # Sigma = (K_g^-1 + Lambda)^-1 = Lambda^-1/2 (I - B^-1) Lambda^-1/2  (since
    # Lambda^1/2 Sigma Lambda^1/2 = S (I + S)^-1 = I - B^-1 with S = Lambda^1/2 K_g Lambda^1/2).
    sig_diag = (1.0 - np.diag(T)) / lam
    beta = lam - 0.5  # (Lambda - I/2) 1
    mu = Kg @ beta + m  # [N q(g)], with the prior mean m(x) in place of mu0
    return _QG(lam=lam, s=s, LB=LB, T=T, logdet_B=logdet_B, sig_diag=sig_diag, beta=beta, mu=mu)


def _likelihood(Kf: np.ndarray, q: _QG, y: np.ndarray) -> _Lik:
    """log N(y | 0, K_f + R) with R = diag(exp(mu_i - Sigma_ii / 2)) [N bound]."""
    n = y.shape[0]
    r = np.exp(q.mu - 0.5 * q.sig_diag)
    A = Kf.copy()
    A[np.diag_indices(n)] += r
    LA, jitter = chol(A, what="K_f + R")
    Ainv = chol_inverse(LA)
    alpha = Ainv @ y

    # log N(y | 0, K_f + R); the jitter (if any) is part of the covariance actually used.
    log_lik = -0.5 * float(y @ alpha) - float(np.sum(np.log(np.diag(LA)))) - 0.5 * n * LOG_2PI
    return _Lik(r=r, LA=LA, jitter=jitter, Ainv=Ainv, alpha=alpha, log_lik=log_lik)


def _bound(q: _QG, lik: _Lik, m: np.ndarray | float) -> float:
    """F = log N - KL - tr(Sigma)/4 [N bound]."""
    n = q.lam.shape[0]
    # KL(N(mu, Sigma) || N(m, K_g)) = 1/2 [tr(K_g^-1 Sigma) + (mu - m)^T K_g^-1 (mu - m)
    #     - n + log|K_g| - log|Sigma|] with tr(K_g^-1 Sigma) = tr(B^-1),
    # (mu - m)^T K_g^-1 (mu - m) = beta^T K_g beta, log|K_g| - log|Sigma| = log|B|.
    kl = 0.5 * (float(np.trace(q.T)) + float(q.beta @ (q.mu - m)) - n + q.logdet_B)
    return lik.log_lik - kl - 0.25 * float(np.sum(q.sig_diag))


def _gradient(q: _QG, lik: _Lik, X: np.ndarray, kf: Kernel, kg: Kernel, Kf_se: np.ndarray, Kg: np.ndarray,
              Kg_se: np.ndarray, dm: np.ndarray | None) -> np.ndarray:
    """dF/d(log Lambda, f kernel block, g kernel block, log c), shape (layout.size,)."""
    lam, T, beta, s, alpha, Ainv, r = q.lam, q.T, q.beta, q.s, lik.alpha, lik.Ainv, lik.r
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
    return np.concatenate([g_lam, g_f, g_g, g_m])


def mv_bound(theta: np.ndarray, X: np.ndarray, y: np.ndarray, layout: Layout, *, want_grad: bool = True,
             want_state: bool = False, Phi: np.ndarray | None = None
             ) -> tuple[float, np.ndarray | None, dict | None]:
    """The MV bound F and its gradient with respect to the flat parameter vector.

    Parameters
    ----------
    theta : ndarray, shape (layout.size,)
        See :class:`Layout`.
    X : ndarray, shape (n, d), standardised inputs
    y : ndarray, shape (n,), standardised outputs
    layout : Layout
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
    kf = layout.f.unpack(theta[layout.f_slice])
    kg = layout.g.unpack(theta[layout.g_slice])
    m, dm = prior_mean_terms(theta[layout.mean_slice], Phi)

    Kf_se = kf.se(X, X)
    Kg_se = kg.se(X, X)
    Kf = kf.matrix(X, X, se=Kf_se)
    Kg = kg.matrix(X, X, se=Kg_se)

    q = _q_g(theta[:n], Kg, m)
    lik = _likelihood(Kf, q, y)
    F = _bound(q, lik, m)
    grad = _gradient(q, lik, X, kf, kg, Kf_se, Kg, Kg_se, dm) if want_grad else None

    state = None
    if want_state:
        state = {
            "f_alpha": lik.alpha,
            "f_chol": lik.LA,
            "g_beta": q.beta,
            # K_g + Lambda^-1 = Lambda^-1/2 B Lambda^-1/2, so its lower factor is Lambda^-1/2 L_B.
            "g_chol": q.LB / q.s[:, None],
            "jitter": lik.jitter,
            "mu": q.mu,
            "sigma_diag": q.sig_diag,
            "r": lik.r,
            "A_inv": lik.Ainv,
        }
    return F, grad, state


def mean_coef_covariance(state: dict, log_c: np.ndarray, Phi: np.ndarray | None) -> np.ndarray:
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
