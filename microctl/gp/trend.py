"""A feature trend in f's kernel: Bayesian regression on fixed, shaped features of the inputs.

The kernel of f (:mod:`microctl.gp.kernels`) may carry, besides its SE, bias and linear parts,

    k_trend(x, x') = v sum_j phi_j(x) phi_j(x'),      phi_j(x) = shape_j(a_j . xs + b_j) / scale_j

with a fixed prior variance v of the coefficients (standardised units). It is the explicit-basis
form of a GP (Rasmussen & Williams 2006, sect. 2.7): the mean correction is ``sum_j beta_j
phi_j(x)`` plus the GP, the coefficients have the Gaussian prior N(0, v I), and the posterior
variance of f includes their uncertainty.

Why the residual model wants it (:mod:`microctl.models.mean_shift`): where a move scatters and the
stage's response is not linear in the scattered quantity (a ball that lifts off on one side and
pushes on the other, a gauge with a quadratic term), the *mean* reading shifts with the scatter's
variance (second order: ``E[h(q + e)] = h(q) + h''(q) Var(e) / 2``). The noise model's selected
sources are that variance, source by source, so they are the features of the shift. A
stationary kernel over x = [s; u] cannot represent a shift that grows with the step |dq|: the
mean would be learned as if the stage were linear and be biased exactly where the scatter is
largest.

The features are :mod:`microctl.gp.shaped_features` shapes of linear maps of the standardised
inputs the kernel reads (the first k columns). NumPy values and input gradients
(:meth:`FeatureTrend.values`, :meth:`FeatureTrend.gradients`) and CasADi
(:meth:`FeatureTrend.casadi`) are side by side here.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import casadi as ca
import numpy as np

from microctl.errors import ConfigError
from microctl.gp.shaped_features import GATED, SHAPES, _shape_ca, _shape_np

__all__ = ["FeatureTrend", "shape_derivative"]


def shape_derivative(kind: str, z: np.ndarray, p: np.ndarray) -> np.ndarray:
    """d shape(z) / dz of an ungated shape of :mod:`microctl.gp.shaped_features` (same arguments)."""
    if kind == "sq":
        return 2.0 * z
    if kind == "abs":
        return z / np.sqrt(z * z + p[0] ** 2)
    if kind == "sat":
        return 2.0 * z * p[0] ** 2 / (z * z + p[0] ** 2) ** 2
    if kind in ("up", "down"):
        sign = 1.0 if kind == "up" else -1.0
        t = np.tanh(z / p[0])
        return z * (1.0 + sign * t) + sign * 0.5 * z * z * (1.0 - t * t) / p[0]
    if kind == "bump":
        return -(z - p[0]) / p[1] ** 2 * np.exp(-((z - p[0]) ** 2) / (2.0 * p[1] ** 2))
    if kind == "exp":
        return np.where(z < 50.0, np.exp(np.minimum(z, 50.0)), 0.0)
    if kind == "step":
        r = np.sqrt(z * z + p[1] ** 2)
        s = 1.0 / (1.0 + np.exp(-(r - p[0]) / p[1]))
        return s * (1.0 - s) / p[1] * z / r
    raise ConfigError(f"a trend feature's shape must be one of {sorted(k for k in SHAPES if k not in GATED)}, "
                      f"got '{kind}'")


@dataclass(frozen=True, eq=False)
class FeatureTrend:
    """t fixed features of the standardised inputs and the prior variance of their coefficients.

    Attributes
    ----------
    matrix : ndarray, shape (t, k)
        Row j maps the standardised inputs the kernel reads to ``z_j`` (in the quantity's own
        units, µm for a step): ``z_j = matrix_j . xs + offset_j``.
    offset : ndarray, shape (t,)
    shapes : tuple of str
        Ungated shapes of :data:`~microctl.gp.shaped_features.SHAPES`.
    params : ndarray, shape (t, 2)
    scale : ndarray, shape (t,)
        Positive divisor of each feature (its mean over the training inputs: features of order 1).
    names : tuple of str
    log_var : float
        log v, the coefficients' prior variance (standardised outputs per unit feature).
    """

    matrix: np.ndarray
    offset: np.ndarray
    shapes: tuple[str, ...]
    params: np.ndarray
    scale: np.ndarray
    names: tuple[str, ...]
    log_var: float

    def __post_init__(self) -> None:
        A = np.asarray(self.matrix, dtype=float)
        t = A.shape[0] if A.ndim == 2 else -1
        if (t < 1 or np.shape(self.offset) != (t,) or len(self.shapes) != t or np.shape(self.params) != (t, 2)
                or np.shape(self.scale) != (t,) or len(self.names) != t):
            raise ConfigError(f"feature trend: matrix {A.shape}, offset {np.shape(self.offset)}, {len(self.shapes)} "
                              f"shapes, params {np.shape(self.params)}, scale {np.shape(self.scale)} and "
                              f"{len(self.names)} names do not match (at least one feature)")
        bad = [s for s in self.shapes if s not in SHAPES or s in GATED]
        if bad:
            raise ConfigError(f"feature trend: shape(s) {bad} not allowed; valid: "
                              f"{sorted(k for k in SHAPES if k not in GATED)}")
        for arr, what in ((A, "matrix"), (self.offset, "offset"), (self.params, "params"), (self.scale, "scale")):
            if not np.all(np.isfinite(np.asarray(arr, dtype=float))):
                raise ConfigError(f"feature trend: non-finite {what}")
        if np.any(np.asarray(self.scale) <= 0) or not math.isfinite(self.log_var):
            raise ConfigError("feature trend: every scale must be positive and log_var finite")

    def __eq__(self, other: object) -> bool:  # by value (kernel specs compare their trends)
        if not isinstance(other, FeatureTrend):
            return NotImplemented
        return (self.shapes == other.shapes and self.names == other.names and self.log_var == other.log_var
                and all(np.array_equal(np.asarray(a), np.asarray(b)) for a, b in
                        ((self.matrix, other.matrix), (self.offset, other.offset), (self.params, other.params),
                         (self.scale, other.scale))))

    __hash__ = None  # type: ignore[assignment]

    @property
    def t(self) -> int:
        """Number of features."""
        return int(np.asarray(self.matrix).shape[0])

    @property
    def k(self) -> int:
        """Number of (standardised) input columns the features read."""
        return int(np.asarray(self.matrix).shape[1])

    @property
    def var(self) -> float:
        """v = exp(log_var)."""
        return math.exp(self.log_var)

    def _z(self, X: np.ndarray) -> np.ndarray:
        return np.asarray(X, dtype=float)[:, :self.k] @ np.asarray(self.matrix, dtype=float).T + np.asarray(self.offset)

    def values(self, X: np.ndarray) -> np.ndarray:
        """phi at the rows of the standardised inputs X (columns beyond k ignored), shape (m, t)."""
        Z = self._z(X)
        P = np.asarray(self.params, dtype=float)
        out = np.empty_like(Z)
        for j, kind in enumerate(self.shapes):
            out[:, j] = _shape_np(kind, Z[:, j], P[j])
        return out / np.asarray(self.scale, dtype=float)

    def gradients(self, X: np.ndarray) -> np.ndarray:
        """d phi_j / d xs at the rows of X, shape (m, t, k)."""
        Z = self._z(X)
        P = np.asarray(self.params, dtype=float)
        D = np.empty_like(Z)
        for j, kind in enumerate(self.shapes):
            D[:, j] = shape_derivative(kind, Z[:, j], P[j]) / float(self.scale[j])
        return D[:, :, None] * np.asarray(self.matrix, dtype=float)[None, :, :]

    def casadi(self, xs: ca.MX) -> ca.MX:
        """phi at a symbolic standardised input xs (>= k rows), shape (t, 1)."""
        z = ca.mtimes(ca.DM(np.asarray(self.matrix, dtype=float)), xs[:self.k]) + ca.DM(np.asarray(self.offset))
        return ca.vertcat(*[_shape_ca(kind, z[j], np.asarray(self.params[j])) / float(self.scale[j])
                            for j, kind in enumerate(self.shapes)])

    @classmethod
    def from_original_units(cls, features, x_mean: np.ndarray, x_scale: np.ndarray, log_var: float) -> "FeatureTrend":
        """The trend of ungated :class:`~microctl.gp.shaped_features.ShapedFeatures` (maps of x in
        original units, their ``scale``) on the standardisation ``xs = (x - x_mean) / x_scale`` of
        the kernel's k = len(x_mean) inputs."""
        A = np.asarray(features.matrix, dtype=float)
        k = len(x_mean)
        if A.shape[1] < k or np.any(A[:, k:] != 0):
            raise ConfigError(f"feature trend: features on {A.shape[1]} inputs, of which only the first {k} may be read")
        A = A[:, :k]
        return cls(A * np.asarray(x_scale, dtype=float), np.asarray(features.offset, dtype=float) + A @ x_mean,
                   tuple(features.shapes), np.asarray(features.params, dtype=float).reshape(-1, 2),
                   np.asarray(features.scale, dtype=float), tuple(features.names), float(log_var))
