"""Elastic contact physics of the stage: the simulator's truth and the diagnosis' model.

The analytic forward model (AFM, paper eq. 5-14) treats every ball as a rigid, always
closed contact. Here the same geometry is given elasticity, so that every cause of the
vocabulary (``shared/spec/diagnosis.md``) acts as a *physical* change of the stage:

- Platform pose p (n_p: the hinge DoF of eq. 5, µm / mrad), relative to the CAD zero.
- Contact i has a height row a_i = H_i R̄_i^T P_i^T J_h (eq. 6, 8, 9): the normal
  displacement of the platform at contact point i per pose (equal to row i of K of
  eq. 12 times n_i·d_i). Contact offsets move c_i and so a_i.
- Ball i is raised by h_i = (n_i·d_i) · gain_i · q_i,actual − gap_i along the normal
  (eq. 7 with an actuator gain; ``contact_loss`` lowers the ball by gap_i).
- The flexure pulls the platform down with the preload: its free pose is
  p_free = −(preload / k_z) e_z, its stiffness K_h = diag(flexure_stiffness).
- Each ball is a one-sided spring k_c (ball + PZT). The equilibrium minimises the convex
  energy

      E(p) = ½ (p − p_free)^T K_h (p − p_free) + Σ_i ½ k_c max(0, h_i − a_i·p)²,

  solved exactly by a damped semismooth Newton (active-set) iteration, vectorised over a
  batch of moves.
- The gauge reads the tool point along its direction (eq. 13) with the tool offset,
  relative to the noise-free zero state: d = w_true·(p − p_zero), through the stage's
  :class:`~microctl.stage.sensor.Sensor` (reading = scale·d + quad·d² + drift·time).

Every cause changes these numbers through its own :meth:`~microctl.stage.causes.Cause.apply`
(:func:`microctl.stage.causes.stage_parts`); this module knows no cause by name.

State-dependent causes: ``backlash`` makes actuator i end lag_i short of its command in
the direction it last moved. The direction of approach has one rule,
:func:`approach_direction`: a step larger than :data:`STILL_TOL_UM` sets it, an actuator
held still (within the tolerance) keeps its last direction, and the zero state counts as
approached from below ("up"), so its actuator sits at −lag_i. ``hysteresis`` adds the
Prandtl-Ishlinskii offset of :mod:`microctl.stage.hysteresis`, which needs the play states
(the loop's memory) beside the direction; its zero state is approached from below too
(−h_i). ``actuator_friction`` and the
driver accuracy are noise (see :func:`tool_sensitivity` and :func:`reading_variance`).

With the default :class:`~microctl.stage.geometry.Physics` (k_c = 20 N/µm, preload 100 N,
flexure (0.01, 5, 5)) each ball is compressed ≈ 1.25 µm at rest and a healthy stage
matches the rigid AFM within the gauge noise (docs/backends.md, "Physics", prints the
difference). Every function accepts either a
:class:`~microctl.stage.geometry.Stage` plus :class:`~microctl.stage.causes.Effects`, or a prebuilt
:class:`ContactModel` (faster inside a fit loop).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property, lru_cache

import numpy as np

from microctl.errors import SolveError
from microctl.stage import hysteresis
from microctl.stage.causes import Effects, StageParts, stage_parts
from microctl.stage.geometry import Stage
from microctl.stage.kinematics import contact_map, hinge_jacobian, tool_vector
from microctl.stage.sensor import Sensor

#: Largest number of Newton iterations before :func:`solve_equilibrium` gives up.
MAX_NEWTON_ITERATIONS = 60

_ALPHAS = 0.5 ** np.arange(0, 40)

#: An actuator step at most this large (µm) is "held still": the actuator keeps its last
#: direction of approach. Covers the round-off of a command recomputed as K u (≈ 1e-12 µm);
#: far below any physical step (the drivers' accuracy is 0.01 µm).
STILL_TOL_UM = 1e-6

#: Direction of approach of the zero state (every actuator approached from below, "up").
ZERO_STATE_DIRECTION = 1.0


@dataclass(frozen=True, eq=False)
class ContactModel:
    """Everything the contact physics needs, as arrays (built by :func:`contact_model`).

    Attributes
    ----------
    A : ndarray, shape (n_c, n_p)
        Contact height rows a_i (µm of normal displacement per unit pose).
    nd : ndarray, shape (n_c,)
        n_i·d_i: normal ball motion per actuator µm.
    parts : StageParts
        The causes' physical changes (:func:`~microctl.stage.causes.stage_parts`); the per-actuator
        ``gain``, ``gap_um``, ``lag_um``, ``friction_std_per_um`` and the ``sensor`` are read from it
        (properties), so each is held in one place.
    k_h : ndarray, shape (n_p,)
        Flexure stiffness per DoF (diagonal of K_h).
    f_preload : ndarray, shape (n_p,)
        K_h p_free: the generalised preload force (−preload on z).
    k_c : float
        Contact stiffness, N/µm.
    w_true : ndarray, shape (n_p,)
        True tool map (eq. 13 with the tool offset).
    q_zero : ndarray, shape (n_c,)
        Actual actuator positions at the zero state (−lag − h: approached "up").
    p_zero : ndarray, shape (n_p,)
        Noise-free equilibrium pose at the zero state (the gauge's zero); solved on first use,
        or together with a batch of moves by :func:`solve_with_zero`.
    """

    A: np.ndarray
    nd: np.ndarray
    parts: StageParts
    k_h: np.ndarray
    f_preload: np.ndarray
    k_c: float
    w_true: np.ndarray
    q_zero: np.ndarray

    @property
    def gain(self) -> np.ndarray:
        """Actuator gains (1 when healthy), shape (n_c,)."""
        return self.parts.gain

    @property
    def gap_um(self) -> np.ndarray:
        """How far each ball sits low (contact loss), µm, shape (n_c,)."""
        return self.parts.gap_um

    @property
    def lag_um(self) -> np.ndarray:
        """Backlash lag per actuator, µm, shape (n_c,)."""
        return self.parts.lag_um

    @property
    def friction_std_per_um(self) -> np.ndarray:
        """Stick-slip scatter per µm of actuator motion, shape (n_c,)."""
        return self.parts.friction_std_per_um

    @property
    def sensor(self) -> Sensor:
        """Gauge transfer (scale, quadratic coefficient, drift rate)."""
        return self.parts.sensor

    @cached_property
    def play_r(self) -> np.ndarray:
        """Play thresholds of the hysteresis, µm, shape (n_c, N_PLAY) (read-only)."""
        r = hysteresis.thresholds(self.parts.hysteresis_range_um)
        r.setflags(write=False)
        return r

    @cached_property
    def play_w(self) -> np.ndarray:
        """Play weights of the hysteresis (0 where an actuator has none), shape (n_c,) (read-only)."""
        w = hysteresis.weights(self.parts.hysteresis_half_um, self.parts.hysteresis_range_um)
        w.setflags(write=False)
        return w

    @property
    def has_hysteresis(self) -> bool:
        """Whether some actuator has hysteresis (then the state carries play states)."""
        return bool(np.any(self.play_w > 0))

    @cached_property
    def p_zero(self) -> np.ndarray:
        """Noise-free equilibrium pose at the zero state, shape (n_p,) (read-only)."""
        p0, _ = solve_equilibrium(self, ball_heights(self, self.q_zero[None, :]))
        p0 = p0[0]
        p0.setflags(write=False)
        return p0

    @property
    def n_p(self) -> int:
        """Number of pose DoF."""
        return self.A.shape[1]

    @property
    def n_c(self) -> int:
        """Number of contacts (= actuators)."""
        return self.A.shape[0]


def _preload_axis(stage: Stage) -> int:
    return stage.dof.index("z") if "z" in stage.dof else 0


@lru_cache(maxsize=256)
def _cached_model(stage: Stage, effects: Effects) -> ContactModel:
    n_p = stage.n_dof
    parts = stage_parts(stage, effects)  # every cause's physical change (microctl.stage.causes)
    hrj, hrp = contact_map(stage, parts)  # eq. 9 with the moved contact points
    A = hrp @ hinge_jacobian(stage.dof)  # a_i = H_i R̄_i^T P_i^T J_h
    nd = np.diag(hrj).copy()
    ph = stage.physics
    k_h = np.asarray(ph.flexure_stiffness, dtype=float)
    j = _preload_axis(stage)
    p_free = np.zeros(n_p)
    p_free[j] = -ph.preload_n / k_h[j]
    model = ContactModel(
        A=A,
        nd=nd,
        parts=parts,
        k_h=k_h,
        f_preload=k_h * p_free,
        k_c=float(ph.contact_stiffness_n_per_um),
        w_true=tool_vector(stage, parts),  # eq. 13 with the moved tool point
        # backlash and hysteresis at the zero state, approached "up" (play states z = -r: offset -h)
        q_zero=-(parts.lag_um + parts.hysteresis_half_um) * ZERO_STATE_DIRECTION,
    )
    for arr in (model.A, model.nd, model.gain, model.gap_um, model.lag_um, model.friction_std_per_um,
                model.k_h, model.f_preload, model.w_true, model.q_zero):
        arr.setflags(write=False)
    return model


def contact_model(stage: Stage | ContactModel, effects: Effects | None = None) -> ContactModel:
    """Build (or pass through) the contact model of a stage with a set of effects.

    Parameters
    ----------
    stage : Stage or ContactModel
        The geometry and physics; a ContactModel is returned unchanged.
    effects : Effects, optional
        The physical causes (truth); default ``stage.corrections``.

    Returns
    -------
    ContactModel
        Cached per (stage, effects): cheap to call repeatedly.
    """
    if isinstance(stage, ContactModel):
        return stage
    if not isinstance(stage, Stage):
        raise TypeError(f"expected a Stage or ContactModel, got {type(stage).__name__}")
    if effects is None:
        effects = stage.corrections
    return _cached_model(stage, effects)


def ball_heights(model: ContactModel, q_actual: np.ndarray) -> np.ndarray:
    """Normal ball heights h = (n·d) gain q_actual − gap, shape (m, n_c).

    Parameters
    ----------
    q_actual : ndarray, shape (m, n_c) or (n_c,)
        Actual actuator displacements (after backlash and noise), µm.
    """
    q = np.atleast_2d(np.asarray(q_actual, dtype=float))
    return model.nd * model.gain * q - model.gap_um


def _solve_active(model: ContactModel, active: np.ndarray, h: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Minimiser of the quadratic with contact set ``active`` (m, n_c); returns p and H."""
    A = model.A
    S = active.astype(float)
    H = np.einsum("mi,ij,ik->mjk", S, A, A) * model.k_c
    idx = np.arange(model.n_p)
    H[:, idx, idx] += model.k_h
    rhs = model.f_preload + model.k_c * np.einsum("mi,ij->mj", S * h, A)
    return np.linalg.solve(H, rhs[..., None])[..., 0], H


def _energy(model: ContactModel, p: np.ndarray, h: np.ndarray) -> np.ndarray:
    """E(p) up to a constant, for p shape (..., n_p) and h broadcastable (..., n_c)."""
    gap = np.maximum(h - p @ model.A.T, 0.0)
    return 0.5 * np.sum(model.k_h * p * p, axis=-1) - p @ model.f_preload + 0.5 * model.k_c * np.sum(gap * gap, axis=-1)


def solve_equilibrium(model: ContactModel, h: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Equilibrium pose for given ball heights (damped semismooth Newton, batched).

    Parameters
    ----------
    model : ContactModel
    h : ndarray, shape (m, n_c)
        Ball heights (:func:`ball_heights`), µm.

    Returns
    -------
    p : ndarray, shape (m, n_p)
        Pose minimising E(p) (exact up to round-off: the final step solves the
        quadratic of the converged contact set).
    active : ndarray of bool, shape (m, n_c)
        Balls in contact (compression h_i − a_i·p > 0).

    Raises
    ------
    SolveError
        If some moves do not converge within ``MAX_NEWTON_ITERATIONS``.
    """
    h = np.atleast_2d(np.asarray(h, dtype=float))
    m = h.shape[0]
    active = np.ones((m, model.n_c), dtype=bool)
    p, _ = _solve_active(model, active, h)
    tol = 1e-10 * (1.0 + np.max(np.abs(h), axis=1, keepdims=True))
    done = np.zeros(m, dtype=bool)
    exact = np.ones(m, dtype=bool)  # p is the minimiser of the quadratic of ``active``
    for _ in range(MAX_NEWTON_ITERATIONS):
        r = h - p @ model.A.T  # ball compressions
        S = r > 0.0
        # KKT within round-off: balls kept in contact are not in tension and balls left
        # out are not compressed (a ball exactly on the boundary, e.g. on the load
        # diagonal, may be either; this stops the active set cycling over it).
        consistent = np.all(np.where(active, r >= -tol, r <= tol), axis=1)
        done |= exact & consistent
        todo = ~done
        if not todo.any():
            return p, active
        # Newton step of the piecewise quadratic from the contact set at p: its minimiser.
        hp, pp, Sp = h[todo], p[todo], S[todo]
        p_n, _ = _solve_active(model, Sp, hp)
        d = p_n - pp
        e0 = _energy(model, pp, hp)
        etol = 1e-12 * (1.0 + np.abs(e0))
        # the full step first (usually accepted); the halving ladder only where it is not
        alpha = np.ones(len(pp))
        bad = ~(_energy(model, p_n, hp) <= e0 + etol)
        if bad.any():
            trial = pp[bad, None, :] + _ALPHAS[None, 1:, None] * d[bad, None, :]
            e = _energy(model, trial, hp[bad, None, :])
            ok = e <= (e0 + etol)[bad, None]
            first = np.argmax(ok, axis=1)  # largest accepted step
            alpha[bad] = np.where(ok.any(axis=1), _ALPHAS[1:][first], 1.0)
        p[todo] = pp + alpha[:, None] * d
        active[todo] = Sp
        exact[todo] = alpha == 1.0
    raise SolveError(
        f"contact equilibrium did not converge in {MAX_NEWTON_ITERATIONS} Newton iterations "
        f"for {int((~done).sum())} of {m} moves"
    )


def solve_with_zero(model: ContactModel, h: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`solve_equilibrium` for heights h (m, n_c), solving the zero state (``model.p_zero``)
    in the same batch when it is not known yet (one Newton run instead of two)."""
    if "p_zero" in model.__dict__:
        return solve_equilibrium(model, h)
    h = np.atleast_2d(np.asarray(h, dtype=float))
    p, active = solve_equilibrium(model, np.vstack([ball_heights(model, model.q_zero[None, :]), h]))
    p0 = p[0].copy()
    p0.setflags(write=False)
    model.__dict__["p_zero"] = p0  # the cached_property's slot
    return p[1:], active[1:]


def equilibrium(
    stage: Stage | ContactModel, effects: Effects | None, q_actual: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Equilibrium platform pose for actual actuator displacements.

    Parameters
    ----------
    stage : Stage or ContactModel
    effects : Effects or None
        Physical causes (ignored when ``stage`` is a ContactModel; None = stage.corrections).
    q_actual : ndarray, shape (m, n_q) or (n_q,)
        Actual actuator displacements (backlash and noise already applied), µm.

    Returns
    -------
    p : ndarray, shape (m, n_p)
    active : ndarray of bool, shape (m, n_q)
    """
    model = contact_model(stage, effects)
    return solve_equilibrium(model, ball_heights(model, q_actual))


def approach_direction(dq: np.ndarray, last: np.ndarray | float = ZERO_STATE_DIRECTION,
                       tol_um: float = STILL_TOL_UM) -> np.ndarray:
    """The one direction-of-approach rule: the direction each actuator last moved after a step.

    Parameters
    ----------
    dq : ndarray, shape (n_q,) or (m, n_q)
        Commanded step of each actuator (q − q_before), µm.
    last : float or ndarray broadcastable to ``dq``
        Direction before the step (±1); the zero state's is +1 ("up").
    tol_um : float
        A step with abs(dq) <= tol_um is an actuator held still: it keeps ``last``.

    Returns
    -------
    ndarray, shape of ``dq``
        +1 / −1.
    """
    dq = np.asarray(dq, dtype=float)
    last = np.broadcast_to(np.asarray(last, dtype=float), dq.shape)
    return np.where(dq > tol_um, 1.0, np.where(dq < -tol_um, -1.0, last))


def directions_from_steps(dq: np.ndarray, initial: np.ndarray | float = ZERO_STATE_DIRECTION,
                          tol_um: float = STILL_TOL_UM) -> np.ndarray:
    """:func:`approach_direction` along a run: steps dq (m, n_q) in execution order.

    Row k's direction is that of its step, or row k−1's when actuator i is held still
    (``initial`` before the first row). Returns shape (m, n_q), entries ±1.
    """
    dq = np.atleast_2d(np.asarray(dq, dtype=float))
    m, n = dq.shape
    # the rule row by row is a forward fill of the moving steps' signs
    sign = approach_direction(dq, 0.0, tol_um)
    init = np.broadcast_to(np.asarray(initial, dtype=float), (n,))
    padded = np.vstack([init[None, :], sign])
    idx = np.where(padded != 0, np.arange(m + 1)[:, None], 0)
    idx = np.maximum.accumulate(idx, axis=0)
    return np.take_along_axis(padded, idx, axis=0)[1:]


def move_directions(q_cmd: np.ndarray, q_start: np.ndarray | None = None,
                    initial: np.ndarray | float = ZERO_STATE_DIRECTION) -> np.ndarray:
    """Direction each actuator last moved, for a *sequence* of commands (backlash state).

    Parameters
    ----------
    q_cmd : ndarray, shape (m, n_q)
        Commands in execution order.
    q_start : ndarray, shape (n_q,), optional
        Commands before the first row (default the zero state).
    initial : float or ndarray (n_q,)
        Direction before the first row (+1 = "up", the zero state's convention).

    Returns
    -------
    ndarray, shape (m, n_q)
        +1 / −1 by :func:`approach_direction` (a held actuator keeps the previous row's).
    """
    q = np.atleast_2d(np.asarray(q_cmd, dtype=float))
    start = np.zeros(q.shape[1]) if q_start is None else np.asarray(q_start, dtype=float)
    prev = np.vstack([start[None, :], q[:-1]])
    return directions_from_steps(q - prev, initial)


def actual_positions(model: ContactModel, q_cmd: np.ndarray,
                     direction: np.ndarray | float = ZERO_STATE_DIRECTION,
                     play: np.ndarray | None = None) -> np.ndarray:
    """Noise-free actual actuator positions, shape (m, n_q).

    q − lag·direction (backlash) + w Σ_j (z_j − q) (hysteresis, :func:`hysteresis.offset`).

    Parameters
    ----------
    model : ContactModel
    q_cmd : ndarray, shape (m, n_q) or (n_q,)
        Commands, µm.
    direction : float or ndarray broadcastable to (m, n_q)
        Direction each actuator last moved (±1).
    play : ndarray, shape (m, n_q, N_PLAY), optional
        Play states after each move (:func:`hysteresis.play_run`); needed when the model has
        hysteresis.

    Raises
    ------
    ValueError
        If the model has hysteresis and ``play`` is not given.
    """
    q = np.atleast_2d(np.asarray(q_cmd, dtype=float))
    out = q - model.lag_um * np.asarray(direction, dtype=float)
    if model.has_hysteresis:
        if play is None:
            raise ValueError("this stage has hysteresis: actual_positions needs the play states (play=)")
        out = out + hysteresis.offset(model.play_w, np.asarray(play, dtype=float).reshape(q.shape + (-1,)), q)
    return out


def tool_displacement(model: ContactModel, p: np.ndarray) -> np.ndarray:
    """Linear tool displacement d = w_true·(p − p_zero) (eq. 13 relative to the zero state), shape (m,)."""
    return (np.atleast_2d(p) - model.p_zero) @ model.w_true


def sensor_reading(model: ContactModel, p: np.ndarray, time_s: np.ndarray | float | None = None) -> np.ndarray:
    """Noise-free gauge reading for poses p (m, n_p) through ``model.sensor``, shape (m,)."""
    return model.sensor.forward(tool_displacement(model, p), time_s)


def mean_reading(
    stage: Stage | ContactModel,
    effects: Effects | None,
    q_cmd: np.ndarray,
    *,
    q_prev: np.ndarray | None = None,
    direction: np.ndarray | None = None,
    time_s: np.ndarray | float | None = None,
) -> np.ndarray:
    """Deterministic expected gauge reading for commanded moves (the simulator's mean).

    Parameters
    ----------
    stage : Stage or ContactModel
    effects : Effects or None
        Causes (ignored for a ContactModel; None = stage.corrections).
    q_cmd : ndarray, shape (m, n_q)
        Commanded actuator displacements, µm.
    q_prev : ndarray, shape (m, n_q), optional
        Commands of the move before each row. With backlash, the direction of row k is
        sign(q_k − q_prev,k); where that is 0 the previous row's direction is kept (rows
        are taken as one run in execution order, starting "up"). With hysteresis the play
        states run along the rows the same way (:func:`hysteresis.play_run`); without
        ``q_prev`` each row is one move from the zero state.
    direction : ndarray, shape (m, n_q), optional
        Explicit last-move directions (±1); overrides ``q_prev``.
    time_s : ndarray (m,) or float, optional
        Settling times, for drift.

    Returns
    -------
    ndarray, shape (m,)
        Expected reading, µm, relative to the zero state.
    """
    model = contact_model(stage, effects)
    q = np.atleast_2d(np.asarray(q_cmd, dtype=float))
    if direction is None:
        direction = ZERO_STATE_DIRECTION if q_prev is None else directions_from_steps(q - np.atleast_2d(q_prev))
    play = None
    if model.has_hysteresis:  # the run's play states; without q_prev each row from the zero state
        play = (hysteresis.play_step(-model.play_r, q, model.play_r) if q_prev is None
                else hysteresis.play_run(model.play_r, q, q_prev))
    p, _ = solve_equilibrium(model, ball_heights(model, actual_positions(model, q, direction, play)))
    return sensor_reading(model, p, time_s)


def tool_sensitivity(model: ContactModel, p: np.ndarray, active: np.ndarray) -> np.ndarray:
    """Linearised reading change per µm of actual actuator displacement, shape (m, n_q).

    dreading/dq = sensor'(d) · w_true^T (K_h + k_c A_S^T A_S)^-1 k_c A_S^T (n·d·gain),
    from the equilibrium of the contact set S (balls out of contact contribute 0).
    """
    p = np.atleast_2d(p)
    S = np.atleast_2d(active).astype(float)
    H = np.einsum("mi,ij,ik->mjk", S, model.A, model.A) * model.k_c
    idx = np.arange(model.n_p)
    H[:, idx, idx] += model.k_h
    v = np.linalg.solve(H, np.broadcast_to(model.w_true, p.shape)[..., None])[..., 0]  # H^-1 w (H symmetric)
    dp = model.k_c * S * (v @ model.A.T)  # (m, n_c): w^T H^-1 k_c a_i for active i
    return model.sensor.derivative(tool_displacement(model, p))[:, None] * dp * model.nd * model.gain


def reading_variance(sensitivity: np.ndarray, dq: np.ndarray, friction_std_per_um: np.ndarray,
                     actuator_std_um: float, gauge_std_um: float) -> np.ndarray:
    """Variance of a reading from actuator and gauge noise, first order, µm², shape (m,).

    v = Σ_i J_i² (σ_a² + (s_i |Δq_i|)²) + σ_g²: driver accuracy σ_a and stick-slip s_i |Δq_i|
    per actuator, propagated through the contact sensitivity J (:func:`tool_sensitivity`),
    plus the gauge noise σ_g.

    Parameters
    ----------
    sensitivity : ndarray, shape (m, n_q)
    dq : ndarray, shape (m, n_q)
        Actuator steps of the moves, µm.
    friction_std_per_um : ndarray, shape (n_q,)
    actuator_std_um, gauge_std_um : float
    """
    J = np.atleast_2d(sensitivity)
    var_q = actuator_std_um**2 + (np.asarray(friction_std_per_um) * np.abs(np.atleast_2d(dq))) ** 2
    return np.sum(J * J * var_q, axis=1) + gauge_std_um**2
