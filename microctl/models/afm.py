"""The analytic forward model (AFM) of a contact-driven flexure platform (paper III-A/B).

Built generally from a :class:`~microctl.stage.geometry.Stage`: any number of actuators (one
ball each), tilted contact normals and actuator directions, any hinge DoF. Following
eq. 5-14 literally:

- J_h (6 × n_p) selects the twist components the flexure allows (eq. 5);
- P_i maps the platform twist to the twist of contact point i (eq. 6), R̄_i rotates it
  into the contact frame {C}_i = [n_i o_i a_i], and H_i keeps its normal component (eq. 8);
- J (6 n_c × n_q) maps actuator velocities to the ball twists (eq. 7);
- q = (H R̄^T J)^-1 H R̄^T P^T J_h p = K p (eq. 10-12), the inverse kinematics;
- t = T_s (P_t^T J_h p + t0) (eq. 13), relative to the zero state: t = w · p;
- f_a(s, u) = [t; q] with u = p (eq. 14).

Static model corrections of the stage (``stage.corrections``, the ``static`` kind of the
cause registry :mod:`microctl.stage.causes`: actuator gain, contact offset, tool offset, sensor
scale and nonlinearity) are applied to the *prediction*: the command is still q = K u from
the CAD geometry, the balls move G q, the platform settles at the least-squares pose of the
(shared elastic) contact heights, and the gauge reads through :class:`~microctl.stage.sensor.Sensor`.
Causes that need the state, time or the contact physics (the ``dynamic`` kind: backlash,
contact loss, drift) belong to the physics model (:mod:`microctl.stage.physics`), not here,
except hysteresis, whose memory (play states) the AFM carries beside the state
(:attr:`AnalyticForwardModel.memory`, :mod:`microctl.models.memory`): the GP's input x = [s; u]
cannot express it.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Callable

import casadi as ca
import numpy as np

from microctl.errors import ConfigError, SolveError
from microctl.models.memory import ActuatorMemory
from microctl.stage.causes import REGISTRY, Effects, stage_parts
from microctl.stage.geometry import Stage
from microctl.stage.kinematics import inverse_kinematics_matrix, tool_vector
from microctl.stage.sensor import Sensor


@dataclass(frozen=True)
class Workspace:
    """The polytope of control signals whose actuator commands are all in range.

    {u : lo ≤ K u ≤ hi}, shape conventions: u has n_p entries.

    Attributes
    ----------
    K : ndarray, shape (n_q, n_p)
    lo, hi : ndarray, shape (n_q,)
    u_lo, u_hi : ndarray, shape (n_p,)
        The bounding box of the polytope (by linear programming).
    """

    K: np.ndarray
    lo: np.ndarray
    hi: np.ndarray
    u_lo: np.ndarray
    u_hi: np.ndarray

    def contains(self, u: np.ndarray, tol: float = 1e-9) -> np.ndarray:
        """Whether each row of ``u`` (shape (m, n_p) or (n_p,)) is in the polytope."""
        q = np.atleast_2d(u) @ self.K.T
        inside = np.all((q >= self.lo - tol) & (q <= self.hi + tol), axis=1)
        return inside if np.ndim(u) == 2 else bool(inside[0])

    def sample(self, n: int, rng: np.random.Generator, max_batches: int = 1000) -> np.ndarray:
        """Uniform samples from the polytope by rejection from its bounding box.

        Returns
        -------
        ndarray, shape (n, n_p)
        """
        size = (max(4 * n, 64), self.u_lo.size)
        return self.first_inside(n, lambda: rng.uniform(self.u_lo, self.u_hi, size=size), max_batches,
                                 "the workspace polytope is too thin to sample by rejection")

    def first_inside(self, n: int, draw: Callable[[], np.ndarray], max_batches: int, failure: str) -> np.ndarray:
        """The first ``n`` rows, in order, of successive ``draw()`` batches that lie in the polytope.

        Parameters
        ----------
        n : int
        draw : callable
            Returns the next batch of candidate control signals, shape (m, n_p).
        max_batches : int
            Batches drawn at most before giving up.
        failure : str
            Message of the :class:`SolveError` raised when fewer than ``n`` rows are found.

        Returns
        -------
        ndarray, shape (n, n_p)
        """
        out: list[np.ndarray] = []
        have = 0
        for _ in range(max_batches):
            cand = draw()
            ok = cand[self.contains(cand)]
            out.append(ok)
            have += len(ok)
            if have >= n:
                return np.vstack(out)[:n]
        raise SolveError(failure)

    def map_unit(self, z: np.ndarray) -> np.ndarray:
        """Map points of the unit cube (shape (m, n_p)) to the bounding box."""
        return self.u_lo + np.asarray(z) * (self.u_hi - self.u_lo)


def _polytope_vertices(K: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray | None:
    """Vertices of {u : lo ≤ K u ≤ hi} by enumeration, shape (m, n_p); None when that is not exact or cheap.

    Exact for K of full column rank (the polytope is then bounded, so its extremes lie at
    vertices); every choice of n_p of the 2 n_q faces is solved at once (C(8, 3) = 56 systems
    of 3 × 3 for Table I's kind of stage). None for a rank-deficient K or too many choices.
    """
    from itertools import combinations
    from math import comb

    n_q, n_p = K.shape
    if n_p > n_q or comb(2 * n_q, n_p) > 5000 or np.linalg.matrix_rank(K) < n_p:
        return None
    A = np.vstack([K, -K])
    b = np.concatenate([hi, -lo])
    combos = np.array(list(combinations(range(2 * n_q), n_p)))
    As, bs = A[combos], b[combos]
    ok = np.abs(np.linalg.det(As)) > 1e-12 * max(1.0, float(np.abs(K).max())) ** n_p
    if not np.any(ok):
        return np.zeros((0, n_p))
    V = np.linalg.solve(As[ok], bs[ok][..., None])[..., 0]
    scale = 1.0 + np.abs(b).max()
    return V[np.all(V @ A.T <= b + 1e-9 * scale, axis=1)]


def _lp_extreme(c: np.ndarray, K: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> float:
    """min c·u s.t. lo ≤ K u ≤ hi.

    Parameters
    ----------
    c : ndarray, shape (n_p,)
    K : ndarray, shape (n_q, n_p)
    lo, hi : ndarray, shape (n_q,)

    With K of full column rank (every stage of Table I's kind) the polytope is bounded and the
    minimum is the smallest c·v over its vertices (:func:`_polytope_vertices`); otherwise a
    linear program (``scipy.optimize.linprog``, imported only then: it costs a large part of
    the command line's start-up).
    """
    if np.any(lo > hi):
        raise ConfigError("the actuator ranges admit no platform pose (a range has lo > hi)")
    V = _polytope_vertices(K, lo, hi)
    if V is not None:
        if V.shape[0] == 0:
            raise ConfigError("the actuator ranges admit no platform pose (the polytope lo <= K u <= hi is empty)")
        return float(np.min(V @ c))
    from scipy.optimize import linprog

    res = linprog(
        c,
        A_ub=np.vstack([K, -K]),
        b_ub=np.concatenate([hi, -lo]),
        bounds=[(None, None)] * K.shape[1],
        method="highs",
    )
    if res.status != 0:
        raise ConfigError(f"the actuator ranges admit no platform pose (linear program: {res.message})")
    return float(res.fun)


class AnalyticForwardModel:
    """The AFM f_a(s, u) = [t; q] of eq. 14, as CasADi Functions and NumPy.

    Parameters
    ----------
    stage : Stage
        Geometry (and optional static corrections).

    Attributes
    ----------
    K : ndarray, shape (n_q, n_p)
        Inverse kinematics q = K u (eq. 12), from the CAD geometry: what the drivers get.
    w : ndarray, shape (n_p,)
        Tool map t = w · u (eq. 13) of the CAD geometry.
    F : ndarray, shape (n_p, n_q)
        Forward map from commands to platform pose under the corrections (identity-like
        ``F K = I`` when there are none).
    w_pred : ndarray, shape (n_p,)
        Tool map of the corrected geometry.
    sensor : Sensor
        The gauge transfer under the static corrections (forward, derivative, inverse);
        ``scale`` and ``quad`` are its coefficients.
    memory : ActuatorMemory
        The hysteresis corrections' play-state model (:mod:`microctl.models.memory`;
        ``memory.active`` is False without hysteresis): the prediction at a command depends on
        the play states before the move, which the callers that know the command history pass
        (:mod:`microctl.control.memory`); ``t_of`` is the prediction without the loop.
    f_a, ik, tool : casadi.Function
        Named Functions: ``f_a(s, u) -> (t, q)``, ``ik(u) -> q``, ``tool(u) -> t``.
    """

    def __init__(self, stage: Stage):
        self.stage = stage
        self.n_p = stage.n_dof
        self.n_q = stage.n_act
        self.n_s = 1 + self.n_q
        self.K = inverse_kinematics_matrix(stage)
        self.w = tool_vector(stage)
        corr = stage.corrections
        # dynamic causes left to the GP (hysteresis is applied through the play states, ``memory``)
        self.dynamic_corrections = tuple(n for n, c in REGISTRY.items()
                                         if c.kind == "dynamic" and n != "hysteresis" and getattr(corr, n))
        # Static corrections: balls move G q (gains), the platform settles at the pose whose
        # contact heights best match them (elastic sharing among equal contacts: least squares),
        # the gauge reads the corrected tool point through the corrected sensor.
        parts = stage_parts(stage, corr, ("static",))
        K_true = inverse_kinematics_matrix(stage, parts)
        self.F = np.linalg.pinv(K_true) @ np.diag(parts.gain)
        self.w_pred = tool_vector(stage, parts) @ self.F @ self.K
        self.sensor: Sensor = parts.sensor
        # the hysteresis loop's memory (play states) on the actual positions: same static map
        loop = stage_parts(stage, Effects(hysteresis=corr.hysteresis), ("dynamic",))
        self.memory = ActuatorMemory.from_parts(loop.hysteresis_half_um, loop.hysteresis_range_um,
                                                tool_vector(stage, parts) @ self.F, self.sensor)
        self.lo = stage.range_lo
        self.hi = stage.range_hi
        self.workspace = Workspace(
            K=self.K,
            lo=self.lo,
            hi=self.hi,
            u_lo=np.array([_lp_extreme(e, self.K, self.lo, self.hi) for e in np.eye(self.n_p)]),
            u_hi=np.array([-_lp_extreme(-e, self.K, self.lo, self.hi) for e in np.eye(self.n_p)]),
        )
        self._build_casadi()

    # ---- names -------------------------------------------------------------------
    @property
    def dof(self) -> tuple[str, ...]:
        """DoF names (entries of u)."""
        return self.stage.dof

    @property
    def actuator_names(self) -> tuple[str, ...]:
        """Actuator names (entries of q)."""
        return self.stage.actuator_names

    @property
    def state_names(self) -> tuple[str, ...]:
        """Entries of the state s = [t; q]."""
        return (self.stage.tool.name, *self.stage.actuator_names)

    @property
    def scale(self) -> float:
        """Gauge scale of the static corrections (``sensor.scale``)."""
        return self.sensor.scale

    @property
    def quad(self) -> float:
        """Gauge quadratic coefficient of the static corrections (``sensor.quad_per_um``), 1/µm."""
        return self.sensor.quad_per_um

    # ---- CasADi ------------------------------------------------------------------
    def _build_casadi(self) -> None:
        u = ca.MX.sym("u", self.n_p)
        s = ca.MX.sym("s", self.n_s)
        q = ca.mtimes(ca.DM(self.K), u)  # eq. 12
        t = self.sensor.forward(ca.dot(ca.DM(self.w_pred), u))  # eq. 13 (+ static corrections)
        self.ik = ca.Function("ik", [u], [q], ["u"], ["q"])
        self.tool = ca.Function("tool", [u], [t], ["u"], ["t"])
        # s is an input for the interface of eq. 14; this AFM is absolute (relative to the
        # zero state), so the prediction does not depend on it.
        self.f_a = ca.Function("f_a", [s, u], [t, q], ["s", "u"], ["t", "q"])

    # ---- NumPy -------------------------------------------------------------------
    def q_of(self, u: np.ndarray) -> np.ndarray:
        """Actuator commands q = K u (eq. 12); u shape (n_p,) or (m, n_p)."""
        return np.asarray(u, dtype=float) @ self.K.T

    def t_of(self, u: np.ndarray, s: np.ndarray | None = None) -> np.ndarray:
        """Predicted tool pose t (eq. 13); u shape (n_p,) or (m, n_p); s ignored (absolute AFM)."""
        return self.sensor.forward(np.asarray(u, dtype=float) @ self.w_pred)

    def predict(self, s: np.ndarray | None, u: np.ndarray) -> np.ndarray:
        """f_a(s, u) = [t; q] (eq. 14); returns shape (n_s,) or (m, n_s)."""
        u = np.asarray(u, dtype=float)
        t = np.asarray(self.t_of(u))
        return np.concatenate([t[..., None], self.q_of(u)], axis=-1)

    # ---- ranges ------------------------------------------------------------------
    def t_range(self, s: np.ndarray | None = None) -> tuple[float, float]:
        """Reachable interval [lo, hi] of t from state ``s`` over the workspace (µm).

        The AFM is absolute, so every pose of the workspace is reachable from every state.
        """
        d_lo = _lp_extreme(self.w_pred, self.K, self.lo, self.hi)
        d_hi = -_lp_extreme(-self.w_pred, self.K, self.lo, self.hi)
        return self.sensor.reading_range(d_lo, d_hi)

    def zero_state(self) -> np.ndarray:
        """The zero state s = [t; q] = 0, shape (n_s,)."""
        return np.zeros(self.n_s)

    def dynamic_corrections_note(self) -> str | None:
        """A one-line note when ``stage.corrections`` holds causes this AFM does not model.

        Backlash, contact loss and drift need the state, the contact physics or time; the
        AFM (and so the EAFM graph and the controller) leaves them to the GP, which learns
        them from the residual. ``None`` when there are none. Hysteresis is not among them: the
        AFM carries its play states (:attr:`memory`, :mod:`microctl.models.memory`).
        """
        if not self.dynamic_corrections:
            return None
        return (f"stage.corrections has {', '.join(self.dynamic_corrections)}, which the AFM graph does not "
                "model; the GP learns it from the residual (microctl.models.extended models it through the physics)")

    def without_corrections(self) -> "AnalyticForwardModel":
        """The CAD AFM of the same stage (corrections dropped)."""
        return AnalyticForwardModel(replace(self.stage, corrections=Effects()))


#: A gauge reading ``t`` or ``t_prev`` is refused when its magnitude exceeds this many times
#: the largest |t| the stage can reach (AFM over the workspace); such a value is a wrong unit,
#: an untared gauge or a corrupt file, and would wreck a fit (y_scale = inf).
T_PLAUSIBLE_FACTOR = 10.0


def plausible_t_bound_um(stage: Stage) -> float:
    """Largest |t| (µm) a log or a state may hold: :data:`T_PLAUSIBLE_FACTOR` × the AFM's reach."""
    lo, hi = AnalyticForwardModel(stage).t_range()
    return T_PLAUSIBLE_FACTOR * max(abs(lo), abs(hi), 1.0)
