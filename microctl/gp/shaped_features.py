"""Variance features of any smooth shape: ``phi_j(x) = shape_j(a_j . x + b_j)`` (a dictionary).

The physical noise model (:mod:`microctl.gp.noise_prior`) writes the noise variance as a floor
plus a sum of non-negative contributions, one per physical source,

    V(x) = c_0 + sum_j c_j phi_j(x),     c_j >= 0,                                    (1)

each source independent of the others, so their variances add. There the contributions are
squares of linear maps (stick-slip whose std is proportional to an actuator's step). A piezo
stage has other sources whose variance is some other function of one physical quantity that
is itself linear in the inputs x = [s; u] (eq. 3): an actuator's step dq_i, where it ends
q_i = K_i u (eq. 12), a ball's contact force (linear in u while every ball is loaded). This
module represents each candidate as that linear quantity ``z_j = a_j . x + b_j`` and a shape:

``sq``      z^2                                   (std proportional to |z|: stick-slip)
``abs``     sqrt(z^2 + e^2) - e                   (variance proportional to |z|: creep)
``sat``     z^2 / (z^2 + s^2)                     (saturating: stiction, settling)
``up``      z^2 (1 + tanh(z / e)) / 2             (only when z > 0: one direction)
``down``    z^2 (1 - tanh(z / e)) / 2             (only when z < 0)
``bump``    exp(-(z - mu)^2 / (2 h^2))            (a rough patch of a stroke)
``exp``     exp(z)                                (grows as z rises: a ball unloading)
``step``    1 / (1 + exp(-(|z|_e - d) / w))       (a breakaway: repeatable below a step of d,
                                                   a fixed-size slip beyond; |z|_e = sqrt(z^2 + w^2))
``rev``     z^2/(z^2 + s^2) (1 - tanh(z c / e))/2  (a reversal: scatter, saturating in the step,
                                                   only where the step's sign is opposite to c,
                                                   the actuator's last direction of motion)

The ``rev`` shape reads a second quantity besides z, its *gate* ``c = g_j . x`` (a row of
:attr:`ShapedFeatures.gate`; zero for the other shapes): a context column of x that only g's
prior mean reads (the kernels ignore it, :mod:`microctl.gp.kernels`), here +1 or -1.

Every shape is smooth (CasADi differentiates it exactly) and non-negative. Each feature is
divided by a fixed ``scale`` (its mean over the training inputs) so the coefficients c_j are
comparable: ``phi_j = shape_j(z_j) / scale_j``.

Both forms are here side by side: NumPy (:meth:`ShapedFeatures.values`) and CasADi
(:meth:`ShapedFeatures.casadi`), on inputs in their original units.
"""

from __future__ import annotations

from dataclasses import dataclass

import casadi as ca
import numpy as np

from microctl.errors import ConfigError

__all__ = ["SHAPES", "ShapedFeatures", "ShapeTransform"]

#: Shape name -> number of parameters it reads from its row of ``params``.
SHAPES = {"sq": 0, "abs": 1, "sat": 1, "up": 1, "down": 1, "bump": 2, "exp": 0, "step": 2, "rev": 2}
#: The shapes that read a gate (see the module docstring).
GATED = ("rev",)


def _shape_np(kind: str, z: np.ndarray, p: np.ndarray, c: np.ndarray | None = None) -> np.ndarray:
    if kind == "rev":
        return z * z / (z * z + p[0] ** 2) * 0.5 * (1.0 - np.tanh(z * c / p[1]))
    if kind == "sq":
        return z * z
    if kind == "abs":
        return np.sqrt(z * z + p[0] ** 2) - p[0]
    if kind == "sat":
        return z * z / (z * z + p[0] ** 2)
    if kind == "up":
        return z * z * 0.5 * (1.0 + np.tanh(z / p[0]))
    if kind == "down":
        return z * z * 0.5 * (1.0 - np.tanh(z / p[0]))
    if kind == "bump":
        return np.exp(-((z - p[0]) ** 2) / (2.0 * p[1] ** 2))
    if kind == "exp":
        return np.exp(np.minimum(z, 50.0))
    if kind == "step":
        return 1.0 / (1.0 + np.exp(-(np.sqrt(z * z + p[1] ** 2) - p[0]) / p[1]))
    raise ConfigError(f"noise feature shape '{kind}' is not one of {sorted(SHAPES)}")


def _num(v):
    """A shape parameter as CasADi reads it: a float (one feature), or a DM column (a group of them)."""
    return float(v) if np.ndim(v) == 0 else ca.DM(np.asarray(v, dtype=float).reshape(-1, 1))


def _shape_ca(kind: str, z: ca.MX, p: np.ndarray, c: ca.MX | None = None) -> ca.MX:
    """``_shape_np`` for CasADi: z a scalar with ``p`` its two parameters, or a column of k values
    with ``p`` a (2, k) array (elementwise, one node per operation for the whole group)."""
    if kind == "rev":
        return z * z / (z * z + _num(p[0]) ** 2) * 0.5 * (1.0 - ca.tanh(z * c / _num(p[1])))
    if kind == "sq":
        return z * z
    if kind == "abs":
        return ca.sqrt(z * z + _num(p[0]) ** 2) - _num(p[0])
    if kind == "sat":
        return z * z / (z * z + _num(p[0]) ** 2)
    if kind == "up":
        return z * z * 0.5 * (1.0 + ca.tanh(z / _num(p[0])))
    if kind == "down":
        return z * z * 0.5 * (1.0 - ca.tanh(z / _num(p[0])))
    if kind == "bump":
        return ca.exp(-((z - _num(p[0])) ** 2) / (2.0 * _num(p[1]) ** 2))
    if kind == "exp":
        return ca.exp(ca.fmin(z, 50.0))
    if kind == "step":
        return 1.0 / (1.0 + ca.exp(-(ca.sqrt(z * z + _num(p[1]) ** 2) - _num(p[0])) / _num(p[1])))
    raise ConfigError(f"noise feature shape '{kind}' is not one of {sorted(SHAPES)}")


@dataclass(frozen=True, eq=False)
class ShapedFeatures:
    """p variance features ``phi_j(x) = shape_j(a_j . x + b_j) / scale_j`` (module docstring).

    Attributes
    ----------
    matrix : ndarray, shape (p, d)
        Row j is a_j (x in original units).
    offset : ndarray, shape (p,)
        b_j.
    shapes : tuple of str
        One of :data:`SHAPES` per feature.
    params : ndarray, shape (p, 2)
        Shape parameters (unused entries 0).
    scale : ndarray, shape (p,)
        Positive divisor of each feature (its mean over the training inputs).
    names : tuple of str
        One name per feature (``"dq4:sq"``, ``"q2:bump@12"``, ...).
    gate : ndarray, shape (p, d), or None
        Row j is g_j, the gate ``c = g_j . x`` of a ``rev`` feature (zero rows for the other
        shapes); None: no feature has a gate.
    """

    matrix: np.ndarray
    offset: np.ndarray
    shapes: tuple[str, ...]
    params: np.ndarray
    scale: np.ndarray
    names: tuple[str, ...]
    gate: np.ndarray | None = None

    def __post_init__(self) -> None:
        A = np.asarray(self.matrix, dtype=float)
        p = A.shape[0] if A.ndim == 2 else -1
        if (p < 0 or np.shape(self.offset) != (p,) or len(self.shapes) != p or np.shape(self.params) != (p, 2)
                or np.shape(self.scale) != (p,) or len(self.names) != p):
            raise ConfigError(f"shaped noise features: matrix {A.shape}, offset {np.shape(self.offset)}, "
                              f"{len(self.shapes)} shapes, params {np.shape(self.params)}, scale "
                              f"{np.shape(self.scale)} and {len(self.names)} names do not match")
        bad = [s for s in self.shapes if s not in SHAPES]
        if bad:
            raise ConfigError(f"shaped noise features: unknown shape(s) {bad}; valid: {sorted(SHAPES)}")
        for arr, what in ((A, "matrix"), (self.offset, "offset"), (self.params, "params"), (self.scale, "scale")):
            if not np.all(np.isfinite(np.asarray(arr, dtype=float))):
                raise ConfigError(f"shaped noise features: non-finite {what}")
        if np.any(np.asarray(self.scale) <= 0):
            raise ConfigError("shaped noise features: every scale must be positive")
        if self.gate is not None and np.shape(self.gate) != A.shape:
            raise ConfigError(f"shaped noise features: gate {np.shape(self.gate)} does not match matrix {A.shape}")
        if self.gate is None and any(k in GATED for k in self.shapes):
            raise ConfigError(f"shaped noise features: shape(s) {list(GATED)} need a gate")
        # the arrays every evaluation reads, converted once (evaluations run per controller step)
        for name, value in (
                ("_matrix_t", A.T), ("_offset", np.asarray(self.offset)),
                ("_gate_t", None if self.gate is None else np.asarray(self.gate, dtype=float).T),
                ("_params", np.asarray(self.params, dtype=float).reshape(len(self.shapes), 2)),
                ("_scale", np.asarray(self.scale, dtype=float)),
                # the features of each shape, shapes in sorted order (the same in every process)
                ("_groups", [(kind, [j for j, k in enumerate(self.shapes) if k == kind])
                             for kind in sorted(set(self.shapes))])):
            object.__setattr__(self, name, value)
        # what values() reads of each group, indexed once: the columns as an index array and the
        # group's parameters (2, k); a single group of every feature in order reads Z whole
        plan = tuple((kind, np.array(idx), self._params[idx].T) for kind, idx in self._groups)
        whole = len(plan) == 1 and self._groups[0][1] == list(range(p))
        object.__setattr__(self, "_plan", plan)
        object.__setattr__(self, "_whole", (plan[0][0], plan[0][2]) if whole else None)
        # the columns ordered by shape group (each group a slice of them): one gather and one
        # scatter per evaluation instead of a gather and a scatter per group
        order = np.array([j for _, idx in self._groups for j in idx], dtype=int)
        ends = np.cumsum([len(idx) for _, idx in self._groups]).tolist()
        object.__setattr__(self, "_order", order)
        object.__setattr__(self, "_sliced", tuple((kind, slice(end - len(idx), end), params)
                                                  for (kind, idx, params), end in zip(plan, ends)))

    def gates(self, X: np.ndarray) -> np.ndarray | None:
        """c = X g^T at the rows of X, shape (m, p); None without gates."""
        return None if self._gate_t is None else np.asarray(X, dtype=float) @ self._gate_t

    @property
    def p(self) -> int:
        """Number of features."""
        return int(np.asarray(self.matrix).shape[0])

    def linear(self, X: np.ndarray) -> np.ndarray:
        """z = X a^T + b, shape (m, p)."""
        return np.asarray(X, dtype=float) @ self._matrix_t + self._offset

    def values(self, X: np.ndarray) -> np.ndarray:
        """phi(x) at the rows of X (original units), shape (m, p)."""
        Z = self.linear(X)
        C = self.gates(X)
        if self._whole is not None:  # Z itself: the array Z[:, [0, ..., p-1]] copies (C-ordered alike)
            kind, params = self._whole
            return _shape_np(kind, Z, params, C) / self._scale
        # one call per shape, its columns at once (params broadcast), on the columns in group order
        # (each shape's block a slice; the same elementwise operations on the same values)
        Zg = Z[:, self._order]
        Cg = None if C is None else C[:, self._order]
        grouped = np.empty_like(Zg)
        for kind, cols, params in self._sliced:
            grouped[:, cols] = _shape_np(kind, Zg[:, cols], params, None if Cg is None else Cg[:, cols])
        # scattered back into a C-ordered array like Z (a gather grouped[:, restore] would be
        # F-ordered, and a product with it, e.g. the trend's in the kernel, sums in another order)
        out = np.empty_like(Z)
        out[:, self._order] = grouped
        return out / self._scale

    def _linear_ca(self, x: ca.MX) -> tuple[ca.MX, ca.MX | None]:
        """z = A x + b (p, 1) and the gates c = G x (p, 1; None without gates) for a symbolic x."""
        z = ca.mtimes(ca.DM(np.asarray(self.matrix, dtype=float)), x) + ca.DM(np.asarray(self.offset, dtype=float))
        c = None if self.gate is None else ca.mtimes(ca.DM(np.asarray(self.gate, dtype=float)), x)
        return z, c

    def casadi(self, x: ca.MX) -> ca.MX:
        """phi(x) for a symbolic input x (d, 1) in original units, shape (p, 1)."""
        z, c = self._linear_ca(x)
        return ca.vertcat(*[_shape_ca(kind, z[j], np.asarray(self.params[j]), None if c is None else c[j])
                            / float(self.scale[j]) for j, kind in enumerate(self.shapes)])

    def casadi_dot(self, x: ca.MX, weights: np.ndarray) -> ca.MX:
        """``sum_j weights_j phi_j(x)`` for a symbolic x (d, 1), shape (1, 1): the features of one
        shape evaluated together (a few vector operations instead of a few per feature), the
        form a weighted sum of many features in a controller's graph should take."""
        w = np.asarray(weights, dtype=float).reshape(-1)
        z, c = self._linear_ca(x)
        out = ca.MX(0.0)
        for kind, idx in self._groups:
            val = _shape_ca(kind, z[idx], self._params[idx].T, None if c is None else c[idx])
            out = out + ca.dot(ca.DM(w[idx] / self._scale[idx]), val)
        return out

    def subset(self, idx) -> "ShapedFeatures":
        """The features ``idx`` (a sequence of indices), in that order."""
        idx = list(idx)
        d = np.asarray(self.matrix).shape[1]
        gate = None if self.gate is None else np.asarray(self.gate)[idx].reshape(len(idx), d)
        if gate is not None and not any(self.shapes[i] in GATED for i in idx):
            gate = None
        return ShapedFeatures(np.asarray(self.matrix)[idx].reshape(len(idx), d), np.asarray(self.offset)[idx],
                              tuple(self.shapes[i] for i in idx), np.asarray(self.params)[idx].reshape(len(idx), 2),
                              np.asarray(self.scale)[idx], tuple(self.names[i] for i in idx), gate)

    def rescaled(self, X: np.ndarray) -> "ShapedFeatures":
        """The same features with ``scale`` set to each feature's mean over the rows of X
        (floored at 1e-12 of its largest value, and at 1e-300)."""
        raw = ShapedFeatures(self.matrix, self.offset, self.shapes, self.params, np.ones(self.p), self.names, self.gate)
        V = raw.values(X)
        mean = V.mean(axis=0)
        floor = np.maximum(1e-12 * V.max(axis=0, initial=0.0), 1e-300)
        return ShapedFeatures(self.matrix, self.offset, self.shapes, self.params, np.maximum(mean, floor), self.names,
                              self.gate)

    def to_arrays(self) -> dict[str, np.ndarray]:
        """The fields as plain arrays (for a model file; :meth:`from_arrays` reads them back)."""
        return {"matrix": np.asarray(self.matrix, dtype=float), "offset": np.asarray(self.offset, dtype=float),
                "shapes": np.asarray(self.shapes, dtype=str), "params": np.asarray(self.params, dtype=float),
                "scale": np.asarray(self.scale, dtype=float), "names": np.asarray(self.names, dtype=str),
                **({} if self.gate is None else {"gate": np.asarray(self.gate, dtype=float)})}

    @classmethod
    def from_arrays(cls, a: dict) -> "ShapedFeatures":
        p = int(np.asarray(a["matrix"]).shape[0])
        return cls(np.asarray(a["matrix"], dtype=float).reshape(p, -1), np.asarray(a["offset"], dtype=float),
                   tuple(str(s) for s in a["shapes"]), np.asarray(a["params"], dtype=float).reshape(p, 2),
                   np.asarray(a["scale"], dtype=float), tuple(str(s) for s in a["names"]),
                   None if "gate" not in a else np.asarray(a["gate"], dtype=float).reshape(p, -1))


class ShapeTransform:
    """``phi_j = shape_j(y_scale * lin_j)`` column by column: the transform of g's prior mean
    (:class:`~microctl.gp.noise_prior.LogVarianceMean`) for shaped features, whose linear maps the
    trainer standardises to ``lin = (a . x + b) / y_scale`` (so ``y_scale * lin`` is the quantity in
    its own units, µm for a step, where the shapes' parameters live).

    Parameters
    ----------
    shapes : sequence of str
        One of :data:`SHAPES` per feature.
    params : array_like, shape (p, 2)
    y_scale : float
    """

    def __init__(self, shapes, params, y_scale: float):
        self.shapes = tuple(str(s) for s in shapes)
        self.params = np.asarray(params, dtype=float).reshape(len(self.shapes), 2)
        self.y_scale = float(y_scale)
        bad = [s for s in self.shapes if s not in SHAPES]
        if bad:
            raise ConfigError(f"noise feature shape(s) {bad} unknown; valid: {sorted(SHAPES)}")

    def __call__(self, lin, gate=None):
        """The features at the standardised linear quantities ``lin`` (features on the last axis,
        or a CasADi column) and, for ``rev`` features, their gates ``gate`` (same shape; own units)."""
        if isinstance(lin, np.ndarray):
            Z = lin * self.y_scale
            out = np.empty_like(Z)
            for j, kind in enumerate(self.shapes):  # the features are the last axis (any leading shape)
                out[..., j] = _shape_np(kind, Z[..., j], self.params[j], None if gate is None else gate[..., j])
            return out
        return ca.vertcat(*[_shape_ca(kind, lin[j] * self.y_scale, self.params[j], None if gate is None else gate[j])
                            for j, kind in enumerate(self.shapes)])
