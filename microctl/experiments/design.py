"""Training move designs (paper IV-A: "125 randomly generated control signals evenly
distributed in the workspace").

The residual GP's input is x = [s; u] (eq. 3), so a design fixes the distribution of
(previous state, move) pairs as well as of poses. Three designs:

``space_filling``
    :func:`microctl.collect.space_filling_moves`: Sobol points in the workspace polytope, in
    an order that keeps consecutive moves far apart (every actuator makes a large step).
``from_zero``
    The absolute-movement pattern of IV-C: u0, u1, u0, u2, ... with u_k space-filling, so
    every other move starts at the zero state (``moves`` counts the returns too).
``face_episodes``
    Episodes shaped like the incremental experiment (IV-D): a return to the zero state, then
    ``episode_moves`` poses in increasing order of the AFM tool pose, all on the face of the
    workspace where one actuator, chosen at random per episode, stays at its zero-state
    command. Variance-optimal commands (eq. 4) sit on such faces: with stick-slip or any
    step-dependent scatter, holding an actuator still is what a redundant stage can do to
    be repeatable, so the model must see both the still and the moving actuator in similar
    states. No actuator is singled out: each is held in a quarter of the episodes (Table I).
"""

from __future__ import annotations

import numpy as np

from microctl.afm import AnalyticForwardModel
from microctl.collect import space_filling_moves
from microctl.errors import ConfigError

__all__ = ["training_moves", "face_episode_moves"]


def training_moves(afm: AnalyticForwardModel, design: str, n: int, seed: int, episode_moves: int = 4) -> np.ndarray:
    """The training control signals of a design.

    Parameters
    ----------
    afm : AnalyticForwardModel
        Gives the workspace polytope and K (eq. 12).
    design : str
        ``space_filling``, ``from_zero`` or ``face_episodes`` (see the module docstring).
    n : int
        Number of moves (returns to the zero state included).
    seed : int
    episode_moves : int
        Poses per episode (``face_episodes`` only).

    Returns
    -------
    ndarray, shape (n, n_p)
    """
    if design == "space_filling":
        return space_filling_moves(afm, n, seed=seed)
    if design == "from_zero":
        m = (n + 1) // 2
        sig = space_filling_moves(afm, m, seed=seed)
        out = np.zeros((2 * m, afm.n_p))
        out[1::2] = sig  # u0, u1, u0, u2, ... (IV-C)
        return out[:n]
    if design == "face_episodes":
        return face_episode_moves(afm, n, np.random.default_rng(seed), episode_moves)
    raise ConfigError(f"training design '{design}' is not one of space_filling, from_zero, face_episodes")


def face_episode_moves(afm: AnalyticForwardModel, n: int, rng: np.random.Generator,
                       episode_moves: int = 4, pool_size: int = 20000) -> np.ndarray:
    """Episodes: zero state, then poses on a face {K_i u = 0} in increasing AFM t order.

    Parameters
    ----------
    afm : AnalyticForwardModel
    n : int
        Total number of moves (returns included), ≥ 1.
    rng : numpy.random.Generator
    episode_moves : int
        Poses per episode after its return to the zero state.
    pool_size : int
        Uniform workspace samples the face points are drawn from.

    Returns
    -------
    ndarray, shape (n, n_p)
    """
    ws = afm.workspace
    pool = ws.sample(pool_size, rng)
    K = afm.K
    faces = []
    for i in range(afm.n_q):
        Ki = K[i]
        # project the pool onto the plane K_i u = 0 (the actuator at its zero-state command)
        P = pool - np.outer(pool @ Ki, Ki) / float(Ki @ Ki)
        P = P[ws.contains(P)]
        faces.append(P if len(P) >= episode_moves else pool)
    out: list[np.ndarray] = []
    while len(out) < n:
        out.append(np.zeros(afm.n_p))
        face = faces[int(rng.integers(afm.n_q))]
        pts = face[rng.choice(len(face), size=episode_moves, replace=False)]
        out.extend(pts[np.argsort(np.asarray(afm.t_of(pts)))])
    return np.array(out[:n])
