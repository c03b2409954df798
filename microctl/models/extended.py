"""The stage model: one object for the simulated stage, its oracle and the diagnosis.

The AFM (:mod:`microctl.models.afm`, eq. 5-14) applies only the *static* corrections of
``stage.corrections`` in the rigid least-squares limit. :class:`ExtendedForwardModel`
predicts the reading with *every* cause of the registry (:mod:`microctl.stage.causes`) —
including backlash (needs the direction each actuator last moved, i.e. the state),
hysteresis (needs the play states, the loop's memory: :mod:`microctl.stage.hysteresis`),
contact loss (a ball lifting off: a kink) and drift (needs the time) — through the elastic
contact equilibrium of :mod:`microctl.stage.physics`:

    q = K u                                  (eq. 12, CAD geometry: what the drivers get)
    direction = approach_direction(q − q_prev, last)   (one rule, physics module)
    z = play(z_before, q)                    (hysteresis play states)
    q_act = q − lag ⊙ direction + w ⊙ Σ_j (z_j − q)   (backlash, hysteresis)
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

from microctl.stage import hysteresis
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

    def actual_positions(self, q: np.ndarray, direction: np.ndarray | float,
                         play: np.ndarray | None = None) -> np.ndarray:
        """Noise-free actual actuator positions (backlash, hysteresis), shape (m, n_q).

        ``play`` (m, n_q, N_PLAY): the play states after the moves, needed with hysteresis
        (:meth:`next_play`, :meth:`play_run`)."""
        return actual_positions(self.model, q, direction, play)

    @property
    def has_hysteresis(self) -> bool:
        """Whether the state must carry play states (some actuator has hysteresis)."""
        return self.model.has_hysteresis

    def zero_play(self) -> np.ndarray | None:
        """Play states of the zero state, shape (n_q, N_PLAY), or None without hysteresis."""
        return -np.array(self.model.play_r) if self.has_hysteresis else None

    def next_play(self, q: np.ndarray, last_play: np.ndarray | None) -> np.ndarray | None:
        """Play states after moves to commands q (m, n_q) or (n_q,), each from ``last_play``
        ((n_q, N_PLAY), default the zero state's): shape (m, n_q, N_PLAY), or None without
        hysteresis. Rows are alternative moves from one state (not a run)."""
        if not self.has_hysteresis:
            return None
        z0 = self.zero_play() if last_play is None else np.asarray(last_play, dtype=float)
        return hysteresis.play_step(z0, np.atleast_2d(np.asarray(q, dtype=float)), self.model.play_r)

    def play_run(self, q: np.ndarray, q_prev: np.ndarray | None = None,
                 last_play: np.ndarray | None = None) -> np.ndarray | None:
        """Play states along a run of commands q (m, n_q) in execution order, each row fed its
        q_prev first (:func:`microctl.stage.hysteresis.play_run`), from ``last_play`` (default
        the zero state's): shape (m, n_q, N_PLAY), or None without hysteresis."""
        if not self.has_hysteresis:
            return None
        return hysteresis.play_run(self.model.play_r, q, q_prev, last_play)

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
        play: np.ndarray | None = None,
        last_play: np.ndarray | None = None,
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
        play : ndarray, shape (m, n_q, N_PLAY), optional
            Play states after each move (hysteresis); overrides the ones below.
        last_play : ndarray, shape (n_q, N_PLAY), optional
            Play states before the move(s) (default the zero state's). With a 2-D ``q_prev``
            they run along the rows (:meth:`play_run`); otherwise each row is a move from them
            (:meth:`next_play`). Ignored without hysteresis.

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
        if play is None and self.has_hysteresis:
            play = (self.play_run(q, q_prev, last_play) if q_prev is not None and np.ndim(q_prev) == 2
                    else self.next_play(q, last_play))
        p, active = self.pose(self.actual_positions(q, d, play))
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
        last_play: np.ndarray | None = None,
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
        last_play : ndarray, shape (n_q, N_PLAY), optional
            Play states before state s (hysteresis; default the zero state's). Each row is a
            move from q_prev with these states (the move to q_prev fed first).

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
        play = None
        if self.has_hysteresis:  # the state's q_prev, then q
            z0 = last_play if s is None else self.next_play(np.atleast_2d(np.asarray(s, dtype=float))[:, 1:], last_play)
            play = self.next_play(q, z0)
        return self.predict_q(q, direction=direction, time_s=time_s, play=play).t

    def variance(self, prediction: ExtendedPrediction, dq: np.ndarray, *, actuator_std_um: float,
                 gauge_std_um: float) -> np.ndarray:
        """Variance of the readings of predicted moves with steps ``dq`` (m, n_q), µm², shape (m,)
        (:func:`microctl.stage.physics.reading_variance` with this model's stick-slip)."""
        return reading_variance(prediction.sensitivity, dq, self.model.friction_std_per_um, actuator_std_um,
                                gauge_std_um)

    def predict_data(self, data) -> ExtendedPrediction:
        """Prediction for the moves of a :class:`~microctl.diagnosis.data.DiagnosisData`: its
        directions and times; with hysteresis, the play states run along its rows in order, each
        row fed its q_prev first (a row whose predecessor was left out of a subset still starts
        from its true previous command; memory older than that move is lost there)."""
        return self.predict_q(data.q, direction=data.direction, time_s=data.time_s,
                              play=self.play_run(data.q, data.q_prev))

    def residual(self, data) -> np.ndarray:
        """Measured minus predicted reading for a :class:`~microctl.diagnosis.data.DiagnosisData`, (n,)."""
        return data.t - self.predict_data(data).t
