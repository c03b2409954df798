"""A sparse variational heteroscedastic GP: inducing points for f and g, and streaming updates.

The exact VHGPR (:mod:`microctl.gp.trainer`) costs O(n^3) per bound evaluation and its
posterior holds all n training points. This module fits the same model,

    y_i = f(x_i) + e_i,   e_i ~ N(0, exp(g(x_i))),   f ~ GP(0, K_f),   g ~ GP(m(x), K_g),

with M inducing points Z shared by f and g (u_f = f(Z), u_g = g(Z)) and a Gaussian q(u_f) q(u_g),
the chained-GP form of the bound (no quadrature: the Gaussian likelihood's expectation under a
Gaussian q(g) is closed form). In whitened coordinates ``u = L_K v`` (``L_K L_K^T = K(Z, Z)``,
``Phi = K(X, Z) L_K^-T``), with the marginals ``mu_i, s_i^2`` of q(g) and ``a_i, c_i^2`` of q(f):

    E_i  = -1/2 log 2 pi - 1/2 mu_i - 1/2 w_i ((y_i - a_i)^2 + c_i^2),   w_i = exp(-mu_i + s_i^2 / 2)   (S1)
    L    = sum_i E_i - KL(q(v_f) || N(0, I)) - KL(q(v_g) || N(0, I))                                   (S2)

- q(v_f) given q(g) is the maximiser of (S2), a weighted Gaussian regression:
  precision ``I + Phi_f^T W Phi_f``, mean ``P^-1 Phi_f^T W y`` (S3).
- q(v_g) takes damped natural-gradient steps on (S2). The step's precision target is
  ``I + Phi_g^T Lambda Phi_g`` with ``Lambda_i = w_i r_i / 2`` (``r_i = (y_i - a_i)^2 + c_i^2``), so
  q(v_g) keeps the form of Lázaro-Gredilla & Titsias' optimum, one Lambda per point (S4).
  The step length grows while the bound rises and halves when it falls; the iterations stop on
  a relative tolerance of the bound, not on a count.
- The hyperparameters (kernels of f and g, g's prior mean from the noise model) are those of
  an exact VHGPR fitted on a seeded random subset of the data (``subset`` points) with the
  caller's trainer (the hyperparameters are not refined on the sparse bound); Z are k-means centres of the standardised inputs (``n_inducing``).

The fitted model is a :class:`~microctl.gp.fitted.FittedVHGPR` in the *sparse form*
(``posterior_form == "sparse"``): ``X`` holds Z, and every prediction formula of
:mod:`microctl.gp.posterior` holds unchanged, because a sparse posterior is an exact GP
posterior on Z with a full pseudo-noise covariance. With ``A = Phi_Z^T W Phi_Z`` the data's
whitened precision (``Phi_Z = K(Z,Z) L_K^-T = L_K``-coordinates):

    k** - k^T (K^-1 - K^-1 S K^-1) k = k** - k^T (K + R)^-1 k,   R = L_K A^-1 L_K^T          (S5)
    mean = k^T K^-1 m_u = k^T alpha,   alpha = L_K^-T m_v                                      (S6)

so ``f_chol`` is the Cholesky factor of ``K + R`` (the CasADi graphs, the controller and the
model file see n = M points). For g, ``g_beta = L_K^-T m_v`` and ``g_chol`` likewise from its
Lambda. Directions of u no data inform (A's eigenvalues below :data:`_EIG_FLOOR`) get the
prior's variance.

:func:`update` adds k new moves without refitting: the model's posterior over (u_f, u_g)
becomes the prior of the new points (online variational Bayes with Z and hyperparameters
fixed), O(k M^2 + M^3) per iteration. It also applies to an exact model (Z = its training
inputs, where (S5) holds with R diagonal), returning a sparse-form model.
"""

from __future__ import annotations

import hashlib
import time
from collections import OrderedDict
from dataclasses import replace
from typing import Any

import numpy as np
import scipy.linalg as sla
from scipy.cluster.vq import kmeans2

from microctl.errors import ConfigError, DataError
from microctl.gp.arrays import as_float_array, check_finite, freeze, training_hash, validate_training
from microctl.gp.fitted import FittedVHGPR
from microctl.gp.kernels import Kernel
from microctl.gp.linalg import LOG_2PI, chol
from microctl.gp.noise_prior import LogVarianceMean
from microctl.gp.trainer import VHGPR
from microctl.util.blas import single_thread_blas

__all__ = ["SparseVHGPR", "subset_rows", "update", "whitened_posterior"]

#: Eigenvalues of the data's whitened precision A below this are taken as "no information"
#: (the pseudo-noise of (S5) is 1/_EIG_FLOOR times the prior there: variance reduction < 1e-9).
_EIG_FLOOR = 1e-9
#: Jitter on K(Z, Z), relative to its mean diagonal: k-means centres can nearly coincide.
_JITTER = 1e-8
#: exp(-mu + s2/2) is clipped at exp(_MAX_EXP) (a point the model thinks noise-free).
_MAX_EXP = 60.0


class SparseVHGPR:
    """Settings of the sparse VHGPR trainer; :meth:`fit` returns a sparse-form :class:`FittedVHGPR`.

    Parameters
    ----------
    n_inducing : int
        Number M of inducing points (k-means centres of the standardised inputs; all the
        distinct inputs when there are at most M of them).
    subset : int
        Size of the seeded random subset on which the exact VHGPR (``hyper``) fits the
        hyperparameters; all the data when n <= subset.
    hyper : VHGPR, optional
        The exact trainer of the hyperparameters (kernels, noise model, restarts). Default
        ``VHGPR(g_start="both")`` (one more run, from unit lengthscales of g).
    tol : float
        Stop when the bound (S2) changes by less than ``tol * n`` between iterations (nats).
    max_iter : int
        Safety cap on the iterations of (S3)-(S4); reaching it is recorded in ``info``.
    random_state : int or None
        Seed of the subset and of k-means.
    """

    def __init__(self, *, n_inducing: int = 256, subset: int = 1000, hyper: VHGPR | None = None,
                 tol: float = 1e-7, max_iter: int = 500, random_state: int | None = 0) -> None:
        for name, v, lo in (("n_inducing", n_inducing, 2), ("subset", subset, 2), ("max_iter", max_iter, 1)):
            if isinstance(v, bool) or int(v) != v or v < lo:
                raise ConfigError(f"SparseVHGPR: {name} must be an integer >= {lo}, got {v!r}")
        if not (isinstance(tol, (int, float)) and tol > 0):
            raise ConfigError(f"SparseVHGPR: tol must be positive, got {tol!r}")
        if hyper is not None and not isinstance(hyper, VHGPR):
            raise ConfigError(f"SparseVHGPR: hyper must be a VHGPR trainer, got {type(hyper).__name__}")
        self.n_inducing = int(n_inducing)
        self.subset = int(subset)
        self.hyper = hyper if hyper is not None else VHGPR(random_state=random_state, g_start="both")
        self.tol = float(tol)
        self.max_iter = int(max_iter)
        self.random_state = random_state

    def __repr__(self) -> str:
        return (f"SparseVHGPR(n_inducing={self.n_inducing}, subset={self.subset}, hyper={self.hyper!r}, "
                f"tol={self.tol}, max_iter={self.max_iter}, random_state={self.random_state})")

    def fit(self, X: Any, y: Any, *, inducing: np.ndarray | None = None) -> FittedVHGPR:
        """Fit the hyperparameters on a subset, then q(u_f) q(u_g) on all the data.

        Parameters
        ----------
        X : array_like, shape (n, d)
        y : array_like, shape (n,)
        inducing : ndarray, shape (M, d), optional
            Inducing inputs in the ORIGINAL units (default: k-means, see the class).

        Returns
        -------
        FittedVHGPR
            ``posterior_form == "sparse"``, ``X`` the standardised inducing inputs, ``info``
            the subset fit's diagnostics plus ``info["sparse"]`` (n, M, subset, iterations,
            converged, seconds).

        Raises
        ------
        DataError
            As :meth:`VHGPR.fit`; or inducing inputs of the wrong width.
        """
        t0 = time.perf_counter()
        X, y = validate_training(X, y)
        n, d = X.shape
        if inducing is not None:  # checked before any work
            inducing = as_float_array(inducing, "inducing")
            if inducing.ndim != 2 or inducing.shape[1] != d or inducing.shape[0] < 1:
                raise DataError(f"inducing has shape {inducing.shape}; expected (M, {d}) with M >= 1")
            check_finite(inducing, "inducing")
        rng = np.random.default_rng(self.random_state)
        idx = subset_rows(rng, n, self.subset)
        base = self.hyper.fit(X[idx], y[idx])
        t_hyper = time.perf_counter() - t0
        Xs = (X - base.x_mean) / base.x_scale
        ys = (y - base.y_mean) / base.y_scale
        if inducing is None:
            Z = _inducing_points(Xs, self.n_inducing, rng)
        else:
            Z = (inducing - base.x_mean) / base.x_scale
        with single_thread_blas():  # see microctl.util.blas: threads that spin cost more than they give
            state = _Problem(Z, base.f_kernel, base.g_kernel, base.g_prior_mean, Xs, ys)
            bound, iters, converged = state.solve(tol=self.tol, max_iter=self.max_iter)
            info = dict(base.info)
            info["sparse"] = {"n": int(n), "n_inducing": int(Z.shape[0]), "subset": int(idx.size),
                              "iterations": int(iters), "converged": bool(converged), "bound": float(bound),
                              "hyper_seconds": round(t_hyper, 3), "seconds": round(time.perf_counter() - t0, 3)}
            return state.fitted(base, bound=bound, training_hash=training_hash(X, y), info=info)


def subset_rows(rng: np.random.Generator, n: int, size: int) -> np.ndarray:
    """Sorted indices of ``size`` of n rows drawn without replacement (all n when n <= size), shape (min(n, size),)."""
    return np.sort(rng.choice(n, size=size, replace=False)) if n > size else np.arange(n)


#: The last few k-means results, keyed by (digest of the sample, M, seed): the residual model's
#: fits of one data set (microctl.models.training: the selected sources, a refit without the
#: pruned ones, the mean shift) draw the same sample and seed, and k-means is deterministic.
_KMEANS_CACHE: OrderedDict[tuple, np.ndarray] = OrderedDict()
_KMEANS_CACHE_SIZE = 4


def _inducing_points(Xs: np.ndarray, M: int, rng: np.random.Generator) -> np.ndarray:
    """M k-means centres of the rows of Xs (the distinct rows when there are at most M), shape (M', d)."""
    uniq = np.unique(Xs, axis=0)
    if uniq.shape[0] <= M:
        return uniq
    sample = Xs if Xs.shape[0] <= 50 * M else Xs[rng.choice(Xs.shape[0], 50 * M, replace=False)]
    seed = int(rng.integers(2**31 - 1))
    sample = np.ascontiguousarray(sample, dtype=float)
    key = (hashlib.sha256(sample.tobytes()).hexdigest(), sample.shape, M, seed)
    if key in _KMEANS_CACHE:
        _KMEANS_CACHE.move_to_end(key)
        return _KMEANS_CACHE[key].copy()
    centres, labels = kmeans2(sample, M, minit="++", seed=seed, iter=20)
    keep = np.bincount(labels, minlength=M) > 0  # empty clusters keep their initial centre: drop them
    _KMEANS_CACHE[key] = points = centres[keep]  # a new array (boolean indexing); callers get copies
    while len(_KMEANS_CACHE) > _KMEANS_CACHE_SIZE:
        _KMEANS_CACHE.popitem(last=False)
    return points.copy()


class _Problem:
    """The sparse bound (S1)-(S4) for fixed Z, kernels and prior mean; its state is q(v_f), q(v_g)."""

    def __init__(self, Z: np.ndarray, kf: Kernel, kg: Kernel, prior: LogVarianceMean,
                 Xs: np.ndarray, ys: np.ndarray, *, prior_f: tuple | None = None, prior_g: tuple | None = None):
        self.Z, self.kf, self.kg, self.prior = Z, kf, kg, prior
        self.Lf = _kernel_chol(kf, Z)
        self.Lg = _kernel_chol(kg, Z)
        self.M = Z.shape[0]
        # the prior of v in natural form (precision P0, linear term h0): N(0, I) for a fit,
        # the old posterior for an update
        I = np.eye(self.M)
        self.Pf0, self.hf0 = prior_f if prior_f is not None else (I, np.zeros(self.M))
        self.Pg0, self.hg0 = prior_g if prior_g is not None else (I.copy(), np.zeros(self.M))
        self.mz = prior.value(Z)
        self.set_data(Xs, ys)

    def set_data(self, Xs: np.ndarray, ys: np.ndarray) -> None:
        self.Xs, self.ys = Xs, ys
        self.Phf = sla.solve_triangular(self.Lf, self.kf.matrix(Xs, self.Z).T, lower=True).T  # (n, M)
        self.Phg = sla.solve_triangular(self.Lg, self.kg.matrix(Xs, self.Z).T, lower=True).T
        self.qf_diag = self.kf.diag(Xs) - np.einsum("ij,ij->i", self.Phf, self.Phf)  # k** - ||Phi_i||^2 >= 0
        self.qg_diag = self.kg.diag(Xs) - np.einsum("ij,ij->i", self.Phg, self.Phg)
        self.mx = self.prior.value(Xs)
        n = Xs.shape[0]
        self.lam = np.full(n, 0.5)
        self.hg = self.hg0.copy()

    # (S4): q(v_g) from (Lambda, h): precision P0 + Phi^T Lambda Phi, mean P^-1 h
    def q_g(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        P = self.Pg0 + self.Phg.T @ (self.lam[:, None] * self.Phg)
        Lp, _ = chol(P, what="q(u_g) precision")
        m = sla.cho_solve((Lp, True), self.hg)
        V = sla.solve_triangular(Lp, self.Phg.T, lower=True)
        mu = self.mx + self.Phg @ m
        s2 = np.maximum(self.qg_diag + np.einsum("ij,ij->j", V, V), 0.0)
        return m, Lp, mu, s2

    # (S3): the optimal q(v_f) given the weights w
    def q_f(self, w: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        P = self.Pf0 + self.Phf.T @ (w[:, None] * self.Phf)
        Lp, _ = chol(P, what="q(u_f) precision")
        m = sla.cho_solve((Lp, True), self.hf0 + self.Phf.T @ (w * self.ys))
        V = sla.solve_triangular(Lp, self.Phf.T, lower=True)
        a = self.Phf @ m
        c2 = np.maximum(self.qf_diag + np.einsum("ij,ij->j", V, V), 0.0)
        return m, Lp, a, c2

    def _kl(self, P0: np.ndarray, h0: np.ndarray, m: np.ndarray, Lp: np.ndarray) -> float:
        """KL(N(m, P^-1) || N(P0^-1 h0, P0^-1)) with P = Lp Lp^T."""
        L0, _ = chol(P0, what="prior precision")
        Linv = sla.solve_triangular(Lp, np.eye(self.M), lower=True)
        S = Linv.T @ Linv
        m0 = sla.cho_solve((L0, True), h0)
        dm = m - m0
        logdet_S = -2.0 * np.sum(np.log(np.diag(Lp)))
        logdet_S0 = -2.0 * np.sum(np.log(np.diag(L0)))
        return 0.5 * (float(np.sum(P0 * S)) + float(dm @ P0 @ dm) - self.M + logdet_S0 - logdet_S)

    def evaluate(self) -> dict:
        """The bound (S2) at the current q(v_g) with q(v_f) optimal (S3), and the pieces of a step."""
        mg, Lpg, mu, s2 = self.q_g()
        w = np.exp(np.minimum(-mu + 0.5 * s2, _MAX_EXP))
        mf, Lpf, a, c2 = self.q_f(w)
        r = (self.ys - a) ** 2 + c2
        e = w * r
        lik = float(np.sum(-0.5 * LOG_2PI - 0.5 * mu - 0.5 * e))
        bound = lik - self._kl(self.Pf0, self.hf0, mf, Lpf) - self._kl(self.Pg0, self.hg0, mg, Lpg)
        return {"bound": bound, "mg": mg, "mu": mu, "e": e, "mf": mf, "Lpf": Lpf, "Lpg": Lpg}

    def solve(self, *, tol: float, max_iter: int) -> tuple[float, int, bool]:
        """Iterate (S3)-(S4) to a relative tolerance of the bound; returns (bound, iterations, converged)."""
        n = self.Xs.shape[0]
        cur = self.evaluate()
        gamma, it, converged = 0.5, 0, False
        for it in range(1, max_iter + 1):
            lam_old, hg_old = self.lam, self.hg
            # natural-gradient target (S4): d E_i / d mu_i = (e_i - 1)/2, -2 d E_i / d s_i^2 = e_i / 2
            lam_t = 0.5 * cur["e"]
            mu_lin = cur["mu"] - self.mx  # the part of mu linear in v
            h_t = self.hg0 + self.Phg.T @ (0.5 * (cur["e"] - 1.0) + lam_t * mu_lin)
            self.lam = (1.0 - gamma) * lam_old + gamma * lam_t
            self.hg = (1.0 - gamma) * hg_old + gamma * h_t
            new = self.evaluate()
            change = new["bound"] - cur["bound"]
            if change < 0:  # overshoot: undo, shorten the step
                self.lam, self.hg = lam_old, hg_old
                gamma *= 0.5
                if gamma < 1e-6:
                    converged = True
                    break
                continue
            cur = new
            gamma = min(1.0, 1.5 * gamma)
            if change < tol * n:
                converged = True
                break
        self.current = cur
        return cur["bound"], it, converged

    def fitted(self, base: FittedVHGPR, *, bound: float, training_hash: str, info: dict) -> FittedVHGPR:
        """The sparse-form FittedVHGPR (S5)-(S6) of the current state, on ``base``'s standardisation."""
        cur = self.current
        Af = cur["Lpf"] @ cur["Lpf"].T - np.eye(self.M)   # the data's whitened precision of f
        Ag = cur["Lpg"] @ cur["Lpg"].T - np.eye(self.M)
        arrays = {
            "X": self.Z,
            "f_alpha": sla.solve_triangular(self.Lf.T, cur["mf"], lower=False),   # (S6)
            "f_chol": _pseudo_factor(self.Lf, Af),                                 # (S5)
            "g_beta": sla.solve_triangular(self.Lg.T, cur["mg"], lower=False),
            "g_chol": _pseudo_factor(self.Lg, Ag),
            "log_lambda": np.zeros(self.M),
        }
        for v in arrays.values():
            freeze(v)
        return replace(base, **arrays, bound=float(bound), training_hash=training_hash, info=info,
                       posterior_form="sparse")


def _kernel_chol(k: Kernel, Z: np.ndarray) -> np.ndarray:
    """Lower Cholesky factor of K(Z, Z) + jitter."""
    K = k.matrix(Z, Z)
    K[np.diag_indices_from(K)] += _JITTER * float(np.mean(np.diag(K)))
    L, _ = chol(K, what="K(Z, Z)")
    return L


def _pseudo_factor(LK: np.ndarray, A: np.ndarray) -> np.ndarray:
    """Lower Cholesky factor of ``K + R = L_K (I + A^-1) L_K^T`` (S5), A's small eigenvalues floored."""
    A = 0.5 * (A + A.T)
    a, V = np.linalg.eigh(A)
    a = np.maximum(a, _EIG_FLOOR)
    G = LK @ (V * np.sqrt(1.0 + 1.0 / a))      # G G^T = K + R
    R = np.linalg.qr(G.T, mode="r")             # G G^T = R^T R
    L = R.T * np.sign(np.diag(R))               # positive diagonal
    return np.ascontiguousarray(L)


def whitened_posterior(model: FittedVHGPR, which: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """q(v) of f or g of a model (either form) in the whitened coordinates of its inputs X.

    Returns ``(L_K, P, h)``: the Cholesky factor of K(X, X) (+ jitter), and q(v)'s precision
    ``P`` (M, M) and linear term ``h = P m`` (M,), from (S5)-(S6) read backwards:
    ``P = I + A``, ``A^-1 = L_K^-1 (L L^T) L_K^-T - I``.
    """
    k = model.f_kernel if which == "f" else model.g_kernel
    L = np.asarray(model.f_chol if which == "f" else model.g_chol)
    coef = np.asarray(model.f_alpha if which == "f" else model.g_beta)
    LK = _kernel_chol(k, np.asarray(model.X))
    B = sla.solve_triangular(LK, L, lower=True)     # L_K^-1 L
    Minv = B @ B.T                                   # I + A^-1
    ev, V = np.linalg.eigh(0.5 * (Minv + Minv.T))
    a = 1.0 / np.maximum(ev - 1.0, _EIG_FLOOR)       # the eigenvalues of A (~0 where no data informs)
    P = np.eye(LK.shape[0]) + (V * a) @ V.T
    m = LK.T @ coef                                  # (S6): m_v = L_K^T alpha
    return LK, P, P @ m


def update(model: FittedVHGPR, X_new: Any, y_new: Any, *, tol: float = 1e-7, max_iter: int = 200) -> FittedVHGPR:
    """Add k new points to a fitted model without refitting (online variational Bayes).

    The model's q(u_f) q(u_g) become the prior of the new points; Z (the model's inputs),
    the kernels, g's prior mean and the standardisation stay. Cost O(k M^2 + M^3) per
    iteration.

    Parameters
    ----------
    model : FittedVHGPR
        Sparse or exact form (an exact model's training inputs become the inducing points).
    X_new : array_like, shape (k, d)
    y_new : array_like, shape (k,)

    Returns
    -------
    FittedVHGPR
        Sparse form; ``training_hash`` chains the old hash with the new points;
        ``info["sparse"]["updates"]`` counts the points added.
    """
    with single_thread_blas():  # see microctl.util.blas
        return _update(model, X_new, y_new, tol=tol, max_iter=max_iter)


def _update(model: FittedVHGPR, X_new: Any, y_new: Any, *, tol: float, max_iter: int) -> FittedVHGPR:
    t0 = time.perf_counter()
    X_new, y_new = _validate_new(model, X_new, y_new)
    Xs = (X_new - model.x_mean) / model.x_scale
    ys = (y_new - model.y_mean) / model.y_scale
    _, Pf, hf = whitened_posterior(model, "f")
    _, Pg, hg = whitened_posterior(model, "g")
    prob = _Problem(np.asarray(model.X), model.f_kernel, model.g_kernel, model.g_prior_mean, Xs, ys,
                    prior_f=(Pf, hf), prior_g=(Pg, hg))
    bound, iters, converged = prob.solve(tol=tol, max_iter=max_iter)
    chained = hashlib.sha256(model.training_hash.encode() + np.ascontiguousarray(X_new).tobytes()
                             + np.ascontiguousarray(y_new).tobytes()).hexdigest()
    info = dict(model.info)
    sp = dict(info.get("sparse") or {"n": None, "n_inducing": int(model.X.shape[0])})
    sp["updates"] = int(sp.get("updates", 0)) + int(X_new.shape[0])
    sp["last_update"] = {"k": int(X_new.shape[0]), "iterations": int(iters), "converged": bool(converged),
                         "seconds": round(time.perf_counter() - t0, 4)}
    info["sparse"] = sp
    return prob.fitted(model, bound=model.bound, training_hash=chained, info=info)


def _validate_new(model: FittedVHGPR, X: Any, y: Any) -> tuple[np.ndarray, np.ndarray]:
    X = model.check_inputs(X, "X_new")
    if X.shape[0] < 1:
        raise DataError(f"X_new has shape {X.shape}; at least one new point is needed")
    y = as_float_array(y, "y_new")
    if y.shape != (X.shape[0],):
        raise DataError(f"y_new has shape {y.shape}; expected ({X.shape[0]},) to match X_new")
    check_finite(y, "y_new")
    return X, y
