"""A parametric prior mean for the VHGPR's log noise variance g: the physics of repeatability.

The paper's noise model (eq. 1, 3) is ``r_e = exp(g)`` with ``g ~ GP(mu0, K_g)`` on
``x = [s; u]``. A piezo stage's scatter has a known shape (``shared/spec/diagnosis.md``,
noise causes): a homoscedastic floor (gauge noise, driver accuracy) plus, per actuator,
stick-slip whose standard deviation grows with how far the actuator moves, ``std_i ∝
|dq_i|`` with ``dq_i = K_i u - q_i,prev`` (eq. 12), reaching the tool through its contact
sensitivity. That is a ridge oblique to every input of x, which an axis-aligned kernel on
x learns only from data lying along it. Here it is the *prior mean* of g instead:

    m(x) = log( c_0 + sum_j c_j (a_j . x + b_j)^2 ),     c_0, c_j > 0              (1)

with the features ``phi_j(x) = (a_j . x + b_j)^2`` given (for the stage:
``a_j . x + b_j = dq_j``, :func:`microctl.models.training.actuator_step_features`), and
``log c`` fitted with the other hyperparameters by maximising the MV bound
(:mod:`microctl.gp.vhgpr`). The variance in (1) is a sum of squares of linear functions of x,
so m is smooth everywhere (no ``|.|``), and CasADi differentiates it exactly. The GP on g
then models what (1) leaves: ``g ~ GP(m(x), K_g)``. With no features, (1) is the constant
``log c_0 = mu0`` of the paper.

Parameter uncertainty enters the posterior variance of g: with ``C`` the Laplace
covariance of ``c = (c_0, c_1, ...)`` (Fisher information of the fitted Gaussian
likelihood and a weak prior; :mod:`microctl.gp.vhgpr`), the prior variance
``V(x) = sum_j c_j phi_j(x)`` has variance ``phi(x) C phi(x)^T`` (phi_0 = 1), and the
log-normal with the same mean and variance has log-variance

    var m(x) = log(1 + phi(x) C phi(x)^T / V(x)^2)                                (2)

So a pose whose scatter would come from an actuator whose friction the data determined
poorly (or never saw move) gets an uncertain noise prediction; a friction consistent with
zero keeps an uncertainty of its own size, not one tied to its estimate, and (2) grows
only logarithmically where V is small.

Everything here is in the trainer's standardised units: inputs ``xs = (x - x_mean) /
x_scale``, outputs ``ys = (y - y_mean) / y_scale`` (so ``c`` are variances in units of
``y_scale^2``); :meth:`NoiseFeatures.standardised` converts.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Callable

import casadi as ca
import numpy as np

from microctl.errors import ConfigError

__all__ = ["NoiseFeatures", "LogVarianceMean", "square"]


def square(z: Any) -> Any:
    """``phi = z * z`` of (1), elementwise, for a NumPy array or a CasADi expression."""
    return z * z


@dataclass(frozen=True, eq=False)
class NoiseFeatures:
    """The linear maps whose squares are the features of (1), in the inputs' own units.

    Attributes
    ----------
    matrix : ndarray, shape (p, d)
        Row j is a_j: ``a_j . x + b_j`` is feature j's linear function (µm for actuator steps).
    offset : ndarray, shape (p,)
        b_j.
    names : tuple of str
        One name per feature (``"dq1"``, ...).
    shapes : tuple of str
        Per feature, the shape a noise model with shaped features (``dictionary``,
        :mod:`microctl.gp.shaped_features`) applies to ``a_j . x + b_j``; empty: squares (eq. 1).
    params : tuple of (float, float)
        The shapes' parameters, in the linear quantity's own units (empty with ``shapes``).
    gate : ndarray, shape (p, d), or None
        Per feature, the gate ``c_j = g_j . x`` a gated shape reads beside ``a_j . x + b_j``
        (:mod:`microctl.gp.shaped_features`, ``rev``); None: no gated feature.
    context : int
        How many trailing columns of x only the prior mean reads (a move's context, such as
        each actuator's last direction of motion): the kernels read the others.
    """

    matrix: np.ndarray
    offset: np.ndarray
    names: tuple[str, ...]
    shapes: tuple[str, ...] = ()
    params: tuple[tuple[float, float], ...] = ()
    gate: np.ndarray | None = None
    context: int = 0

    def __post_init__(self) -> None:
        A = np.asarray(self.matrix, dtype=float)
        b = np.asarray(self.offset, dtype=float)
        if A.ndim != 2 or b.shape != (A.shape[0],) or len(self.names) != A.shape[0]:
            raise ConfigError(f"noise features: matrix {A.shape}, offset {b.shape} and {len(self.names)} names "
                              "do not match (expected (p, d), (p,), p)")
        if not (np.all(np.isfinite(A)) and np.all(np.isfinite(b))):
            raise ConfigError("noise features: non-finite coefficients")
        if self.shapes and (len(self.shapes) != A.shape[0] or len(self.params) != A.shape[0]):
            raise ConfigError(f"noise features: {len(self.shapes)} shapes and {len(self.params)} parameter pairs "
                              f"for {A.shape[0]} features")
        if self.gate is not None and np.shape(self.gate) != A.shape:
            raise ConfigError(f"noise features: gate {np.shape(self.gate)} does not match matrix {A.shape}")
        if isinstance(self.context, bool) or int(self.context) != self.context or not 0 <= self.context < A.shape[1]:
            raise ConfigError(f"noise features: context must be an integer in [0, {A.shape[1] - 1}], got "
                              f"{self.context!r}")

    @property
    def p(self) -> int:
        """Number of features."""
        return int(np.asarray(self.matrix).shape[0])

    def values(self, X: np.ndarray) -> np.ndarray:
        """``a_j . x + b_j`` at the rows of X (original units), shape (m, p)."""
        return np.asarray(X, dtype=float) @ np.asarray(self.matrix, dtype=float).T + np.asarray(self.offset)

    def standardised(self, x_mean: np.ndarray, x_scale: np.ndarray, y_scale: float) -> tuple[np.ndarray, np.ndarray]:
        """(A_s, b_s) with ``A_s . xs + b_s = (a . x + b) / y_scale`` for ``x = x_mean + x_scale xs``."""
        A = np.asarray(self.matrix, dtype=float)
        As = A * np.asarray(x_scale)[None, :] / y_scale
        bs = (A @ np.asarray(x_mean) + np.asarray(self.offset)) / y_scale
        return As, bs

    def standardised_gate(self, x_mean: np.ndarray, x_scale: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
        """(G_s, h_s) with ``G_s . xs + h_s = g . x`` (the gate in its own units), or None."""
        if self.gate is None:
            return None
        G = np.asarray(self.gate, dtype=float)
        return G * np.asarray(x_scale)[None, :], G @ np.asarray(x_mean)


@dataclass(frozen=True, eq=False)
class LogVarianceMean:
    """The fitted prior mean (1) of g, in standardised units (see the module docstring).

    Attributes
    ----------
    feature_matrix : ndarray, shape (p, d)
        A_s (standardised inputs, per y_scale).
    feature_offset : ndarray, shape (p,)
        b_s.
    log_const : float
        log c_0.
    log_coef : ndarray, shape (p,)
        log c_j.
    coef_cov : ndarray, shape (p + 1, p + 1), or None
        Covariance of (c_0, .., c_p); None: parameter uncertainty not propagated.
    transform : callable
        ``phi_j = transform(a_j . x + b_j)`` elementwise, for NumPy arrays and CasADi
        expressions alike (default :func:`square`, eq. 1; a noise model of
        :mod:`microctl.gp.noise_models` may give another); with gates,
        ``transform(lin, gate)``.
    gate_matrix, gate_offset : ndarray, shapes (p, d) and (p,), or None
        G_s, h_s: the gates ``c_j = G_s . xs + h_s`` of gated features (own units), or None.
    """

    feature_matrix: np.ndarray
    feature_offset: np.ndarray
    log_const: float
    log_coef: np.ndarray
    coef_cov: np.ndarray | None = None
    transform: Callable[..., Any] = field(default=square)
    gate_matrix: np.ndarray | None = None
    gate_offset: np.ndarray | None = None

    @classmethod
    def constant(cls, d: int, mu0: float) -> "LogVarianceMean":
        """The paper's constant prior mean ``mu0`` (no features)."""
        return cls(np.zeros((0, d)), np.zeros(0), float(mu0), np.zeros(0))

    @property
    def p(self) -> int:
        return int(self.feature_matrix.shape[0])

    @property
    def coef(self) -> np.ndarray:
        """(c_0, c_1, ..., c_p), shape (p + 1,)."""
        return np.exp(np.concatenate([[self.log_const], np.asarray(self.log_coef, dtype=float)]))

    # ---- NumPy ---------------------------------------------------------------------
    def design(self, Xs: np.ndarray) -> np.ndarray:
        """``[1, phi_1(x), ..., phi_p(x)]`` at the rows of Xs, shape (m, p + 1)."""
        Xs = np.asarray(Xs, dtype=float)
        lin = Xs @ self.feature_matrix.T + self.feature_offset
        return np.hstack([np.ones((Xs.shape[0], 1)), self.phi(lin, Xs)])

    def phi(self, lin: Any, xs: Any) -> Any:
        """The features at their linear quantities ``lin`` (of the standardised inputs xs, whose
        gates they read when there are any): NumPy rows or a CasADi column."""
        if self.gate_matrix is None:
            return self.transform(lin)
        if isinstance(lin, np.ndarray):
            return self.transform(lin, xs @ self.gate_matrix.T + self.gate_offset)
        return self.transform(lin, ca.mtimes(ca.DM(self.gate_matrix), xs) + ca.DM(self.gate_offset))

    def value(self, Xs: np.ndarray) -> np.ndarray:
        """m(x) of (1), shape (m,)."""
        return np.log(self.design(Xs) @ self.coef)

    def variance(self, Xs: np.ndarray) -> np.ndarray:
        """Variance (2) of m(x) from ``coef_cov``, shape (m,) (zeros when None)."""
        if self.coef_cov is None:
            return np.zeros(np.asarray(Xs).shape[0])
        J = self._jacobian(Xs)
        return np.log1p(np.maximum(np.einsum("ij,jk,ik->i", J, self.coef_cov, J), 0.0))

    def _jacobian(self, Xs: np.ndarray) -> np.ndarray:
        """``phi(x) / V(x)``: dm/dc, shape (m, p + 1)."""
        Phi = self.design(Xs)
        return Phi / (Phi @ self.coef)[:, None]

    def covariance(self, Xa: np.ndarray, Xb: np.ndarray) -> np.ndarray:
        """Covariance of m between the rows of Xa and Xb, shape (m, k): the delta method's
        correlation ``J_a C J_b^T / sqrt(..)`` with the standard deviations of (2), so the
        joint covariance of any set of points is positive semi-definite and its diagonal is
        :meth:`variance`."""
        if self.coef_cov is None:
            return np.zeros((np.asarray(Xa).shape[0], np.asarray(Xb).shape[0]))
        Ja = self._jacobian(Xa)
        va = np.einsum("ij,jk,ik->i", Ja, self.coef_cov, Ja)
        if Xb is Xa:  # the joint covariance of one set of points: its Jacobian and variances once
            Jb, vb = Ja, va
        else:
            Jb = self._jacobian(Xb)
            vb = np.einsum("ij,jk,ik->i", Jb, self.coef_cov, Jb)
        corr = (Ja @ self.coef_cov @ Jb.T) / np.sqrt(np.maximum(np.outer(va, vb), 1e-300))
        return np.sqrt(np.outer(np.log1p(va), np.log1p(vb))) * corr

    # ---- CasADi --------------------------------------------------------------------
    def casadi(self, xs: ca.MX, with_variance: bool = False) -> tuple[ca.MX, ca.MX | None]:
        """m(x) (and its delta-method variance) for a symbolic standardised input (d, 1)."""
        c = self.coef
        if self.p == 0:
            var = None
            if with_variance:
                var = ca.DM(0.0 if self.coef_cov is None else math.log1p(float(self.coef_cov[0, 0]) / c[0] ** 2))
            return ca.DM(float(self.log_const)), var
        lin = ca.mtimes(ca.DM(self.feature_matrix), xs) + ca.DM(self.feature_offset)
        phi = ca.vertcat(ca.DM(1.0), self.phi(lin, xs))
        v = ca.dot(ca.DM(c), phi)
        m = ca.log(v)  # (1)
        if not with_variance:
            return m, None
        if self.coef_cov is None:
            return m, ca.DM(0.0)
        J = phi / v
        return m, ca.log1p(ca.dot(J, ca.mtimes(ca.DM(self.coef_cov), J)))  # (2)
