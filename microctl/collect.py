"""Space-filling training moves (paper IV-A: 125 control signals evenly covering the workspace).

Design:

1. **Points.** A scrambled Sobol sequence (``scipy.stats.qmc.Sobol``, seeded) in the
   bounding box of the workspace polytope {u : lo ≤ K u ≤ hi}; points outside the polytope
   are dropped, in sequence order, until ``n`` are kept. Keeping a prefix-filtered Sobol
   sequence preserves its low discrepancy inside the polytope (rejection of a
   uniform-in-box low-discrepancy set is low-discrepancy in the accepted region).
2. **Order.** The previous state matters to the model (g_e(s, u), eq. 3), so consecutive
   moves should not be near each other: the points are put in a seeded random order, then
   a repair pass swaps any move that lies within a quarter of the median inter-point
   distance (in actuator space, µm) of its predecessor with the first later point that
   is far enough from both neighbours. Pairs (s_prev, u) so spread over the product space.
   The first move starts from the zero state.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy.stats import qmc

from microctl.afm import AnalyticForwardModel
from microctl.backends.base import StageBackend
from microctl.errors import BackendError, SolveError
from microctl.measurement_log import MeasurementLogWriter
from microctl.progress import Progress

#: Consecutive moves closer than this fraction of the median inter-point distance are re-ordered.
MIN_STEP_FRACTION = 0.25


def space_filling_moves(afm: AnalyticForwardModel, n: int, seed: int = 0) -> np.ndarray:
    """``n`` control signals filling the workspace polytope, in a state-spreading order.

    Parameters
    ----------
    afm : AnalyticForwardModel
        Gives the polytope (``afm.workspace``) and K.
    n : int
        Number of moves (≥ 1).
    seed : int
        Seed of the Sobol scrambling and of the order.

    Returns
    -------
    ndarray, shape (n, n_p)
    """
    if n < 1:
        raise SolveError(f"the number of moves must be at least 1, got {n}")
    ws = afm.workspace
    n_p = ws.u_lo.size
    sobol = qmc.Sobol(d=n_p, scramble=True, seed=np.random.default_rng(seed))
    kept: list[np.ndarray] = []
    have = 0
    for _ in range(64):
        z = sobol.random_base2(m=max(int(np.ceil(np.log2(max(4 * n, 16)))), 4))
        u = ws.map_unit(z)
        ok = u[ws.contains(u)]
        kept.append(ok)
        have += len(ok)
        if have >= n:
            break
    else:
        raise SolveError("the workspace polytope is too thin to fill from its bounding box")
    pts = np.vstack(kept)[:n]
    return _spread_order(pts, afm.K, np.random.default_rng([seed, 1]))


def _spread_order(u: np.ndarray, K: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    n = len(u)
    order = rng.permutation(n)
    if n < 3:
        return u[order]
    q = u @ K.T
    dist = np.linalg.norm(q[:, None, :] - q[None, :, :], axis=-1)
    min_step = MIN_STEP_FRACTION * np.median(dist[np.triu_indices(n, 1)])
    order = list(order)
    for k in range(1, n):
        if dist[order[k - 1], order[k]] >= min_step:
            continue
        for j in range(k + 1, n):
            nxt = order[k + 1] if k + 1 < n and k + 1 != j else None
            if dist[order[k - 1], order[j]] >= min_step and (nxt is None or dist[order[j], nxt] >= min_step):
                order[k], order[j] = order[j], order[k]
                break
    return u[np.array(order)]


def run_collect(
    backend: StageBackend,
    moves: np.ndarray,
    out: str | Path,
    *,
    quiet: bool = False,
) -> int:
    """Execute moves on a backend, writing the measurement log row by row.

    Parameters
    ----------
    backend : StageBackend
    moves : ndarray, shape (n, n_p)
    out : path
        The log file (overwritten).
    quiet : bool
        Hide progress on stderr.

    Returns
    -------
    int
        Number of completed moves (all of them).

    Raises
    ------
    BackendError
        From a failed move; the log keeps every move completed before it, and the message
        says how many.
    """
    moves = np.atleast_2d(moves)
    with MeasurementLogWriter(out, backend.stage) as log, Progress(len(moves), "collect", quiet=quiet) as prog:
        for k, u in enumerate(moves):
            s_prev = backend.state
            try:
                m = backend.move(u)
            except BackendError as exc:
                raise BackendError(
                    f"move {k + 1} of {len(moves)} failed: {exc}; {out} keeps the {k} completed moves"
                ) from None
            log.write(m, s_prev, seq=k)
            prog.step(info=f"t = {m.t_um:.3f} µm")
    return len(moves)
