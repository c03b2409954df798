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

The features are :class:`~microctl.gp.shaped_features.ShapedFeatures` (ungated) on the
standardised inputs the kernel reads (the first k columns), which give their NumPy and CasADi
values; the input gradients the controller's seeding needs (:meth:`FeatureTrend.gradients`) are
here.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import casadi as ca
import numpy as np

from microctl.errors import ConfigError
from microctl.gp.shaped_features import GATED, SHAPES, ShapedFeatures

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
    features : ShapedFeatures
        t ungated features on the standardised inputs the kernel reads (k columns): row j of
        ``features.matrix`` maps them to ``z_j`` in the quantity's own units (µm for a step);
        ``features.scale`` is each feature's mean over the training inputs (features of order 1).
    log_var : float
        log v, the coefficients' prior variance (standardised outputs per unit feature).
    """

    features: ShapedFeatures
    log_var: float

    def __post_init__(self) -> None:
        if not isinstance(self.features, ShapedFeatures) or self.features.p < 1:
            raise ConfigError("feature trend: needs at least one ShapedFeatures feature")
        bad = [s for s in self.features.shapes if s in GATED]
        if bad:
            raise ConfigError(f"feature trend: shape(s) {bad} not allowed (they read a gate); valid: "
                              f"{sorted(k for k in SHAPES if k not in GATED)}")
        if not math.isfinite(self.log_var):
            raise ConfigError("feature trend: log_var must be finite")
        # what every evaluation reads of the features, converted once (evaluations run per Newton step)
        f = self.features
        object.__setattr__(self, "_matrix", np.asarray(f.matrix, dtype=float))
        object.__setattr__(self, "_params", np.asarray(f.params, dtype=float))
        object.__setattr__(self, "_scale", [float(c) for c in f.scale])

    @property
    def t(self) -> int:
        """Number of features."""
        return self.features.p

    @property
    def k(self) -> int:
        """Number of (standardised) input columns the features read."""
        return int(self._matrix.shape[1])

    @property
    def var(self) -> float:
        """v = exp(log_var)."""
        return math.exp(self.log_var)

    def values(self, X: np.ndarray) -> np.ndarray:
        """phi at the rows of the standardised inputs X (columns beyond k ignored), shape (m, t)."""
        return self.features.values(np.asarray(X, dtype=float)[:, :self._matrix.shape[1]])

    def gradients(self, X: np.ndarray) -> np.ndarray:
        """d phi_j / d xs at the rows of X, shape (m, t, k)."""
        f = self.features
        Z = f.linear(np.asarray(X, dtype=float)[:, :self._matrix.shape[1]])
        P = self._params
        D = np.empty_like(Z)
        for j, kind in enumerate(f.shapes):
            D[:, j] = shape_derivative(kind, Z[:, j], P[j]) / self._scale[j]
        return D[:, :, None] * self._matrix[None, :, :]

    def casadi(self, xs: ca.MX) -> ca.MX:
        """phi at a symbolic standardised input xs (>= k rows), shape (t, 1)."""
        return self.features.casadi(xs[:self.k])

    @classmethod
    def from_original_units(cls, features: ShapedFeatures, x_mean: np.ndarray, x_scale: np.ndarray,
                            log_var: float) -> "FeatureTrend":
        """The trend of ungated features of x in original units (their ``scale`` kept) on the
        standardisation ``xs = (x - x_mean) / x_scale`` of the kernel's k = len(x_mean) inputs."""
        A = np.asarray(features.matrix, dtype=float)
        k = len(x_mean)
        if A.shape[1] < k or np.any(A[:, k:] != 0) or features.gate is not None:
            raise ConfigError(f"feature trend: features on {A.shape[1]} inputs, of which only the first {k} may be "
                              "read, and no gate")
        A = A[:, :k]
        std = ShapedFeatures(A * np.asarray(x_scale, dtype=float), np.asarray(features.offset, dtype=float) + A @ x_mean,
                             tuple(features.shapes), np.asarray(features.params, dtype=float).reshape(-1, 2),
                             np.asarray(features.scale, dtype=float), tuple(features.names))
        return cls(std, float(log_var))
