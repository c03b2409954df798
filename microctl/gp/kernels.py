"""The covariance functions of the VHGPR, in one place for the trainer, the graph and the diagnosis.

One kernel family, written once:

    k(x, x') = sf2 * exp(-1/2 sum_d ((x_d - x'_d) / l_d)^2)          ARD squared exponential
               + b                                                   optional bias
               + sum_d v_d x_d x'_d                                  optional ARD linear part
               + v_t sum_j phi_j(x) phi_j(x')                        optional feature trend (f only)

All hyperparameters are positive and live in log space (``log l``, ``log sf2``, ``log b``,
``log v``). The linear part is Bayesian linear regression on the inputs folded into the GP
(Rasmussen & Williams 2006, sect. 2.7 with a Gaussian prior on the coefficients): the
posterior mean then extrapolates along the fitted trend, and the posterior variance
includes the coefficients' uncertainty. The AFM residual is dominated by linear
miscalibration (actuator gains, offsets, sensor scale), which an SE kernel alone
extrapolates poorly towards the faces of the workspace, where quiet poses lie. The feature
trend (:mod:`microctl.gp.trend`) is the same regression on fixed nonlinear features of the
inputs, with a fixed prior variance (no hyperparameter of the block).

:class:`KernelSpec` says which parts a kernel has and where each hyperparameter sits in a
flat block; :class:`Kernel` is one kernel with its hyperparameters, evaluated in NumPy
(:meth:`Kernel.matrix`, :meth:`Kernel.diag`, :meth:`Kernel.grad_traces`) and as CasADi
expressions against fixed training inputs (:meth:`Kernel.casadi_column`). Its *feature form*
(:meth:`Kernel.features`, :meth:`Kernel.se_remainder`) writes it as explicit features plus a
PSD remainder, from which :mod:`microctl.gp.posterior` computes f's variance in O(n p).

A kernel of d lengthscales reads the first d columns of its inputs: inputs may carry further
columns that only g's prior mean reads (a move's context, such as each actuator's last
direction of motion: :mod:`microctl.models.noise_dictionary`), which the kernels ignore.
A kernel with an ``input_map`` M (d, d_in) reads the first d_in columns x and evaluates
every part on ``M x`` instead: a fixed linear change of inputs (for g, the actuators'
positions and steps, :func:`microctl.models.noise_inputs.actuator_inputs`), so that ARD
lengthscales lie along physical directions that are diagonal in no raw input.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import casadi as ca
import numpy as np

from microctl.gp.trend import FeatureTrend

__all__ = ["KernelSpec", "Kernel", "CrossTerms", "RowsSide", "se_matrix", "ard_se"]


def se_matrix(Xa: np.ndarray, Xb: np.ndarray, log_lengthscales: np.ndarray, log_signal_var: float,
              flush: float | None = None) -> np.ndarray:
    """The ARD squared-exponential part ``sf2 exp(-|(xa - xb) / l|^2 / 2)``, shape (m, n).

    Computed as ``|a|^2 + |b|^2 - 2 a.b`` on scaled inputs (one BLAS product), clipped at 0.

    Parameters
    ----------
    Xa : ndarray, shape (m, d)
    Xb : ndarray, shape (n, d)
    log_lengthscales : ndarray, shape (d,)
    log_signal_var : float
    flush : float, optional
        Factors ``exp(-|.|^2 / 2)`` below ``exp(-flush)`` are set to 0 instead of computed:
        subnormal values slow ``exp`` and the BLAS products that use the matrix several-fold.
    """
    inv_ls = np.exp(-np.asarray(log_lengthscales, dtype=float))
    Zb = np.asarray(Xb, dtype=float) * inv_ls
    return _se_scaled(np.asarray(Xa, dtype=float) * inv_ls, Zb, -0.5 * np.einsum("ij,ij->i", Zb, Zb),
                      log_signal_var, flush)


def _se_scaled(Za: np.ndarray, Zb: np.ndarray, half_zb2: np.ndarray, log_signal_var: float,
               flush: float | None = None) -> np.ndarray:
    """:func:`se_matrix` from the scaled inputs Za (m, d), Zb (n, d) and Zb's squared row norms
    times -1/2, ``half_zb2`` (n,), which a caller evaluating against fixed training inputs
    computes once."""
    # -|za - zb|^2 / 2 as -(|za|^2 + |zb|^2) / 2 + za.zb: the factor -1/2 applied to the two norm
    # vectors, not twice to the (m, n) array (as 2 za.zb, then -1/2 times the difference). A
    # power of two scales exactly (outside the subnormal range), so the same numbers to the last
    # bit with two passes over the (m, n) array fewer
    sq = (-0.5 * np.einsum("ij,ij->i", Za, Za))[:, None] + half_zb2[None, :]
    sq += Za @ Zb.T
    # clipped at 0 (a squared distance below 0 is round-off) by a masked store, several times
    # faster than np.minimum on a large array; the same kernel to the last bit (a -0.0 or a +0.0
    # goes through exp to 1 alike)
    sq[sq > 0.0] = 0.0
    far = None
    if flush is not None:
        far = sq < -flush
        np.maximum(sq, -flush, out=sq)
    np.exp(sq, out=sq)
    if far is not None:
        sq[far] = 0.0
    sq *= math.exp(float(log_signal_var))
    return sq


@dataclass(frozen=True)
class CrossTerms:
    """The training side of :meth:`Kernel.cross_grad`: inputs X (n, d), weights (n,) and their
    product ``weights[:, None] * X`` (n, d), the scaled inputs Z = X / l (n, d) and their squared
    norms times -1/2 (n,), and the bias, linear (d,) and trend (t,) parts' sums over the weights
    (None where the kernel has no such part)."""

    X: np.ndarray
    weights: np.ndarray
    WX: np.ndarray
    inv_ls: np.ndarray
    Z: np.ndarray
    half_z2: np.ndarray
    bias: float
    linear: np.ndarray | None
    trend: np.ndarray | None


@dataclass(frozen=True)
class RowsSide:
    """What :meth:`Kernel.matrix` reads of its second argument Xb: the kernel's inputs X (n, d),
    the scaled inputs Z = X / l (n, d), their squared norms times -1/2 (n,) and the trend's
    features of Xb (n, t; None without a trend). A posterior's training inputs do not change:
    computed once."""

    X: np.ndarray
    Z: np.ndarray
    half_z2: np.ndarray
    trend: np.ndarray | None


@dataclass(frozen=True)
class KernelSpec:
    """Which parts a kernel on d inputs has, and the layout of its hyperparameter block.

    The block is ``[log l (d), log sf2, (log b), (log v (d))]``.

    Attributes
    ----------
    d : int
        Input dimension.
    bias : bool
        Constant term b.
    linear : bool
        ARD linear part with variances v (d).
    trend : FeatureTrend or None
        Fixed feature trend (:mod:`microctl.gp.trend`); not in the hyperparameter block.
    input_map : tuple of d rows, or None
        Fixed linear map M (d, d_in) of the inputs the kernel reads (see the module
        docstring); a tuple so that specs compare by value.
    """

    d: int
    bias: bool = False
    linear: bool = False
    trend: FeatureTrend | None = None
    input_map: tuple[tuple[float, ...], ...] | None = None

    @property
    def size(self) -> int:
        """Length of the hyperparameter block."""
        return self.d + 1 + int(self.bias) + (self.d if self.linear else 0)

    def unpack(self, block: np.ndarray) -> "Kernel":
        """The kernel with the hyperparameters of a flat block (see the class docstring)."""
        block = np.asarray(block, dtype=float)
        d = self.d
        log_b = float(block[d + 1]) if self.bias else None
        log_v = block[d + 1 + int(self.bias):].copy() if self.linear else None
        return Kernel(log_lengthscales=block[:d].copy(), log_signal_var=float(block[d]), log_bias_var=log_b,
                      log_linear_vars=log_v, trend=self.trend,
                      input_map=None if self.input_map is None else np.array(self.input_map, dtype=float))

    def bounds(self, ls: tuple[float, float], sf2: tuple[float, float], bias: tuple[float, float],
               linear: tuple[float, float], affine: Sequence[tuple[float, float]] | None = None
               ) -> list[tuple[float, float]]:
        """Box bounds of the block, from the bounds of each kind of hyperparameter; ``affine``
        (d + 1 pairs), for a kernel with a linear part, replaces those of [bias, linear (d)]
        (the affine trend's prior variances, fixed or free)."""
        out = [ls] * self.d + [sf2]
        if self.bias:
            out.append(bias)
        if self.linear:
            out += [linear] * self.d
            if affine is not None:
                out[-self.d - 1:] = list(affine)
        return out


@dataclass(frozen=True, eq=False)
class Kernel:
    """One kernel of the family (see the module docstring), hyperparameters in log space.

    Attributes
    ----------
    log_lengthscales : ndarray, shape (d,)
    log_signal_var : float
    log_bias_var : float or None
    log_linear_vars : ndarray, shape (d,), or None
    trend : FeatureTrend or None
        The fixed feature trend (:mod:`microctl.gp.trend`), reading the first d inputs.
    input_map : ndarray, shape (d, d_in), or None
        Fixed linear map of the first d_in inputs; every part reads ``M x`` (module docstring).
    """

    log_lengthscales: np.ndarray
    log_signal_var: float
    log_bias_var: float | None = None
    log_linear_vars: np.ndarray | None = None
    trend: FeatureTrend | None = None
    input_map: np.ndarray | None = None

    def __post_init__(self) -> None:
        M = self.input_map
        if M is not None and (np.ndim(M) != 2 or np.shape(M)[0] != np.size(self.log_lengthscales)):
            raise ValueError(f"input_map has shape {np.shape(M)}; expected ({np.size(self.log_lengthscales)}, d_in), "
                             "one row per lengthscale")
        if M is not None and self.trend is not None:
            raise ValueError("a kernel with an input_map cannot carry a feature trend (the trend reads raw inputs)")
        # d and d_in, read by every evaluation (:meth:`_cols`), counted once
        d = int(np.size(self.log_lengthscales))
        object.__setattr__(self, "_d", d)
        object.__setattr__(self, "_d_in", d if M is None else int(np.shape(M)[1]))

    @property
    def spec(self) -> KernelSpec:
        """The :class:`KernelSpec` of this kernel."""
        M = None if self.input_map is None else tuple(tuple(float(v) for v in row) for row in self.input_map)
        return KernelSpec(d=int(np.size(self.log_lengthscales)), bias=self.log_bias_var is not None,
                          linear=self.log_linear_vars is not None, trend=self.trend, input_map=M)

    def pack(self) -> np.ndarray:
        """The flat hyperparameter block (inverse of :meth:`KernelSpec.unpack`)."""
        parts = [np.asarray(self.log_lengthscales, dtype=float), [self.log_signal_var]]
        if self.log_bias_var is not None:
            parts.append([self.log_bias_var])
        if self.log_linear_vars is not None:
            parts.append(np.asarray(self.log_linear_vars, dtype=float))
        return np.concatenate(parts)

    @property
    def signal_var(self) -> float:
        return math.exp(self.log_signal_var)

    @property
    def bias_var(self) -> float:
        """b (0 when the kernel has no bias)."""
        return math.exp(self.log_bias_var) if self.log_bias_var is not None else 0.0

    @property
    def linear_vars(self) -> np.ndarray | None:
        """v, shape (d,), or None."""
        return None if self.log_linear_vars is None else np.exp(np.asarray(self.log_linear_vars, dtype=float))

    @property
    def d(self) -> int:
        """Number of lengthscales: the kernel's inputs (the first d columns, or ``M x``)."""
        return self._d

    @property
    def d_in(self) -> int:
        """Number of input columns the kernel reads (d, or the input map's columns)."""
        return self._d_in

    def _cols(self, X: np.ndarray) -> np.ndarray:
        """The kernel's inputs from X (see the module docstring): its first d_in columns, mapped
        by the input map if there is one; shape (m, d)."""
        X = np.asarray(X, dtype=float)
        d_in = self._d_in
        X = X[:, :d_in] if X.ndim == 2 and X.shape[1] > d_in else X
        return X if self.input_map is None else X @ np.asarray(self.input_map, dtype=float).T

    def inputs(self, X: np.ndarray) -> np.ndarray:
        """What the kernel reads of X (its first d_in columns, mapped if it has a map), shape (m, d)."""
        return self._cols(X)

    def _cols_ca(self, xs: ca.MX) -> ca.MX:
        """:meth:`_cols` of a symbolic column (d', 1), d' >= d_in."""
        xs = xs[:self.d_in] if xs.shape[0] > self.d_in else xs
        return xs if self.input_map is None else ca.mtimes(ca.DM(np.asarray(self.input_map, dtype=float)), xs)

    # ---- NumPy ---------------------------------------------------------------------
    def se(self, Xa: np.ndarray, Xb: np.ndarray) -> np.ndarray:
        """The SE part alone, shape (m, n)."""
        return se_matrix(self._cols(Xa), self._cols(Xb), self.log_lengthscales, self.log_signal_var)

    def matrix(self, Xa: np.ndarray, Xb: np.ndarray, se: np.ndarray | None = None,
               side: RowsSide | None = None) -> np.ndarray:
        """k(Xa, Xb), shape (m, n); ``se`` reuses an SE part already computed; ``side``, the
        :meth:`rows_side` of Xb, stands for what is read of Xb (computed once for fixed training
        inputs; the same numbers)."""
        if se is not None:
            K = se.copy()
        elif side is None:
            K = self.se(Xa, Xb)
        else:
            inv_ls = np.exp(-np.asarray(self.log_lengthscales, dtype=float))
            K = _se_scaled(self._cols(Xa) * inv_ls, side.Z, side.half_z2, self.log_signal_var)
        if self.log_bias_var is not None:
            K += self.bias_var
        v = self.linear_vars
        if v is not None:
            K += (self._cols(Xa) * v) @ (self._cols(Xb) if side is None else side.X).T
        if self.trend is not None:
            K += (self.trend.var * self.trend.values(Xa)) @ (self.trend.values(Xb) if side is None else side.trend).T
        return K

    def rows_side(self, Xb: np.ndarray) -> RowsSide:
        """What :meth:`matrix` reads of its second argument Xb (n, d'), for ``side=``."""
        Z, z2 = self._z2(Xb)
        return RowsSide(X=self._cols(Xb), Z=Z, half_z2=-0.5 * z2, trend=None if self.trend is None else self.trend.values(Xb))

    def diag(self, X: np.ndarray) -> np.ndarray:
        """k(x, x) at the rows of X, shape (m,)."""
        Xc = self._cols(X)
        return self._diag_of(Xc, None if self.trend is None else self.trend.values(Xc))

    def _diag_of(self, Xc: np.ndarray, trend: np.ndarray | None) -> np.ndarray:
        """k(x, x) from the kernel's inputs Xc (m, d) and the trend's features of Xc (m, t) or None."""
        out = np.full(Xc.shape[0], self.signal_var + self.bias_var)
        v = self.linear_vars
        if v is not None:
            out += (Xc * Xc) @ v
        if trend is not None:
            out += self.trend.var * np.einsum("ij,ij->i", trend, trend)
        return out

    def grad_traces(self, G: np.ndarray, se: np.ndarray, X: np.ndarray) -> np.ndarray:
        """``sum_ij G_ij dk(x_i, x_j)/dtheta`` for every theta of the block, shape (spec.size,).

        For the SE part with Z = X / l: ``dK/dlog l_d = K_se (z_id - z_jd)^2`` and, for
        symmetric ``H = G o K_se``, ``sum_ij H_ij (z_id - z_jd)^2 = 2 sum_i z_id^2 (H 1)_i -
        2 z_d^T H z_d``: one product H Z, no (n, n, d) temporary. ``dK/dlog sf2 = K_se``,
        ``dK/dlog b = b``, ``dK/dlog v_d = v_d x_d x_d^T``.

        Parameters
        ----------
        G : ndarray, shape (n, n), symmetric
        se : ndarray, shape (n, n), the SE part of k(X, X)
        X : ndarray, shape (n, d)
        """
        H = G * se
        X = self._cols(X)
        Z = X * np.exp(-np.asarray(self.log_lengthscales, dtype=float))
        h = H.sum(axis=1)
        HZ = H @ Z
        out = [2.0 * (Z * Z).T @ h - 2.0 * np.einsum("ij,ij->j", Z, HZ), [h.sum()]]
        if self.log_bias_var is not None:
            out.append([self.bias_var * G.sum()])
        v = self.linear_vars
        if v is not None:
            out.append(v * np.einsum("ij,ij->j", X, G @ X))
        return np.concatenate(out)

    def cross_terms(self, X: np.ndarray, weights: np.ndarray) -> CrossTerms:
        """What :meth:`cross_grad` computes from ``X`` and ``weights`` alone, computed once (a
        fitted posterior's training inputs and weights do not change between calls).

        Parameters
        ----------
        X : ndarray, shape (n, d)
        weights : ndarray, shape (n,)
        """
        Z, z2 = self._z2(X)
        X = self._cols(X)
        weights = np.asarray(weights, dtype=float)
        v = self.linear_vars
        return CrossTerms(
            X=X, weights=weights, WX=weights[:, None] * X, Z=Z, half_z2=-0.5 * z2,
            inv_ls=np.exp(-np.asarray(self.log_lengthscales, dtype=float)),
            bias=self.bias_var * float(np.sum(weights)),
            linear=None if v is None else (X * v).T @ weights,
            trend=None if self.trend is None else self.trend.var * (self.trend.values(X).T @ weights))

    def cross_grad(self, Xs: np.ndarray, terms: CrossTerms) -> tuple[np.ndarray, np.ndarray]:
        """``k(Xs, X) @ weights`` and its gradient in the rows of Xs (vectorised, for seeding).

        Parameters
        ----------
        Xs : ndarray, shape (m, d')
            d' >= d; the columns beyond the kernel's d are not read.
        terms : CrossTerms
            :meth:`cross_terms` of the training inputs X (n, d) and weights (n,), computed once
            per fitted posterior (they do not change between calls).

        Returns
        -------
        value : ndarray, shape (m,)
        grad : ndarray, shape (m, d')
            Zero in the columns beyond the kernel's d.
        """
        value, se, se_w = self.cross_value_parts(Xs, terms)
        return value, self.cross_gradient(Xs, terms, se, se_w)

    def cross_value_parts(self, Xs: np.ndarray, terms: CrossTerms) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`cross_grad`'s value alone, the SE part ``k_se(Xs, X)`` (m, n) and the product
        ``k_se(Xs, X) @ weights`` (m,) its value adds to: what :meth:`cross_gradient` reads (so a
        caller that needs the gradient only sometimes, a Newton step's convergence check, pays for
        the (m, n) kernel once)."""
        Xs = self._cols(Xs)
        K = _se_scaled(Xs * terms.inv_ls, terms.Z, terms.half_z2, self.log_signal_var)  # the SE part, training side precomputed
        Kw = K @ terms.weights
        value = Kw + terms.bias
        if terms.linear is not None:
            value = value + Xs @ terms.linear
        if terms.trend is not None:  # v_t phi(xs) . (Phi(X)^T w)
            value = value + self.trend.values(Xs) @ terms.trend
        return value, K, Kw

    def cross_gradient(self, Xs: np.ndarray, terms: CrossTerms, se: np.ndarray, se_weights: np.ndarray) -> np.ndarray:
        """:meth:`cross_grad`'s gradient, shape (m, d'), from :meth:`cross_value_parts`'s SE part
        ``se`` and its ``se_weights`` = ``se @ weights``."""
        width = np.asarray(Xs).shape[1]
        Xs = self._cols(Xs)
        inv_ls = terms.inv_ls
        # d k_se(x, X_i)/dx = -k_se (x - X_i) / l^2: sum_i w_i k_i (X_i - x) = K (w X) - (K w) x
        grad = (se @ terms.WX - se_weights[:, None] * Xs) * (inv_ls * inv_ls)
        if terms.linear is not None:
            grad = grad + terms.linear[None, :]
        if terms.trend is not None:  # the chain rule through phi
            grad = grad + np.einsum("j,mjk->mk", terms.trend, self.trend.gradients(Xs))
        if self.input_map is not None:  # d/dx of k(M x): the chain rule through the map
            grad = grad @ np.asarray(self.input_map, dtype=float)
        if width > grad.shape[1]:  # zero columns after the kernel's (np.hstack's values, one array fewer)
            out = np.zeros((grad.shape[0], width))
            out[:, :grad.shape[1]] = grad
            grad = out
        return grad

    # ---- the feature form (the posterior's low-rank variance of f) -----------------
    # The SE part factors as sf2 a(z) a(z') exp(z . z') with z = x / l and a(z) = exp(-|z|^2 / 2),
    # so with psi = [a(z), 1 (bias), x (linear), phi(x) (trend)] and weights
    # w = [sf2, b, v, v_t], every kernel of the family is
    #     k(x, x') = psi(x)^T diag(w) psi(x') + e(x, x'),
    #     e(x, x') = sf2 a(z) a(z') (exp(z . z') - 1),       e(x, x) = sf2 (1 - exp(-|z|^2)),
    # and e is itself a PSD kernel (exp(z . z') - 1 = sum_k>=1 (z . z')^k / k!, a sum of PSD
    # kernels, times a(z) a(z')). When the lengthscales are long and sf2 is small (f's SE part
    # switched off: signal variance at its floor, lengthscales at their upper bound), e is
    # below 1e-8 of the output variance at the data: :mod:`microctl.gp.posterior` uses it.
    @property
    def feature_weights(self) -> np.ndarray:
        """w of the feature form (comment above), shape (p,)."""
        w = [self.signal_var] + ([self.bias_var] if self.log_bias_var is not None else [])
        v = self.linear_vars
        if v is not None:
            w += list(v)
        if self.trend is not None:
            w += [self.trend.var] * self.trend.t
        return np.array(w, dtype=float)

    def _z2(self, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        Z = self._cols(X) * np.exp(-np.asarray(self.log_lengthscales, dtype=float))
        return Z, np.einsum("ij,ij->i", Z, Z)

    def features(self, X: np.ndarray) -> np.ndarray:
        """psi of the feature form at the rows of X, shape (m, p) (p = ``feature_weights.size``)."""
        Z, z2 = self._z2(X)
        return self._psi_of(np.exp(-0.5 * z2), self._cols(X), None if self.trend is None else self.trend.values(X))

    def _psi_of(self, az: np.ndarray, Xc: np.ndarray, trend: np.ndarray | None) -> np.ndarray:
        """psi's columns [exp(-|z|^2 / 2), 1, x, phi(x)] (those the kernel has) written into one
        array (m, p), from az (m,), the kernel's inputs Xc (m, d) and the trend's features (m, t) or None."""
        blocks = [az[:, None]] + ([1.0] if self.log_bias_var is not None else []) + (
            [Xc] if self.log_linear_vars is not None else []) + ([trend] if trend is not None else [])
        widths = [1 if np.ndim(b) < 2 else b.shape[1] for b in blocks]
        psi = np.empty((az.shape[0], sum(widths)))
        col = 0
        for b, w in zip(blocks, widths):
            psi[:, col:col + w] = b
            col += w
        return psi

    def se_remainder(self, Xa: np.ndarray, Xb: np.ndarray,
                     side_b: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
        """e(Xa, Xb) of the feature form, shape (m, n), from ``expm1`` (no cancellation).

        ``side_b``: :meth:`se_remainder_side` of Xb when the caller holds it (fixed training
        inputs: computed once); Xb is then not read.
        """
        Za, za2 = self._z2(Xa)
        Zb, ab = self.se_remainder_side(Xb) if side_b is None else side_b
        return self.signal_var * np.exp(-0.5 * za2)[:, None] * ab[None, :] * np.expm1(Za @ Zb.T)

    def feature_form(self, X: np.ndarray, side_b: tuple[np.ndarray, np.ndarray]
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`features` (m, p), :meth:`se_remainder` against the ``side_b`` of fixed inputs
        (m, n) and :meth:`diag` (m,) at the rows of X, the same numbers as the three calls, with
        what they share (the scaled inputs, ``exp(-|z|^2 / 2)``, the trend's features) computed
        once: f's variance in the feature form reads all three at every evaluation."""
        if self.input_map is not None:  # diag reads the trend of the mapped inputs: the three calls
            return self.features(X), self.se_remainder(X, X, side_b=side_b), self.diag(X)
        Z, z2 = self._z2(X)
        Xc = self._cols(X)
        az = np.exp(-0.5 * z2)
        trend = None if self.trend is None else self.trend.values(X)  # X's first k columns, as Xc's
        Zb, ab = side_b
        # sf2 a(z) a(z') (exp(z . z') - 1) with the (m, n) temporaries reused in place (the same
        # products in the same order as sf2 * az[:, None] * ab[None, :] * np.expm1(Z @ Zb.T))
        G = Z @ Zb.T
        np.expm1(G, out=G)
        E = self.signal_var * az[:, None] * ab[None, :]
        E *= G
        return self._psi_of(az, Xc, trend), E, self._diag_of(Xc, trend)

    def se_remainder_side(self, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """What :meth:`se_remainder` reads of one side X (n, d): Z = X / l (n, d) and exp(-|z|^2 / 2) (n,)."""
        Z, z2 = self._z2(X)
        return Z, np.exp(-0.5 * z2)

    def se_remainder_diag(self, X: np.ndarray) -> np.ndarray:
        """e(x, x) = sf2 (1 - exp(-|z|^2)) at the rows of X, shape (m,)."""
        return -self.signal_var * np.expm1(-self._z2(X)[1])

    def features_casadi(self, xs: ca.MX) -> ca.MX:
        """psi of the feature form at a symbolic input xs (d', 1), shape (p, 1)."""
        z = self._cols_ca(xs) * ca.DM(np.exp(-np.asarray(self.log_lengthscales, dtype=float)))
        parts = [ca.exp(-0.5 * ca.sumsqr(z))]
        if self.log_bias_var is not None:
            parts.append(ca.DM(1.0))
        if self.log_linear_vars is not None:
            parts.append(self._cols_ca(xs))
        if self.trend is not None:
            parts.append(self.trend.casadi(xs))
        return ca.vertcat(*parts)

    def se_remainder_casadi_column(self, xs: ca.MX, X: np.ndarray) -> ca.MX:
        """e(x*, X) of the feature form as an (n, 1) column for a symbolic input xs (d', 1)."""
        Z, z2 = self._z2(X)
        z = self._cols_ca(xs) * ca.DM(np.exp(-np.asarray(self.log_lengthscales, dtype=float)))
        scale = ca.DM(self.signal_var * np.exp(-0.5 * z2))
        return ca.exp(-0.5 * ca.sumsqr(z)) * (scale * ca.expm1(ca.mtimes(ca.DM(Z), z)))

    # ---- CasADi --------------------------------------------------------------------
    def casadi_column(self, xs: ca.MX, X: np.ndarray) -> ca.MX:
        """k(x*, X) as an (n, 1) MX column for a symbolic input ``xs`` of shape (d, 1)."""
        X = self._cols(X)
        xs = self._cols_ca(xs)
        inv_ls = np.exp(-np.asarray(self.log_lengthscales, dtype=float))
        Z = X * inv_ls
        z = xs * ca.DM(inv_ls)
        d2 = ca.DM(np.einsum("ij,ij->i", Z, Z)) + ca.sumsqr(z) - 2.0 * ca.mtimes(ca.DM(Z), z)
        k = self.signal_var * ca.exp(-0.5 * d2)
        if self.log_bias_var is not None:
            k = k + self.bias_var
        v = self.linear_vars
        if v is not None:
            k = k + ca.mtimes(ca.DM(X * v), xs)
        if self.trend is not None:
            k = k + ca.mtimes(ca.DM(self.trend.var * self.trend.values(X)), self.trend.casadi(xs))
        return k

    def casadi_diag(self, xs: ca.MX) -> ca.MX:
        """k(x*, x*) for a symbolic input ``xs`` (d, 1)."""
        out = ca.DM(self.signal_var + self.bias_var)
        v = self.linear_vars
        xs = self._cols_ca(xs)
        if v is not None:
            out = out + ca.dot(ca.DM(v), xs * xs)
        if self.trend is not None:
            out = out + self.trend.var * ca.sumsqr(self.trend.casadi(xs))
        return out


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
    :class:`Kernel`, the one implementation.

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

