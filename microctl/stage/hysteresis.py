"""Rate-independent piezo hysteresis: play operators and the Prandtl-Ishlinskii sum of the ``hysteresis`` cause.

A play operator of threshold r (Krasnosel'skii & Pokrovskii) has a state z that follows its
input x only when x has moved more than r away from it:

    z_k = max(x_k - r, min(x_k + r, z_{k-1}))

so after a long move up z = x - r, after a long move down z = x + r, and after a reversal
shorter than 2r it has not moved at all. The ``hysteresis`` cause of actuator i
(:class:`~microctl.stage.causes.Hysteresis`) is a Prandtl-Ishlinskii sum of
:data:`N_PLAY` operators on the *command* q_i, thresholds r_ij = R_i j / N_PLAY (j = 1..N_PLAY)
and equal weights w_i with w_i Σ_j r_ij = h_i:

    q_act,i = q_i + w_i Σ_j (z_ij - q_i)

After a move longer than 2 R_i the actuator ends h_i short of its command in the direction it
moved (a backlash of lag h_i: the limit R -> 0 is the ``backlash`` cause); after a shorter
reversal it is part-way round its loop, by an amount that depends on how far the reversal went
and on the moves before it (the loop's memory). The zero state counts as approached from below
(z = -r, so q_act = -h there), the convention of the backlash direction.

The state of a stage with hysteresis is therefore the play states z (n_q, N_PLAY) beside the
last commands: the simulated stage carries them (:class:`~microctl.backends.simulated.SimulatedStage`),
and a diagnosis runs them along the log's commands (:func:`play_run`).
"""

from __future__ import annotations

import numpy as np

__all__ = ["N_PLAY", "thresholds", "weights", "zero_play", "play_step", "play_run", "offset"]

#: Play operators per actuator of the ``hysteresis`` cause (thresholds R j / N_PLAY).
N_PLAY = 4


def thresholds(range_um: np.ndarray) -> np.ndarray:
    """Thresholds r_ij = R_i j / N_PLAY, µm, shape (n_q, N_PLAY), from the largest ones R (n_q,)."""
    R = np.asarray(range_um, dtype=float).reshape(-1)
    return R[:, None] * (np.arange(1, N_PLAY + 1) / N_PLAY)[None, :]


def weights(half_width_um: np.ndarray, range_um: np.ndarray) -> np.ndarray:
    """Equal weights per actuator with Σ_j w_i r_ij = h_i (the major loop's half-width), shape (n_q,).

    0 where h_i = 0 or R_i = 0 (no hysteresis on that actuator)."""
    h = np.asarray(half_width_um, dtype=float).reshape(-1)
    s = thresholds(range_um).sum(axis=1)
    return np.where(s > 0, h / np.where(s > 0, s, 1.0), 0.0)


def zero_play(range_um: np.ndarray) -> np.ndarray:
    """Play states at the zero state (q = 0 approached from below: z = -r), shape (n_q, N_PLAY)."""
    return -thresholds(range_um)


def play_step(z: np.ndarray, x: np.ndarray, r: np.ndarray) -> np.ndarray:
    """One step of the play operators: z' = max(x - r, min(x + r, z)).

    Parameters
    ----------
    z : ndarray, shape (..., n_q, N_PLAY)
        States before the step.
    x : ndarray, shape (..., n_q)
        Inputs (commands), µm.
    r : ndarray, shape (n_q, N_PLAY)
        Thresholds, µm.

    Returns
    -------
    ndarray, broadcast shape of z and x[..., None]
    """
    xe = np.asarray(x, dtype=float)[..., None]
    return np.maximum(xe - r, np.minimum(xe + r, z))


def play_run(r: np.ndarray, q: np.ndarray, q_prev: np.ndarray | None = None,
             z0: np.ndarray | None = None) -> np.ndarray:
    """Play states after each move of a run of commands in execution order.

    Each row feeds its previous command q_prev (when given) and then q: in a complete run
    q_prev[k] = q[k-1] and the first feed changes nothing; a row whose predecessor was left out
    of the data still starts from its true previous command.

    Parameters
    ----------
    r : ndarray, shape (n_q, N_PLAY)
    q : ndarray, shape (m, n_q)
    q_prev : ndarray, shape (m, n_q), optional
    z0 : ndarray, shape (n_q, N_PLAY), optional
        States before the first row (default the zero state's, -r).

    Returns
    -------
    ndarray, shape (m, n_q, N_PLAY)
    """
    q = np.atleast_2d(np.asarray(q, dtype=float))
    z = -r if z0 is None else np.asarray(z0, dtype=float)
    out = np.empty(q.shape + (r.shape[1],))
    lo, hi = q[:, :, None] - r, q[:, :, None] + r
    if q_prev is not None:
        qp = np.atleast_2d(np.asarray(q_prev, dtype=float))
        plo, phi = qp[:, :, None] - r, qp[:, :, None] + r
        for k in range(q.shape[0]):
            z = np.maximum(lo[k], np.minimum(hi[k], np.maximum(plo[k], np.minimum(phi[k], z))))
            out[k] = z
    else:
        for k in range(q.shape[0]):
            z = np.maximum(lo[k], np.minimum(hi[k], z))
            out[k] = z
    return out


def offset(w: np.ndarray, z: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Hysteresis part of the actual positions, w_i Σ_j (z_ij - q_i), µm.

    Parameters
    ----------
    w : ndarray, shape (n_q,)
    z : ndarray, shape (m, n_q, N_PLAY)
    q : ndarray, shape (m, n_q)

    Returns
    -------
    ndarray, shape (m, n_q)
    """
    q = np.atleast_2d(np.asarray(q, dtype=float))
    return w * (np.sum(z, axis=-1) - z.shape[-1] * q)
