"""Refinement: training moves chosen by the trained model, where it is least sure of the optimum.

A designed log (``microctl collect``, :mod:`microctl.measurement.design`) spreads its moves over
the workspace without knowing where the controller will go. The poses eq. 4 picks are the quiet
ones, and the quiet pose is often a move the design hardly makes: a pure lift of every actuator
on a stage whose hinge slips with the platform's rotation, a small step of an actuator whose
stiction breaks away past a threshold. There the noise floor and the sources that decide the
choice are extrapolated, and the model can rank the poses wrongly and state a repeatability the
stage does not have. Refinement executes the moves the controller would consider: episodes from
the zero state to random targets (sorted, as the incremental experiment of IV-D climbs), and
for each target, among the candidate optimal poses of the redundant set (the local minima of
the controller's objective within :data:`EXPLORE_RATIO` of the best) and the controller's own
choice, the pose whose predicted log noise variance is least certain
(:meth:`microctl.models.eafm.EAFM.noise_uncertainty`: g's variance plus the noise parameters'
variance). The model is then trained again on everything.

The moves are a generator: each is computed from the stage's state after the previous one was
executed, so whoever executes them (``microctl collect --refine``, the experiments' training,
``scripts/bench_rigs.py``) logs them as it logs designed moves. For a model that reads the move's
context (a reversal source, :mod:`microctl.control.context`) each move is planned with each
actuator's last direction of motion, tracked from the commands the generator has yielded (the
stage's history before the first is unknown: one move from the zero state to where it stands,
:func:`microctl.models.direction.at_commands`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Iterator

import numpy as np

from microctl.control.context import ByDirection
from microctl.control.controller import ControllerSettings, OptimalController
from microctl.errors import ConfigError, SolveError
from microctl.models import direction as directions
from microctl.models.eafm import EAFM

__all__ = ["RefineMove", "REFINE_STRATEGIES", "EXPLORE_RATIO", "EPISODE_TARGETS", "ROUND_MOVES", "REFINE_SHARE",
           "explore", "refinement_moves", "refinement_commands", "check_target_range", "learning_rounds"]

#: ``uncertainty``: the least certain candidate optimum (default); ``on_policy``: the controller's choice.
REFINE_STRATEGIES = ("uncertainty", "on_policy")
#: Candidate optima within this factor of the best objective are explored.
EXPLORE_RATIO = 2.0
#: Targets per episode from the zero state (the incremental experiment's four).
EPISODE_TARGETS = 4
#: Learning a stage (``microctl learn``, :func:`microctl.api.learn`): refinement rounds of this many
#: moves, as many as fit in :data:`REFINE_SHARE` of the moves (1 round of 125 moves, 2 of 200);
#: the rest is the designed log the first model is trained on.
ROUND_MOVES, REFINE_SHARE = 40, 0.4


def learning_rounds(n_moves: int) -> int:
    """Refinement rounds of :data:`ROUND_MOVES` moves in a learning run of ``n_moves`` moves in all."""
    return int(REFINE_SHARE * n_moves) // ROUND_MOVES


@dataclass(frozen=True)
class RefineMove:
    """One refinement move.

    Attributes
    ----------
    u : ndarray, shape (n_p,)
        The command.
    target_um : float
        The episode's target (0 for the return to the zero state).
    label : str
        ``"zero"`` (the return to the zero state that starts an episode), ``"eafm"`` (the
        controller's choice) or ``"explore"`` (a less certain candidate optimum).
    """

    u: np.ndarray
    target_um: float
    label: str


def explore(ctrl: OptimalController, eafm: EAFM, target_um: float, s: np.ndarray, u_opt: np.ndarray
            ) -> tuple[np.ndarray, str]:
    """The refinement pose for one target: among the candidate optimal poses (grid local minima
    within :data:`EXPLORE_RATIO` of the best objective) and the controller's choice ``u_opt``,
    the one whose noise prediction is least certain.

    Returns
    -------
    u : ndarray, shape (n_p,)
    label : str
        ``"explore"`` for a candidate, ``"eafm"`` when it is the controller's choice.
    """
    U, _ = ctrl.candidates(target_um, s, max_ratio=EXPLORE_RATIO)
    U = np.vstack([u_opt[None, :], U])
    unc = eafm.noise_uncertainty(s, U)
    k = int(np.argmax(unc))
    return (U[k], "explore") if k > 0 and unc[k] > unc[0] else (u_opt, "eafm")


def check_target_range(eafm, target_range_um, where: str) -> tuple[float, float]:
    """``target_range_um`` as (lo, hi) inside the AFM's reachable range; None gives that range.

    ``eafm`` is the model (an EAFM, whose AFM is read) or the AnalyticForwardModel itself.

    Raises
    ------
    ConfigError
        Naming ``where`` and the reachable range, for a range that is not lo < hi inside it.
    """
    lo_r, hi_r = (eafm.afm if isinstance(eafm, EAFM) else eafm).t_range()
    if target_range_um is None:
        return float(lo_r), float(hi_r)
    lo, hi = (float(v) for v in target_range_um)
    if not (np.isfinite(lo) and np.isfinite(hi) and lo < hi):
        raise ConfigError(f"{where}: expected LO,HI with LO < HI (µm), got {lo:g},{hi:g}")
    if lo < lo_r or hi > hi_r:
        raise ConfigError(f"{where}: {lo:g},{hi:g} µm is not inside the stage's reachable range "
                          f"{lo_r:.6g},{hi_r:.6g} µm")
    return lo, hi


def refinement_moves(controllers: ByDirection, n_moves: int, target_range_um: tuple[float, float],
                     rng: np.random.Generator, state: Callable[[], np.ndarray], *,
                     episode_targets: int = EPISODE_TARGETS, strategy: str = "uncertainty") -> Iterator[RefineMove]:
    """``n_moves`` refinement moves (module docstring), each computed when it is asked for.

    Parameters
    ----------
    controllers : ByDirection
        The trained model's controller for each direction of the actuators' last motion
        (``controllers.eafm`` is the model).
    n_moves : int
        Moves to yield, the returns to the zero state included.
    target_range_um : (float, float)
        Targets are drawn uniformly from it, ``episode_targets`` per episode, sorted.
    rng : numpy.random.Generator
        Draws the targets.
    state : callable
        ``state() -> s``, shape (n_s,) = [t_prev, q_prev (n_q)]: the stage's state now (after
        the moves yielded so far were executed).
    episode_targets : int
    strategy : {"uncertainty", "on_policy"}

    Yields
    ------
    RefineMove
        A target whose solve fails is skipped (the next one of the episode follows).
    """
    if strategy not in REFINE_STRATEGIES:
        raise ConfigError(f"refinement strategy: expected one of {', '.join(REFINE_STRATEGIES)}, got {strategy!r}")
    afm = controllers.eafm.afm
    lo, hi = target_range_um
    done, last = 0, None
    while done < n_moves:
        zero = np.zeros(afm.n_p)
        q_before = np.asarray(state(), dtype=float)[1:]
        last = directions.at_commands(q_before) if last is None else last
        yield RefineMove(zero, 0.0, "zero")
        last = directions.after_move(last, q_before, afm.q_of(zero))
        done += 1
        prev_u = None
        for target in np.sort(rng.uniform(lo, hi, episode_targets)):
            if done >= n_moves:
                break
            s = np.asarray(state(), dtype=float)
            ctrl = controllers(last)
            try:
                res = ctrl.solve(float(target), s, u_init=prev_u)
            except SolveError:
                continue
            u, label = res.u, "eafm"
            if strategy == "uncertainty":
                u, label = explore(ctrl, controllers.eafm.with_direction(last), float(target), s, res.u)
            yield RefineMove(u, float(target), label)
            last = directions.after_move(last, s[1:], afm.q_of(u))
            prev_u = u
            done += 1


def refinement_commands(eafm: EAFM, n_moves: int, target_range_um: tuple[float, float], seed,
                        state: Callable[[], np.ndarray], settings: ControllerSettings | None = None
                        ) -> Iterator[np.ndarray]:
    """The commands u, shape (n_p,), of :func:`refinement_moves` with ``eafm``'s optimal controller
    (``settings``, default the package's) and the targets drawn by ``numpy.random.default_rng(seed)``:
    what an executor (``microctl collect --refine``, ``api.refine``, ``scripts/bench_rigs.py``)
    hands to :func:`microctl.backends.collect.run_collect`."""
    controllers = ByDirection(eafm, lambda e: OptimalController(e, settings))
    return (mv.u for mv in refinement_moves(controllers, n_moves, target_range_um, np.random.default_rng(seed), state))
