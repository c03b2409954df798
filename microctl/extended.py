"""The extended forward model: the stage model with every accepted correction, through the physics.

The AFM (:mod:`microctl.afm`, eq. 5-14) applies only the *static* corrections of
``stage.corrections`` in the rigid least-squares limit. The extended model predicts the
reading with *all* of them — including backlash (needs the direction each actuator last
moved, i.e. the state s), contact loss (a ball lifting off: a kink) and drift (needs the
time) — through the elastic contact equilibrium of :mod:`microctl.physics`:

    q = K u                                  (eq. 12, CAD geometry: what the drivers get)
    q_act = q − lag ⊙ direction              (backlash)
    h = (n·d) ⊙ gain ⊙ q_act − gap           (ball heights)
    p = argmin E(p; h)                       (contact equilibrium, physics module)
    t = scale·d + quad·d² + drift·time,  d = w_true·(p − p_zero)

Its residual ``t − t_ext(s, u)`` is what the heteroscedastic GP is trained on for the
"extended EAFM" (``microctl diagnose``, shared/spec/diagnosis.md step 3).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from microctl.afm import inverse_kinematics_matrix
from microctl.config import Effects, Stage
from microctl.physics import (
    actual_positions,
    ball_heights,
    contact_model,
    directions_from_steps,
    sensor_reading,
    solve_equilibrium,
    tool_sensitivity,
)

__all__ = ["ExtendedForwardModel", "ExtendedPrediction"]


@dataclass(frozen=True)
class ExtendedPrediction:
    """Extended-model prediction at m moves.

    Attributes
    ----------
    t : ndarray, shape (m,)
        Expected reading, µm.
    q : ndarray, shape (m, n_q)
        Actuator commands q = K u, µm.
    sensitivity : ndarray, shape (m, n_q)
        d reading / d actual actuator displacement (to propagate actuator noise), µm/µm.
    active : ndarray of bool, shape (m, n_q)
        Balls in contact.
    """

    t: np.ndarray
    q: np.ndarray
    sensitivity: np.ndarray
    active: np.ndarray


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
        self.K = inverse_kinematics_matrix(stage)
        self.model = contact_model(stage, self.effects)

    @property
    def n_s(self) -> int:
        """Size of the state s = [t; q]."""
        return 1 + self.stage.n_act

    def _directions(self, q: np.ndarray, q_prev: np.ndarray | None, direction: np.ndarray | None) -> np.ndarray:
        if direction is not None:
            return np.broadcast_to(np.asarray(direction, dtype=float), q.shape)
        if q_prev is None:
            return np.ones_like(q)
        # Δq_i = 0 keeps the previous row's direction (rows taken as one run), "up" at the start.
        return directions_from_steps(q - np.broadcast_to(q_prev, q.shape), 1.0)

    def predict_q(
        self,
        q: np.ndarray,
        *,
        q_prev: np.ndarray | None = None,
        direction: np.ndarray | None = None,
        time_s: np.ndarray | float | None = None,
    ) -> ExtendedPrediction:
        """Prediction for actuator commands.

        Parameters
        ----------
        q : ndarray, shape (m, n_q) or (n_q,)
            Commands sent, µm.
        q_prev : ndarray, shape (m, n_q) or (n_q,), optional
            Commands before each move (gives the backlash direction).
        direction : ndarray, shape (m, n_q), optional
            Explicit last-move directions ±1 (overrides ``q_prev``).
        time_s : ndarray (m,) or float, optional
            Settling times; without them the drift term is left out (time 0).

        Returns
        -------
        ExtendedPrediction
        """
        q = np.atleast_2d(np.asarray(q, dtype=float))
        qp = None if q_prev is None else np.atleast_2d(np.asarray(q_prev, dtype=float))
        d = self._directions(q, qp, direction)
        q_act = actual_positions(self.model, q, d)
        p, active = solve_equilibrium(self.model, ball_heights(self.model, q_act))
        t = sensor_reading(self.model, p, time_s)
        return ExtendedPrediction(t=t, q=q, sensitivity=tool_sensitivity(self.model, p, active), active=active)

    def predict(
        self,
        s: np.ndarray | None,
        u: np.ndarray,
        *,
        time_s: np.ndarray | float | None = None,
        direction: np.ndarray | None = None,
    ) -> np.ndarray:
        """Expected reading t(s, u[, time]).

        Parameters
        ----------
        s : ndarray, shape (n_s,) or (m, n_s), or None
            State before the move [t_prev; q_prev] (only q_prev matters, for backlash);
            None: every actuator taken as having last moved up.
        u : ndarray, shape (n_p,) or (m, n_p)
        time_s, direction : see :meth:`predict_q`

        Returns
        -------
        ndarray, shape (m,)
        """
        u2 = np.atleast_2d(np.asarray(u, dtype=float))
        q = u2 @ self.K.T
        q_prev = None
        if s is not None and direction is None:
            s2 = np.atleast_2d(np.asarray(s, dtype=float))
            q_prev = np.broadcast_to(s2[:, 1:], q.shape)
            # each row is a separate move from its own state: a zero step counts as "up"
            direction = np.where(q > q_prev, 1.0, np.where(q < q_prev, -1.0, 1.0))
        return self.predict_q(q, q_prev=q_prev, direction=direction, time_s=time_s).t

    def residual(self, data) -> np.ndarray:
        """Measured minus predicted reading for a :class:`~microctl.diagnosis.data.DiagnosisData`, (n,)."""
        return data.t - self.predict_q(data.q, direction=data.direction, time_s=data.time_s).t
