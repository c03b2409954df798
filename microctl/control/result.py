"""What a controller returns: :class:`ControlResult` (one move), :class:`SequenceResult` (a planned
sequence of moves) and :class:`NoiseComparison` (whether the chosen pose is credibly quieter
than a baseline's); the :class:`Controller` protocol every controller satisfies; and
:class:`MoveRecord`, one move a controller's result was executed with
(:class:`microctl.api.Operator`)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Protocol, runtime_checkable

import numpy as np

__all__ = ["Controller", "ControlResult", "SequenceResult", "NoiseComparison", "MoveRecord"]


@runtime_checkable
class Controller(Protocol):
    """What the experiments, the CLI and the benchmarks need of a controller."""

    name: str

    def solve(self, target_um: float, state: np.ndarray | None = None, *,
              u_init: np.ndarray | None = None) -> "ControlResult":
        """The control signal for ``target_um`` from ``state`` (default the zero state)."""
        ...




@dataclass(frozen=True)
class ControlResult:
    """The outcome of one ``solve``.

    Attributes
    ----------
    controller : str
        ``"eafm"``, ``"afm"`` or ``"eafm_mean"``.
    target_um : float
    state : ndarray, shape (n_s,)
        s = [t; q] the command was computed from.
    u : ndarray, shape (n_p,)
        Control signal (platform pose: µm, mrad, mrad).
    q : ndarray, shape (n_q,)
        Actuator commands K u (eq. 12), inside the ranges.
    predicted_um, predicted_std_um : float
        EAFM predictive mean and std of the tool pose at u (``std = sqrt(f_var +
        exp(g_mean + g_var/2))``); for the AFM controller without an EAFM to report with,
        the AFM prediction and NaN.
    objective : float
        The controller's own objective at u (eq. 4 for ``eafm``; ``||K u - q_prev||^2`` µm²
        for the baselines).
    status : str
        IPOPT return status of the accepted start (``"...; fallback to seed"`` on failure).
    iterations : int
        IPOPT iterations summed over all starts.
    solve_time_s : float
        Wall time of the whole call (seeding included).
    success : bool
        IPOPT converged on the returned command and all checks passed.
    constraint_residual : float
        ``|t_pred(u) - target|`` under the controller's constraint model (µm).
    n_starts : int
        IPOPT starts made.
    noise_std_um : float
        Predicted noise std at u, ``sqrt(E[exp(g)])`` (NaN without an EAFM).
    noise_upper_std_um : float
        Square root of the upper quantile ``exp(mu_g + kappa s_g)`` of the noise variance
        (``ControllerSettings.kappa``; NaN without an EAFM).
    bias_std_um : float
        Predicted uncertainty of the mean at u: ``sqrt(f_var)``, the posterior std of the mean
        correction (large where f extrapolates, e.g. a corner the training never visited); NaN
        without an EAFM. ``predicted_std_um`` combines it with the noise.
    hysteresis_um : float
        The hysteresis loop's part of ``predicted_um``: the reading shift the play states before
        the move give at u (:mod:`microctl.control.memory`); 0 without hysteresis corrections.
    choice : str
        The optimal controller's least-motion rule (``ControllerSettings.prefer_least_motion``,
        :mod:`microctl.control.credible`): which command was returned and why, e.g. ``"least
        motion: eq. 4's optimum better with P = 0.62 < 0.95"``; empty when the rule is off or for
        the other controllers.
    vs_baseline : NoiseComparison or None
        For the optimal controller given a baseline: is u credibly quieter than the
        baseline's command from the same state?
    baseline : ControlResult or None
        The baseline controller's result that ``vs_baseline`` compares with.
    """

    controller: str
    target_um: float
    state: np.ndarray
    u: np.ndarray
    q: np.ndarray
    predicted_um: float
    predicted_std_um: float
    objective: float
    status: str
    iterations: int
    solve_time_s: float
    success: bool
    constraint_residual: float
    n_starts: int
    noise_std_um: float = float("nan")
    noise_upper_std_um: float = float("nan")
    bias_std_um: float = float("nan")
    hysteresis_um: float = 0.0
    choice: str = ""
    vs_baseline: "NoiseComparison | None" = None
    baseline: "ControlResult | None" = None

    def to_dict(self, names: tuple[str, ...] | None = None) -> dict:
        """Plain-Python form; ``u`` as a dict when DoF ``names`` are given."""
        u = {n: float(v) for n, v in zip(names, self.u)} if names else [float(v) for v in self.u]
        return {
            "controller": self.controller, "target_um": self.target_um, "state": self.state.tolist(),
            "u": u, "q_um": self.q.tolist(), "predicted_um": self.predicted_um,
            "predicted_std_um": self.predicted_std_um, "objective": self.objective, "status": self.status,
            "iterations": self.iterations, "solve_time_s": self.solve_time_s, "success": self.success,
            "constraint_residual_um": self.constraint_residual, "n_starts": self.n_starts,
            "noise_std_um": self.noise_std_um, "noise_upper_std_um": self.noise_upper_std_um,
            "bias_std_um": self.bias_std_um, "hysteresis_um": self.hysteresis_um, "choice": self.choice,
            "vs_baseline": None if self.vs_baseline is None else self.vs_baseline.to_dict(),
        }



@dataclass(frozen=True)
class NoiseComparison:
    """Whether pose a is credibly quieter than pose b under the EAFM's noise posterior.

    Attributes
    ----------
    prob_quieter : float
        P(noise variance at a < at b) = P(g_a < g_b) with (g_a, g_b) jointly Gaussian under
        the posterior of g (correlation included).
    log_ratio_mean, log_ratio_std : float
        Mean and std of ``g_a - g_b`` (log of the variance ratio).
    credible : bool
        ``prob_quieter >= level``.
    level : float
    """

    prob_quieter: float
    log_ratio_mean: float
    log_ratio_std: float
    credible: bool
    level: float

    def to_dict(self) -> dict:
        return {"prob_quieter": self.prob_quieter, "log_ratio_mean": self.log_ratio_mean,
                "log_ratio_std": self.log_ratio_std, "credible": self.credible, "level": self.level}


@dataclass(frozen=True)
class SequenceResult:
    """A planned sequence of moves.

    Attributes
    ----------
    steps : tuple of ControlResult
        One per target, in order; step k's ``state`` is s_{k-1} (the given state for k = 1,
        then ``[t_{k-1}; q_{k-1}]``) and its ``objective`` eq. 4 of that move.
    targets_um : tuple of float
    sequence_objective : str
        The name of what was minimised (:mod:`microctl.control.sequence_objectives`), ``"sum"`` or ``"max"``.
    r_e_um2 : ndarray, shape (T,)
        r_e of each move (µm²), the quantity summed (or maximised); the true reading variance
        for the sequence oracle.
    total_r_e_um2, worst_r_e_um2 : float
        Their sum and maximum.
    seed_total_r_e_um2 : float
        The DP seed's value of the chosen start (its objective before the polish; the oracle's:
        before its zoom refinements).
    status : str
        IPOPT return status of the accepted start (``"...; fallback to seed"`` on failure).
    success : bool
    iterations : int
        IPOPT iterations summed over all starts.
    n_starts : int
        IPOPT starts made.
    warm_started : bool
        The returned plan was polished from ``u_init``.
    solve_time_s : float
        Wall time of the whole call (seeding included).
    """

    steps: tuple[ControlResult, ...]
    targets_um: tuple[float, ...]
    sequence_objective: str
    r_e_um2: np.ndarray
    total_r_e_um2: float
    worst_r_e_um2: float
    seed_total_r_e_um2: float
    status: str
    success: bool
    iterations: int
    n_starts: int
    warm_started: bool
    solve_time_s: float

    @property
    def u(self) -> np.ndarray:
        """The commands, shape (T, n_p)."""
        return np.vstack([r.u for r in self.steps])

    def to_dict(self, names: tuple[str, ...] | None = None) -> dict:
        """Plain-Python form (steps as :meth:`ControlResult.to_dict`)."""
        return {
            "targets_um": list(self.targets_um), "sequence_objective": self.sequence_objective,
            "r_e_um2": [float(v) for v in self.r_e_um2], "total_r_e_um2": self.total_r_e_um2,
            "worst_r_e_um2": self.worst_r_e_um2, "seed_total_r_e_um2": self.seed_total_r_e_um2,
            "status": self.status, "success": self.success, "iterations": self.iterations,
            "n_starts": self.n_starts, "warm_started": self.warm_started, "solve_time_s": self.solve_time_s,
            "steps": [r.to_dict(names) for r in self.steps],
        }


@dataclass(frozen=True)
class MoveRecord:
    """One executed move.

    Attributes
    ----------
    seq : int
        Its ``seq`` in the log (or the count of moves made, without a log).
    target_um : float
    state_before : ndarray, shape (n_s,)
        s = [t; q] the command was computed from (the backend's state).
    u : ndarray, shape (n_p,)
        The control signal sent.
    q_um : ndarray, shape (n_q,)
        The actuator commands sent (inside the configured ranges).
    predicted_um, predicted_std_um : float
        The EAFM's predicted pose and its predicted scatter (std) at the command.
    measured_um : float
        The gauge after the move.
    time_s : float
        When the move had settled (s since the backend's start).
    solution : ControlResult
    direction_before : ndarray, shape (n_q,), or None
        Each actuator's last direction of motion before the move (:mod:`microctl.models.direction`).
    """

    seq: int
    target_um: float
    state_before: np.ndarray
    u: np.ndarray
    q_um: np.ndarray
    predicted_um: float
    predicted_std_um: float
    measured_um: float
    time_s: float
    solution: ControlResult
    direction_before: np.ndarray | None = None

    @property
    def error_um(self) -> float:
        """measured - target, µm."""
        return self.measured_um - self.target_um

    def to_dict(self, stage: Any) -> dict:
        """Plain JSON-able form (what ``microctl move --json`` and ``serve`` print)."""
        return {
            "seq": self.seq, "target_um": self.target_um,
            "state_before": dict(zip(stage.state_names, map(float, self.state_before))),
            "u": dict(zip(stage.dof, map(float, self.u))), "q_um": self.q_um.tolist(),
            "predicted_um": self.predicted_um, "predicted_std_um": self.predicted_std_um,
            "measured_um": self.measured_um, "error_um": self.error_um, "time_s": self.time_s,
            "status": self.solution.status, "success": self.solution.success,
            "solve_time_s": self.solution.solve_time_s,
        }
