"""The posterior of a fitted VHGPR (f and g), once, in NumPy and as CasADi graphs side by side.

From ``notes/vhgpr.md`` [N prediction], at a standardised test input x* (``xs``):

    a*   = k_f*^T (K_f + R)^-1 ys,          c*^2 = k_f** - ||L_f^-1 k_f*||^2        (f)
    mu*  = k_g*^T (Lambda - I/2) 1 + m(x*), s*^2 = k_g** - ||L_g^-1 k_g*||^2        (g)

with ``L_f`` the Cholesky factor of ``K_f + R``, ``L_g`` that of ``K_g + Lambda^-1`` and ``m``
g's prior mean (:mod:`microctl.gp.noise_prior` eq. 1, whose parameter variance eq. 2 adds to
s*^2). In original units the mean of f is ``y_mean + y_scale a*``, its variance ``y_scale^2
c*^2``, and g's mean ``mu* + 2 log y_scale``. :class:`Posterior` holds the precomputed
quantities and offers every form the package uses: the chunked prediction of
:meth:`~microctl.gp.fitted.FittedVHGPR.predict`, the vectorised NumPy forms of the EAFM
(mean of g, its GP variance, joint and pairwise forms) and the CasADi graphs of the EAFM
(``k^T alpha`` means from one dense product, ``k** - ||L^-1 k||^2`` variances with ``L^-1``
a constant sparse lower-triangular DM, or f's in the feature form of its kernel when its SE
part is off: :class:`Posterior`).
"""

from __future__ import annotations

import math
from typing import Any, Callable

import casadi as ca
import numpy as np

from microctl.gp.arrays import freeze
from microctl.gp.kernels import CrossTerms, Kernel, se_matrix
from microctl.gp.linalg import tril_inverse
from microctl.gp.noise_prior import LogVarianceMean

__all__ = ["F_SE_REMAINDER_NEGLIGIBLE", "G_GP_VAR_NEGLIGIBLE", "Posterior"]

#: When the prior variance of g's GP part (signal + bias) is at most this (log-variance
#: units: a standard deviation of 0.01, 1 % on the noise variance), its posterior variance,
#: which lies in [0, that prior variance], is taken as the prior variance itself: the
#: conservative end of the interval, in the NumPy prediction and in the CasADi graph alike,
#: so g's variance costs O(n) instead of O(n^2) per evaluation. Fits whose noise a parametric
#: prior mean explains drive g's signal variance to its lower bound exp(-12), well below.
G_GP_VAR_NEGLIGIBLE = 1e-4

#: When the remainder e of f's kernel in its feature form (:mod:`microctl.gp.kernels`:
#: ``k = psi^T diag(w) psi + e``, e the part of the SE term beyond its rank-one factor) has prior
#: variance at most this at every training input (standardised units: 1e-8 of the output
#: variance), f's variance is computed in that form, O(n p) per point instead of O(n^2). It is
#: the conservative end of an interval that holds the exact variance (see :class:`Posterior`).
#: A fit with f's SE part switched off (its signal variance at the floor exp(-12), its
#: lengthscales at the upper bound e^6) has about 3e-9 there; one with the SE part on, far more.
F_SE_REMAINDER_NEGLIGIBLE = 1e-8
#: The values of :class:`Posterior`'s ``f_form``.
F_FORMS = ("auto", "dense", "features")

#: Kernel factors below exp(-_SE_FLUSH) are set to 0 in the pairwise products (< 1e-150 of
#: the largest, far below round-off); their subnormal values and products slow exp and the
#: BLAS product several-fold (``python -m timeit`` of a 150 x 500 x 160 product with and
#: without the flush shows it).
_SE_FLUSH = 345.0


def _tril_dm(Linv: np.ndarray) -> ca.DM:
    """A lower-triangular matrix as a sparse DM (its lower triangle's pattern)."""
    n = Linv.shape[0]
    rows, cols = np.tril_indices(n)
    order = np.lexsort((rows, cols))  # column-major, as CasADi stores
    rows, cols = rows[order], cols[order]
    sp = ca.Sparsity.triplet(n, n, rows.tolist(), cols.tolist())
    return ca.DM(sp, Linv[rows, cols])


class Posterior:
    """Posterior of f and g of a fitted VHGPR (standardised inputs ``xs``, shape (m, d)).

    f's variance in the feature form of its kernel (when ``f_low_rank``): with the kernel
    column ``k* = Psi W psi* + e*`` (``Psi`` (n, p) the features at the training inputs, ``W``
    their weights, ``e*`` the remainder's column) and ``G = L_f^-1 Psi W`` (n, p),

        c*^2 = k** - ||G psi* + L_f^-1 e*||^2
             = k** - psi*^T (G^T G) psi* - 2 psi*^T (G^T L_f^-1) e* - ||L_f^-1 e*||^2,

    and ``0 <= ||L_f^-1 e*||^2 <= e(x*, x*)`` (L_f L_f^T = K_f + R >= E + R with E, R PSD: the
    explained variance of a GP part is at most its prior variance). The first three terms,
    the upper end of that interval, are what is computed: O(n p + p^2) per point with the
    (p, p) and (p, n) matrices precomputed, so a variance is never below the exact one and
    exceeds it by at most ``e(x*, x*) = sf2 (1 - exp(-|z*|^2))``, below
    :data:`F_SE_REMAINDER_NEGLIGIBLE` at the data and at most sf2 anywhere. The same in NumPy
    and in the CasADi graph; with a sparse-form model (R a full PSD pseudo-noise) likewise.

    Parameters
    ----------
    model : FittedVHGPR
        Any object with its fields (``x_mean``, ``x_scale``, ``y_mean``, ``y_scale``, ``X``,
        ``f_alpha``, ``f_chol``, ``g_beta``, ``g_chol``) and kernels and prior means
        (``f_kernel``, ``g_kernel``, ``g_prior_mean``, ``g_prior_mean_with_uncertainty``).
    f_form : {"auto", "dense", "features"}
        How f's variance is computed: ``"auto"`` (default) in the feature form when the
        remainder is below :data:`F_SE_REMAINDER_NEGLIGIBLE` at every training input, else
        dense; ``"dense"`` or ``"features"`` always (the latter's interval is then as wide as
        e(x*, x*) is: for tests and comparisons).
    """

    def __init__(self, model: Any, f_form: str = "auto"):
        self.x_mean = np.asarray(model.x_mean, dtype=float)
        self.x_scale = np.asarray(model.x_scale, dtype=float)
        self.y_mean = model.y_mean
        self.y_scale = model.y_scale
        self.X = model.X
        self.f_kernel: Kernel = model.f_kernel
        self.g_kernel: Kernel = model.g_kernel
        self.f_alpha = model.f_alpha
        self.f_chol = model.f_chol
        self.g_beta = model.g_beta
        self.g_chol = model.g_chol
        self.prior: LogVarianceMean = model.g_prior_mean
        self.prior_evidence: LogVarianceMean = model.g_prior_mean_with_uncertainty
        k = self.g_kernel
        self.g_gp_var_negligible = bool(k.signal_var + k.bias_var <= G_GP_VAR_NEGLIGIBLE)
        self.log_y2 = 2.0 * math.log(self.y_scale)
        self._Lf_inv: ca.DM | None = None
        self._Lg_inv: ca.DM | None = None
        self._inv: dict[str, np.ndarray] = {}
        self._f_cross: CrossTerms | None = None
        if f_form not in F_FORMS:
            raise ValueError(f"Posterior: f_form must be one of {F_FORMS}, got {f_form!r}")
        #: f's variance in the feature form of its kernel (class docstring)
        self.f_low_rank = (f_form == "features" or (
            f_form == "auto" and bool(np.max(self.f_kernel.se_remainder_diag(self.X)) <= F_SE_REMAINDER_NEGLIGIBLE)))
        self._f_lr: dict[str, np.ndarray] = {}
        self._rows_sides: dict[str, Any] = {}  # train_rows: what each kernel reads of X, computed once

    def chol_inverse(self, which: str) -> np.ndarray:
        """``L^-1`` of f's (``"f"``) or g's (``"g"``) Cholesky factor, shape (n, n), computed once:
        the variances' ``||L^-1 k||^2`` as one product, the same in NumPy and in the graphs."""
        if which not in self._inv:
            self._inv[which] = tril_inverse(np.asarray(self.f_chol if which == "f" else self.g_chol, dtype=float))
        return self._inv[which]

    def standardise(self, X: np.ndarray) -> np.ndarray:
        """``(X - x_mean) / x_scale``, shape (m, d)."""
        return (X - self.x_mean) / self.x_scale

    # ---- NumPy: the prediction (standardised units) ---------------------------------------
    def predict_std(self, xs: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """a*, c*^2, mu* and s*^2 (+ the prior mean's variance) at the rows of xs, each (m,), unclipped.

        Computed in chunks of at most 4e6 kernel entries.
        """
        m = xs.shape[0]
        a = np.empty(m)
        c2 = np.empty(m)
        mu = np.empty(m)
        s2 = np.empty(m)
        kf, kg, gm = self.f_kernel, self.g_kernel, self.prior
        chunk = max(1, 4_000_000 // max(1, self.X.shape[0]))
        for start in range(0, m, chunk):
            sl = slice(start, min(m, start + chunk))
            Kf = self.train_rows("f", xs[sl])
            Kg = self.train_rows("g", xs[sl])
            # [N prediction] a* = k_f*^T (K_f + R)^-1 y,  c*^2 = k_f** - ||f_chol^-1 k_f*||^2
            a[sl] = Kf @ self.f_alpha
            c2[sl] = self._f_var_from(xs[sl], Kf)
            # [N prediction] mu* = k_g*^T (Lambda - I/2) 1 + m(x*),  s*^2 = k_g** - ||g_chol^-1 k_g*||^2
            # (+ the prior mean's parameter uncertainty, noise_prior)
            mu[sl] = Kg @ self.g_beta + gm.value(xs[sl])
            if self.g_gp_var_negligible:  # the bound of the interval [0, k**] (G_GP_VAR_NEGLIGIBLE)
                s2[sl] = kg.diag(xs[sl]) + gm.variance(xs[sl])
            else:
                v = self.chol_inverse("g") @ Kg.T
                s2[sl] = kg.diag(xs[sl]) - np.einsum("ij,ij->j", v, v) + gm.variance(xs[sl])
        return a, c2, mu, s2

    def f_low_rank_terms(self) -> dict[str, np.ndarray]:
        """The precomputed matrices of f's variance in the feature form (class docstring),
        computed once: ``M = G^T G`` (p, p), ``H = G^T L_f^-1`` (p, n), and the training side of the
        remainder e (:meth:`Kernel.se_remainder_side`: ``Z`` (n, d), ``a`` (n,))."""
        if not self._f_lr:
            Linv = self.chol_inverse("f")
            kf = self.f_kernel
            G = Linv @ (kf.features(self.X) * kf.feature_weights)
            H = G.T @ Linv
            Z, az = kf.se_remainder_side(self.X)  # the training side of e(x*, X), read by every call
            self._f_lr = {"M": G.T @ G, "H": np.ascontiguousarray(H), "Z": Z, "a": az}
            for a in self._f_lr.values():
                freeze(a)
        return self._f_lr

    def _f_var_from(self, xs: np.ndarray, Kf: np.ndarray | None) -> np.ndarray:
        """[N prediction] c*^2 = k_f** - ||f_chol^-1 k_f*||^2 at the rows of xs from ``Kf = k_f(xs, X)``, unclipped
        (in the feature form when ``f_low_rank``: the class docstring; then Kf is not read)."""
        if self.f_low_rank:
            t = self.f_low_rank_terms()
            psi, E, diag = self.f_kernel.feature_form(xs, (t["Z"], t["a"]))
            return diag - np.einsum("ij,ij->i", psi, psi @ t["M"] + 2.0 * (E @ t["H"].T))
        v = self.chol_inverse("f") @ Kf.T
        return self.f_kernel.diag(xs) - np.einsum("ij,ij->j", v, v)

    def f_var_std(self, xs: np.ndarray) -> np.ndarray:
        """c*^2 alone (:meth:`predict_std`'s, unclipped, the same chunks and operations, so the same
        to the last bit), shape (m,): f's variance without the O(m n^2) work of g's."""
        m = xs.shape[0]
        c2 = np.empty(m)
        chunk = max(1, 4_000_000 // max(1, self.X.shape[0]))
        for start in range(0, m, chunk):
            sl = slice(start, min(m, start + chunk))
            c2[sl] = self._f_var_from(xs[sl], None if self.f_low_rank else self.train_rows("f", xs[sl]))
        return c2

    # ---- NumPy: vectorised forms (original units of y) -------------------------------------
    def f_mean_and_grad(self, xs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Mean of f, shape (m,), and its gradient in the original inputs, shape (m, d)."""
        f, grad = self.f_mean_lazy_grad(xs)
        return f, grad()

    def f_mean_lazy_grad(self, xs: np.ndarray) -> tuple[np.ndarray, Callable[[], np.ndarray]]:
        """Mean of f, shape (m,), and a function returning its gradient in the original inputs,
        shape (m, d), from the kernel rows the mean computed (the same numbers as
        :meth:`f_mean_and_grad`; a caller that needs the gradient only sometimes skips its work)."""
        if self._f_cross is None:  # the training side, computed once (Kernel.cross_terms)
            self._f_cross = self.f_kernel.cross_terms(self.X, np.asarray(self.f_alpha))
        terms = self._f_cross
        a, se, se_w = self.f_kernel.cross_value_parts(xs, terms)
        f = self.y_mean + self.y_scale * a

        def grad() -> np.ndarray:
            return self.y_scale * self.f_kernel.cross_gradient(xs, terms, se, se_w) / self.x_scale
        return f, grad

    def train_rows(self, which: str, xs: np.ndarray) -> np.ndarray:
        """``k(xs, X)`` of f's (``"f"``) or g's (``"g"``) kernel against the training inputs, shape
        (m, n): :meth:`Kernel.matrix` with what it reads of X computed once (the same numbers)."""
        side = self._rows_sides.get(which)
        kernel = self.f_kernel if which == "f" else self.g_kernel
        if side is None:
            side = self._rows_sides[which] = kernel.rows_side(self.X)
        return kernel.matrix(xs, self.X, side=side)

    def g_kernel_rows(self, xs: np.ndarray) -> np.ndarray:
        """``k_g(xs, X)``, shape (m, n)."""
        return self.train_rows("g", xs)

    def g_mean(self, xs: np.ndarray, Kg: np.ndarray) -> np.ndarray:
        """g's posterior mean (log µm² of y), shape (m,), from ``Kg = k_g(xs, X)``."""
        return Kg @ np.asarray(self.g_beta) + self.prior.value(xs) + self.log_y2

    def g_gp_var(self, xs: np.ndarray, Kg: np.ndarray | None = None) -> np.ndarray:
        """g's GP variance ``k** - ||L_g^-1 k||^2`` (O(m n^2)), or its prior bound ``k**`` when
        negligible (O(m)), shape (m,); ``Kg = k_g(xs, X)`` when the caller has it."""
        if self.g_gp_var_negligible:
            return self.g_kernel.diag(xs)
        Kg = self.train_rows("g", xs) if Kg is None else Kg
        v = self.chol_inverse("g") @ Kg.T
        return np.maximum(self.g_kernel.diag(xs) - np.einsum("ij,ij->j", v, v), 0.0)

    def g_mean_var(self, xs: np.ndarray, *, with_gp_var: bool = True) -> tuple[np.ndarray, np.ndarray]:
        """Mean and variance of g, shapes (m,), (m,); without the GP's O(m n^2) variance term
        unless ``with_gp_var`` (or it is negligible, then its O(m) bound)."""
        Kg = self.train_rows("g", xs)
        var = self.prior.variance(xs)
        if self.g_gp_var_negligible or with_gp_var:
            var = var + self.g_gp_var(xs, Kg)
        return self.g_mean(xs, Kg), var

    def g_uncertainty(self, xs: np.ndarray) -> np.ndarray:
        """g's GP variance plus its prior mean's parameter variance, propagated or not, shape (m,)."""
        return self.g_gp_var(xs) + self.prior_evidence.variance(xs)

    def g_joint(self, xs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Joint posterior of g at the rows of xs: mean (m,), covariance (m, m), with the prior
        mean's parameter covariance whether or not the model propagates it."""
        Kg = self.train_rows("g", xs)
        mean = self.g_mean(xs, Kg)
        cov = self.g_kernel.matrix(xs, xs) + self.prior_evidence.covariance(xs, xs)
        if not self.g_gp_var_negligible:  # else the prior covariance (its bound on the diagonal)
            V = self.chol_inverse("g") @ Kg.T
            cov = cov - V.T @ V
        return mean, cov

    def g_pairs(self, xs_s: np.ndarray, xs_u: np.ndarray, *, with_gp_var: bool = True
                ) -> tuple[np.ndarray, np.ndarray]:
        """Mean and variance of g at every x = [xs_s[i]; xs_u[j]], shapes (m1, m2).

        ``xs_u`` carries the model's context columns after the pose, if it has any (they are
        constant over a move's candidates). g's kernel (ARD SE plus a bias) on the raw inputs is
        separable over the two blocks of inputs, so
        ``k([s_i; u_j], X) . beta = sf2 (A_s o beta) A_u^T + bias sum(beta)``: one (m1 x n)(n x m2)
        product; the prior mean is evaluated on the pairwise linear features (a sum of an s
        part and a u part). The exact GP variance, when not negligible, row by row. A kernel
        with an input map (:mod:`microctl.gp.kernels`) is not separable: its mean row by row.
        """
        ns = xs_s.shape[1]
        kg, X, beta = self.g_kernel, self.X, np.asarray(self.g_beta, dtype=float)
        if kg.input_map is None:
            ls, dk = np.asarray(kg.log_lengthscales, dtype=float), kg.d  # a context beyond dk: prior mean only
            A_s = se_matrix(xs_s, X[:, :ns], ls[:ns], 0.0, flush=_SE_FLUSH)                # (m1, n)
            A_u = se_matrix(xs_u[:, :dk - ns], X[:, ns:dk], ls[ns:], kg.log_signal_var, flush=_SE_FLUSH)  # (m2, n), carries sf2
            mean = (A_s * beta[None, :]) @ A_u.T + kg.bias_var * float(beta.sum())
        else:  # a mapped kernel mixes the blocks (a step reads both): k(x, X) . beta row by row of xs_s
            mean = np.vstack([kg.matrix(np.hstack([np.broadcast_to(s, (xs_u.shape[0], ns)), xs_u]), X) @ beta
                              for s in xs_s])
        prior, prior_var = self._prior_pairs(xs_s, xs_u, mean.shape)
        mean = mean + prior + self.log_y2
        var = prior_var
        if self.g_gp_var_negligible:
            var = var + (kg.signal_var + kg.bias_var)
        elif with_gp_var:  # the prior mean's variance plus the GP's exact term, row by row
            rows = (np.hstack([np.broadcast_to(s, (xs_u.shape[0], ns)), xs_u]) for s in xs_s)
            var = np.vstack([self.prior.variance(xs) + self.g_gp_var(xs) for xs in rows])
        return mean, var

    def _prior_pairs(self, xs_s: np.ndarray, xs_u: np.ndarray, shape: tuple[int, int]
                     ) -> tuple[np.ndarray, np.ndarray]:
        """g's prior mean (``noise_prior`` eq. 1) and its variance (eq. 2) for every pair, (m1, m2)."""
        gm, ns = self.prior, xs_s.shape[1]
        if gm.p == 0:
            prior = np.full(shape, float(gm.log_const))
            prior_var = np.full(shape, float(gm.variance(np.zeros((1, self.X.shape[1])))[0]))
            return prior, prior_var
        F = np.asarray(gm.feature_matrix, dtype=float)
        lin = ((xs_s @ F[:, :ns].T)[:, None, :] + (xs_u @ F[:, ns:].T)[None, :, :]
               + np.asarray(gm.feature_offset, dtype=float))             # (m1, m2, p)
        if gm.gate_matrix is None:
            phi = gm.transform(lin)
        else:
            G = np.asarray(gm.gate_matrix, dtype=float)
            gate = ((xs_s @ G[:, :ns].T)[:, None, :] + (xs_u @ G[:, ns:].T)[None, :, :]
                    + np.asarray(gm.gate_offset, dtype=float))
            phi = gm.transform(lin, gate)
        Phi = np.concatenate([np.ones(lin.shape[:2] + (1,)), phi], axis=2)
        V = Phi @ gm.coef
        prior = np.log(V)                                                 # noise_prior eq. 1
        if gm.coef_cov is None:
            prior_var = np.zeros(shape)
        else:
            J = Phi / V[:, :, None]
            prior_var = np.log1p(np.maximum(np.einsum("abi,ij,abj->ab", J, gm.coef_cov, J), 0.0))  # eq. 2
        return prior, prior_var

    # ---- CasADi --------------------------------------------------------------------------
    def _lf_inv(self) -> ca.DM:
        if self._Lf_inv is None:
            self._Lf_inv = _tril_dm(self.chol_inverse("f"))
        return self._Lf_inv

    def _lg_inv(self) -> ca.DM:
        if self._Lg_inv is None:
            self._Lg_inv = _tril_dm(self.chol_inverse("g"))
        return self._Lg_inv

    def casadi(self, xs: ca.MX, which: tuple[str, ...]) -> dict[str, ca.MX]:
        """The quantities ``which`` (of ``f_mean, f_var, g_mean, g_var``) of a symbolic
        standardised input xs (d, 1), in original units; only those requested enter the graph."""
        out: dict[str, ca.MX] = {}
        need_g = any(k in which for k in ("g_mean", "g_var"))
        need_kf = "f_mean" in which or ("f_var" in which and not self.f_low_rank)
        kf = self.f_kernel.casadi_column(xs, self.X) if need_kf else None
        kg = self.g_kernel.casadi_column(xs, self.X) if need_g else None
        if "f_mean" in which:
            a = ca.dot(kf, ca.DM(np.asarray(self.f_alpha)))
            out["f_mean"] = self.y_mean + self.y_scale * a  # GP mean g_e
        if "f_var" in which:
            # epistemic variance  y_scale^2 (k** - ||L_f^-1 k||^2)  [N prediction]
            if self.f_low_rank:  # in the feature form (class docstring)
                t = self.f_low_rank_terms()
                psi = self.f_kernel.features_casadi(xs)
                e = self.f_kernel.se_remainder_casadi_column(xs, self.X)
                explained = ca.bilin(ca.DM(t["M"]), psi, psi) + 2.0 * ca.dot(psi, ca.mtimes(ca.DM(t["H"]), e))
            else:
                explained = ca.sumsqr(ca.mtimes(self._lf_inv(), kf))
            out["f_var"] = self.y_scale**2 * (self.f_kernel.casadi_diag(xs) - explained)
        if need_g:
            # g's prior mean m(x) (noise_prior eq. 1; the constant mu0 for the paper's model) and
            # its parameter variance
            prior, prior_var = self.prior.casadi(xs, with_variance="g_var" in which)
        if "g_mean" in which:
            out["g_mean"] = ca.dot(kg, ca.DM(np.asarray(self.g_beta))) + prior + self.log_y2
        if "g_var" in which:
            gp_var = self.g_kernel.casadi_diag(xs)
            if not self.g_gp_var_negligible:  # else its bound k** (G_GP_VAR_NEGLIGIBLE)
                gp_var = gp_var - ca.sumsqr(ca.mtimes(self._lg_inv(), kg))
            out["g_var"] = gp_var + prior_var
        return out
