"""Each actuator's last direction of motion: the context a reversal's scatter depends on.

A piezo stack's hysteresis makes where an actuator turns round (its step has the sign opposite
to its previous motion) a point of its minor loop that is not repeatable, while a move that goes
on in the same direction is (:mod:`microctl.models.noise_dictionary`, the ``rev`` sources). The
direction an actuator last moved in is not a function of the move x = [s; u] (eq. 3): it is the
move's *context*, which whoever moves the stage knows from the commands it sent.

The rule is the package's one direction-of-approach rule (:func:`microctl.stage.physics.approach_direction`,
which the simulator's backlash also follows): the zero state is approached from below, so every
actuator starts with direction +1; an actuator whose command changes by at most
:data:`~microctl.stage.physics.STILL_TOL_UM` is held and keeps its direction.
"""

from __future__ import annotations

import numpy as np

from microctl.stage.physics import ZERO_STATE_DIRECTION, approach_direction, directions_from_steps

__all__ = ["initial", "after_move", "at_commands", "log_directions"]


def initial(n_q: int) -> np.ndarray:
    """The directions at the zero state, shape (n_q,): all +1."""
    return np.full(int(n_q), float(ZERO_STATE_DIRECTION))


def after_move(direction: np.ndarray, q_prev: np.ndarray, q: np.ndarray) -> np.ndarray:
    """The directions after a move from the commands q_prev to q (n_q,), from ``direction`` before it.

    Returns
    -------
    ndarray, shape (n_q,)
        sign(q - q_prev) where the actuator moved, else the direction before.
    """
    dq = np.asarray(q, dtype=float).reshape(-1) - np.asarray(q_prev, dtype=float).reshape(-1)
    d = np.asarray(direction, dtype=float).reshape(-1)
    if d.shape != dq.shape:
        raise ValueError(f"directions have shape {d.shape}; the commands {dq.shape}")
    return approach_direction(dq, d)


def at_commands(q: np.ndarray) -> np.ndarray:
    """The directions of a stage found standing at the commands q (n_q,), its history unknown:
    one move from the zero state to q (the hysteresis memory's convention), shape (n_q,)."""
    q = np.asarray(q, dtype=float).reshape(-1)
    return after_move(initial(q.size), np.zeros(q.size), q)


def log_directions(q_prev: np.ndarray, q: np.ndarray) -> np.ndarray:
    """The directions before every move of a log in execution order, shape (n, n_q).

    Parameters
    ----------
    q_prev, q : ndarray, shape (n, n_q)
        The commands before and after each move. The first row starts from the zero state;
        where a row's ``q_prev`` is not the row before's ``q`` (another session, a manual jog),
        the unlogged jump between them counts as one move.
    """
    q_prev = np.atleast_2d(np.asarray(q_prev, dtype=float))
    q = np.atleast_2d(np.asarray(q, dtype=float))
    steps = np.empty((2 * q.shape[0], q.shape[1]))
    steps[0::2] = q_prev - np.vstack([np.zeros((1, q.shape[1])), q[:-1]])  # the jump before each row (0: none)
    steps[1::2] = q - q_prev
    return directions_from_steps(steps, ZERO_STATE_DIRECTION)[0::2]
