"""Training move designs: which control signals ``collect`` and the experiments execute.

The residual GP's input is x = [s; u] (eq. 3), so a design fixes the distribution of
(previous state, move) pairs as well as of poses. The noise model (``noise_prior``) needs,
for every actuator, moves where it is still *and* moves where it travels far, with the
other actuators varying independently; the optimal controller (eq. 4) then picks quiet
poses on the faces of the workspace polytope {u : lo <= K u <= hi} (an actuator held
still, another at its range limit), so the mean correction must be learned there too.

``covering``
    A sequence mixing three kinds of move from the current pose, each actuator taking
    each role equally often (a shuffled schedule, seeded):

    - *space-filling*: the next point of a scrambled Sobol sequence in the polytope (the
      paper's IV-A design);
    - *hold*: one or two actuators held still (dq_i = 0 to round-off: the pose is a command u,
      so K_i u keeps its value to floating-point round-off, far inside the hold tolerance
      ``microctl.stage.physics.STILL_TOL_UM``), the pose moved inside
      the section of the polytope where they stay, by a step whose length is a uniform
      fraction of the way to a random point of that section, so step sizes spread from 0 to
      the full range whatever the pose;
    - *face*: one actuator put at its lower or upper limit (a facet of the polytope), with
      another held still or put at a limit too in a share of them (edges).
``covering_still`` (default)
    ``covering`` with every :data:`STILL_EVERY`-th move replaced by a *still* move: the
    previous command sent again, so every actuator's step and the platform's motion are zero.
    The noise floor c_0 (the gauge and the drivers, ``noise_prior`` eq. 1) is identified by the
    moves where no selected noise source is active; where every source grows with the step (a
    hinge that slips with the platform's rotation, stick-slip on several actuators), the covering
    design has few such moves, the floor is confounded with the sources and can be fitted near
    zero, and the repeatability predicted at a quiet pose is then far below the stage's. A still
    move reads the floor plus the pose-dependent sources alone. The other moves are the
    covering design's (the one a still move replaces is left out). The default since it was
    measured against ``covering`` on the rig families of ``scripts/bench_rigs.py`` under an
    adoption rule fixed before the runs (docs/experiments.md, "Training designs").
``space_filling``
    The paper's 125 moves evenly covering the workspace: Sobol points kept inside the
    polytope, in a seeded order in which consecutive moves are not close (every actuator
    makes a large step; O(n) memory).
``from_zero``
    The absolute-movement pattern of IV-C: u0, u1, u0, u2, ... with u_k space-filling.
``face_episodes``
    Episodes shaped like the incremental experiment (IV-D): a return to the zero state,
    then poses in increasing tool-pose order on the face where one actuator (chosen at
    random per episode) stays at its zero-state command.
"""

from __future__ import annotations

import numpy as np

from microctl.errors import ConfigError, SolveError
from microctl.models.afm import AnalyticForwardModel
from microctl.util.signals import interrupts_deferred

__all__ = ["DESIGNS", "DEFAULT_DESIGN", "STILL_EVERY", "training_moves", "covering_moves", "space_filling_moves",
           "face_episode_moves"]

#: Training designs by name (see the module docstring).
DESIGNS = ("covering", "space_filling", "from_zero", "face_episodes", "covering_still")
DEFAULT_DESIGN = "covering_still"

#: Consecutive space-filling moves closer than this fraction of the median inter-point
#: distance are re-ordered.
MIN_STEP_FRACTION = 0.25

#: Shares of the move kinds in the covering design (space-filling, hold, face).
COVERING_SHARES = (0.4, 0.35, 0.25)

#: ``covering_still``: moves 20, 40, ... (1-based) repeat the previous command (5 % of the moves).
STILL_EVERY = 20

#: Largest number of moves a design builds (a guard against typing errors, not a memory limit).
MAX_MOVES = 1_000_000


def training_moves(afm: AnalyticForwardModel, design: str, n: int, seed: int, episode_moves: int = 4) -> np.ndarray:
    """The training control signals of a design.

    Parameters
    ----------
    afm : AnalyticForwardModel
        Gives the workspace polytope and K (eq. 12).
    design : str
        One of :data:`DESIGNS` (see the module docstring).
    n : int
        Number of moves (returns to the zero state included), 1 ... :data:`MAX_MOVES`.
    seed : int
        Non-negative seed.
    episode_moves : int
        Poses per episode (``face_episodes`` only).

    Returns
    -------
    ndarray, shape (n, n_p)

    Raises
    ------
    ConfigError
        Unknown design, n or seed out of range.
    """
    if isinstance(n, bool) or int(n) != n or not 1 <= n <= MAX_MOVES:
        raise ConfigError(f"the number of moves must be an integer in [1, {MAX_MOVES}], got {n!r}")
    if isinstance(seed, bool) or int(seed) != seed or seed < 0:
        raise ConfigError(f"the design seed must be a non-negative integer, got {seed!r}")
    n, seed = int(n), int(seed)
    if design == "covering":
        return covering_moves(afm, n, seed=seed)
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
    if design == "covering_still":
        u = covering_moves(afm, n, seed=seed)
        still = np.arange(STILL_EVERY - 1, n, STILL_EVERY)
        u[still] = u[still - 1]  # never a still move itself: STILL_EVERY >= 2
        return u
    raise ConfigError(f"training design '{design}' is not one of {', '.join(DESIGNS)}")


# --------------------------------------------------------------------------- space filling


def _sobol_in_polytope(afm: AnalyticForwardModel, n: int, seed: int) -> np.ndarray:
    """The first n points of a scrambled Sobol sequence (bounding box) that lie in the polytope."""
    from scipy.stats import qmc  # here, not at import: scipy.stats costs most of a second of start-up

    ws = afm.workspace
    # a Ctrl-C inside the first Sobol's set-up (compiled code that cannot raise) would be printed as a
    # traceback: held until it is done, then raised here (microctl.util.signals)
    with interrupts_deferred():
        sobol = qmc.Sobol(d=ws.u_lo.size, scramble=True, seed=np.random.default_rng(seed))
    m = max(int(np.ceil(np.log2(max(4 * n, 16)))), 4)
    return ws.first_inside(n, lambda: ws.map_unit(sobol.random_base2(m=m)), 64,
                           "the workspace polytope is too thin to fill from its bounding box")


def space_filling_moves(afm: AnalyticForwardModel, n: int, seed: int = 0) -> np.ndarray:
    """``n`` control signals filling the workspace polytope, in a state-spreading order.

    Prefix-filtered scrambled Sobol points (``scipy.stats.qmc.Sobol``) keep their low
    discrepancy inside the polytope; the points are put in a seeded random order, then a
    repair pass swaps any move within a quarter of the median inter-point distance (in
    actuator space, µm) of its predecessor with the first later point far enough from
    both neighbours. Memory O(n): distances are computed pair by pair, the median from a
    random sample of pairs.

    Parameters
    ----------
    afm : AnalyticForwardModel
    n : int
        Number of moves (>= 1).
    seed : int

    Returns
    -------
    ndarray, shape (n, n_p)
    """
    if n < 1:
        raise SolveError(f"the number of moves must be at least 1, got {n}")
    pts = _sobol_in_polytope(afm, n, seed)
    return _spread_order(pts, afm.K, np.random.default_rng([seed, 1]))


def _spread_order(u: np.ndarray, K: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    n = len(u)
    order = rng.permutation(n)
    if n < 3:
        return u[order]
    q = u @ K.T
    if n * (n - 1) // 2 <= 20_000:  # every pair (small n)
        i, j = np.triu_indices(n, 1)
    else:  # a random sample of pairs keeps the memory O(n)
        i, j = rng.integers(0, n, 20_000), rng.integers(0, n, 20_000)
        i, j = i[i != j], j[i != j]
    min_step = MIN_STEP_FRACTION * float(np.median(np.linalg.norm(q[i] - q[j], axis=1)))

    def dist(a: int, b: int) -> float:
        return float(np.linalg.norm(q[a] - q[b]))

    order = list(order)
    for k in range(1, n):
        if dist(order[k - 1], order[k]) >= min_step:
            continue
        for j in range(k + 1, min(n, k + 1 + 200)):  # a bounded search keeps it O(n)
            nxt = order[k + 1] if k + 1 < n and k + 1 != j else None
            if dist(order[k - 1], order[j]) >= min_step and (nxt is None or dist(order[j], nxt) >= min_step):
                order[k], order[j] = order[j], order[k]
                break
    return u[np.array(order)]


# --------------------------------------------------------------------------- covering


def _section_point(afm: AnalyticForwardModel, rows: np.ndarray, values: np.ndarray, rng: np.random.Generator,
                   tries: int = 400) -> np.ndarray | None:
    """A random pose of the polytope with ``K[rows] u = values``, or None if none was found.

    Uniform samples of the polytope projected onto the affine subspace, the first inside.
    """
    K = afm.K
    E = K[rows]
    u_p = np.linalg.lstsq(E, values, rcond=None)[0]
    _, sv, Vt = np.linalg.svd(E)
    rank = int(np.sum(sv > 1e-9 * sv.max()))
    N = Vt[rank:].T  # null space of E
    ws = afm.workspace
    for _ in range(4):
        cand = rng.uniform(ws.u_lo, ws.u_hi, size=(tries, afm.n_p))
        P = u_p + (cand - u_p) @ N @ N.T
        ok = ws.contains(P)
        if np.any(ok):
            return P[np.flatnonzero(ok)[0]]
    return None


def covering_moves(afm: AnalyticForwardModel, n: int, seed: int = 0) -> np.ndarray:
    """The ``covering`` design (module docstring): space-filling, hold and face moves.

    Parameters
    ----------
    afm : AnalyticForwardModel
    n : int
        Number of moves (>= 1); the first starts from the zero state.
    seed : int

    Returns
    -------
    ndarray, shape (n, n_p)
    """
    rng = np.random.default_rng([seed, 2])
    n_q, n_p = afm.n_q, afm.n_p
    max_fixed = max(n_p - 1, 1)  # fixing n_p actuators would leave no freedom
    kinds = rng.choice(3, size=n, p=COVERING_SHARES)
    kinds[0] = 0
    sobol = _sobol_in_polytope(afm, int(np.sum(kinds == 0)) + 1, seed)
    # balanced schedules: each actuator held / put at a limit equally often, in a shuffled order
    hold_cycle = np.concatenate([rng.permutation(n_q) for _ in range(n // max(n_q, 1) + 2)])
    face_cycle = np.concatenate([rng.permutation(2 * n_q) for _ in range(n // max(2 * n_q, 1) + 2)])
    K, lo, hi = afm.K, afm.lo, afm.hi
    out = np.zeros((n, n_p))
    u = np.zeros(n_p)  # the zero state
    k_sobol = k_hold = k_face = 0
    for k in range(n):
        new = None
        if kinds[k] == 1:  # hold one actuator (two in a third of the moves) still, random step
            held = [int(hold_cycle[k_hold])]
            k_hold += 1
            if max_fixed >= 2 and rng.random() < 1 / 3:
                held.append(int(rng.choice([i for i in range(n_q) if i != held[0]])))
            rows = np.array(held)
            target = _section_point(afm, rows, K[rows] @ u, rng)
            if target is not None:
                new = u + rng.uniform(0.0, 1.0) * (target - u)  # convex section: stays inside
        elif kinds[k] == 2:  # one actuator at a limit; in a third of them another held or at a limit
            code = int(face_cycle[k_face])
            k_face += 1
            i, at_hi = code % n_q, code >= n_q
            rows, vals = [i], [hi[i] if at_hi else lo[i]]
            if max_fixed >= 2 and rng.random() < 1 / 3:
                j = int(rng.choice([a for a in range(n_q) if a != i]))
                rows.append(j)
                vals.append(float(K[j] @ u) if rng.random() < 0.5 else (hi[j] if rng.random() < 0.5 else lo[j]))
            new = _section_point(afm, np.array(rows), np.array(vals), rng)
        if new is None:  # space-filling (or a section with no pose: fall back)
            new = sobol[min(k_sobol, len(sobol) - 1)]
            k_sobol += 1
        # round-off must not leave the ranges: the polytope check with the backends' tolerance
        if not afm.workspace.contains(new):
            new = sobol[min(k_sobol, len(sobol) - 1)]
            k_sobol += 1
        out[k] = new
        u = new
    return out


# --------------------------------------------------------------------------- face episodes


def face_episode_moves(afm: AnalyticForwardModel, n: int, rng: np.random.Generator,
                       episode_moves: int = 4, pool_size: int = 20000) -> np.ndarray:
    """Episodes: zero state, then poses on a face {K_i u = 0} in increasing AFM t order.

    Parameters
    ----------
    afm : AnalyticForwardModel
    n : int
        Total number of moves (returns included), >= 1.
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
