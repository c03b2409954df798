"""The stage model: one object for the simulated stage, its oracle and the diagnosis.

The AFM (:mod:`microctl.models.afm`, eq. 5-14) applies only the *static* corrections of
``stage.corrections`` in the rigid least-squares limit. :class:`ExtendedForwardModel`
predicts the reading with *every* cause of the registry (:mod:`microctl.stage.causes`) —
including backlash (needs the direction each actuator last moved, i.e. the state),
contact loss (a ball lifting off: a kink) and drift (needs the time) — through the elastic
contact equilibrium of :mod:`microctl.stage.physics`:

    q = K u                                  (eq. 12, CAD geometry: what the drivers get)
    direction = approach_direction(q − q_prev, last)   (one rule, physics module)
    q_act = q − lag ⊙ direction              (backlash)
    h = (n·d) ⊙ gain ⊙ q_act − gap           (ball heights)
    p = argmin E(p; h)                       (contact equilibrium, physics module)
    t = sensor.forward(d, time),  d = w_true·(p − p_zero)

The same object is the simulated stage's truth (:class:`~microctl.backends.simulated.SimulatedStage`
moves through :meth:`~ExtendedForwardModel.actual_positions`, :meth:`~ExtendedForwardModel.pose`
and :meth:`~ExtendedForwardModel.reading`, and its oracle's ``true_mean``/``true_var`` are
:meth:`~ExtendedForwardModel.predict_q` and :meth:`~ExtendedForwardModel.variance`), and the
diagnosis' model of a candidate set of causes. Its residual ``t − t_ext(s, u)`` is what the
heteroscedastic GP is trained on for the "extended EAFM" (``microctl diagnose``,
shared/spec/diagnosis.md step 3).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

from microctl.stage.causes import Effects
from microctl.stage.geometry import Stage
from microctl.stage.kinematics import inverse_kinematics_matrix
from microctl.stage.physics import (
    ZERO_STATE_DIRECTION,
    actual_positions,
    approach_direction,
    ball_heights,
    contact_model,
    directions_from_steps,
    reading_variance,
    sensor_reading,
    solve_with_zero,
    tool_sensitivity,
)

__all__ = ["ExtendedForwardModel", "ExtendedPrediction"]


@dataclass(frozen=True, eq=False)
class ExtendedPrediction:
    """Extended-model prediction at m moves.

    Attributes
    ----------
    t : ndarray, shape (m,)
        Expected reading, µm.
    q : ndarray, shape (m, n_q)
        Actuator commands q = K u, µm.
    p : ndarray, shape (m, n_p)
        Equilibrium platform poses.
    active : ndarray of bool, shape (m, n_q)
        Balls in contact.
    model : ContactModel
        The physics the prediction was made with.
    """

    t: np.ndarray
    q: np.ndarray
    p: np.ndarray
    active: np.ndarray
    model: object

    @cached_property
    def sensitivity(self) -> np.ndarray:
        """d reading / d actual actuator displacement (to propagate actuator noise), µm/µm, shape (m, n_q)."""
        return tool_sensitivity(self.model, self.p, self.active)


class ExtendedForwardModel:
    """Stage model + corrections (static and dynamic) through the contact physics.

    Parameters
    ----------
    stage : Stage
        Geometry, physics and ``corrections`` (the accepted causes).
    effects : Effects, optional
        Use these corrections instead of ``stage.corrections`` (a candidate during a fit).

    Attributes
    ----------
    K : ndarray, shape (n_q, n_p)
        CAD inverse kinematics (eq. 12).
    model : ContactModel
        The physics with the corrections.
    """

    def __init__(self, stage: Stage, effects: Effects | None = None):
        self.stage = stage
        self.effects = stage.corrections if effects is None else effects
        self.model = contact_model(stage, self.effects)

    @cached_property
    def K(self) -> np.ndarray:
        """q = K u from the CAD geometry (what the drivers get), whatever the physics and
        corrections (read-only; computed on first use: the diagnosis's fits never need it)."""
        K = inverse_kinematics_matrix(self.stage)
        K.setflags(write=False)
        return K

    @property
    def n_s(self) -> int:
        """Size of the state s = [t; q]."""
        return 1 + self.stage.n_act

    # ---- one move, step by step (the simulated stage moves through these) ---------------
    @staticmethod
    def next_direction(dq: np.ndarray, last: np.ndarray | float = ZERO_STATE_DIRECTION) -> np.ndarray:
        """Direction of approach after steps ``dq`` from last directions ``last``
        (:func:`microctl.stage.physics.approach_direction`: a held actuator keeps ``last``)."""
        return approach_direction(dq, last)

    def actual_positions(self, q: np.ndarray, direction: np.ndarray | float) -> np.ndarray:
        """Noise-free actual actuator positions (backlash), shape (m, n_q)."""
        return actual_positions(self.model, q, direction)

    def pose(self, q_actual: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Contact equilibrium for actual actuator positions (m, n_q): pose (m, n_p), balls in contact (m, n_q)."""
        return solve_with_zero(self.model, ball_heights(self.model, q_actual))

    def reading(self, p: np.ndarray, time_s: np.ndarray | float | None = None) -> np.ndarray:
        """Noise-free gauge reading of poses p (m, n_p) at ``time_s``, shape (m,)."""
        return sensor_reading(self.model, p, time_s)

    # ---- predictions ---------------------------------------------------------------------
    def predict_q(
        self,
        q: np.ndarray,
        *,
        q_prev: np.ndarray | None = None,
        direction: np.ndarray | None = None,
        last_direction: np.ndarray | float = ZERO_STATE_DIRECTION,
        time_s: np.ndarray | float | None = None,
    ) -> ExtendedPrediction:
        """Prediction for actuator commands.

        Parameters
        ----------
        q : ndarray, shape (m, n_q) or (n_q,)
            Commands sent, µm.
        q_prev : ndarray, shape (m, n_q) or (n_q,), optional
            Commands before each move (gives the backlash direction by
            :func:`~microctl.stage.physics.approach_direction`). A 2-D ``q_prev`` with one row per
            move is read as one run in execution order (a held actuator keeps the previous
            row's direction, ``last_direction`` before the first row); a single state (n_q,)
            as m alternative moves from it (each held actuator keeps ``last_direction``).
        direction : ndarray, shape (m, n_q), optional
            Explicit last-move directions ±1 (overrides ``q_prev``).
        last_direction : float or ndarray (n_q,) or (m, n_q)
            Direction of approach before the move(s) (+1, "up", for the zero state).
        time_s : ndarray (m,) or float, optional
            Settling times; without them the drift term is left out (time 0).

        Returns
        -------
        ExtendedPrediction
        """
        q = np.atleast_2d(np.asarray(q, dtype=float))
        if direction is not None:
            d = np.broadcast_to(np.asarray(direction, dtype=float), q.shape)
        elif q_prev is None:
            d = np.broadcast_to(np.asarray(last_direction, dtype=float), q.shape)
        elif np.ndim(q_prev) == 1:
            d = approach_direction(q - np.asarray(q_prev, dtype=float)[None, :], last_direction)
        else:
            d = directions_from_steps(q - np.atleast_2d(np.asarray(q_prev, dtype=float)), last_direction)
        p, active = self.pose(self.actual_positions(q, d))
        t = self.reading(p, time_s)
        return ExtendedPrediction(t=t, q=q, p=p, active=active, model=self.model)

    def predict(
        self,
        s: np.ndarray | None,
        u: np.ndarray,
        *,
        time_s: np.ndarray | float | None = None,
        direction: np.ndarray | None = None,
        last_direction: np.ndarray | float = ZERO_STATE_DIRECTION,
    ) -> np.ndarray:
        """Expected reading t(s, u[, time]).

        Parameters
        ----------
        s : ndarray, shape (n_s,) or (m, n_s), or None
            State before the move [t_prev; q_prev] (only q_prev matters, for backlash);
            None: the moves start from the zero state.
        u : ndarray, shape (n_p,) or (m, n_p)
        time_s, direction : see :meth:`predict_q`
        last_direction : float or ndarray (n_q,) or (m, n_q)
            Direction each actuator last moved before state s (the state [t; q] does not hold
            it; +1 for the zero state). An actuator held still keeps it.

        Returns
        -------
        ndarray, shape (m,)
        """
        u2 = np.atleast_2d(np.asarray(u, dtype=float))
        q = u2 @ self.K.T
        if direction is None:
            q_prev = np.zeros_like(q) if s is None else np.broadcast_to(np.atleast_2d(np.asarray(s, dtype=float))[:, 1:],
                                                                         q.shape)
            # each row is a separate move from its own state (not a run)
            direction = approach_direction(q - q_prev, last_direction)
        return self.predict_q(q, direction=direction, time_s=time_s).t

    def variance(self, prediction: ExtendedPrediction, dq: np.ndarray, *, actuator_std_um: float,
                 gauge_std_um: float) -> np.ndarray:
        """Variance of the readings of predicted moves with steps ``dq`` (m, n_q), µm², shape (m,)
        (:func:`microctl.stage.physics.reading_variance` with this model's stick-slip)."""
        return reading_variance(prediction.sensitivity, dq, self.model.friction_std_per_um, actuator_std_um,
                                gauge_std_um)

    def residual(self, data) -> np.ndarray:
        """Measured minus predicted reading for a :class:`~microctl.diagnosis.data.DiagnosisData`, (n,)."""
        return data.t - self.predict_q(data.q, direction=data.direction, time_s=data.time_s).t
