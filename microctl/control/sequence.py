"""Sequence-optimal control: the paper's future work ("an optimal control policy minimizing the
expected cumulative variance") as one multi-stage CasADi NLP.

The paper's controller (eq. 4, :class:`~microctl.control.controller.OptimalController`) chooses each
move on its own. The noise of a move depends on where the previous move left the actuators
(the physical noise model, ``noise_prior`` eq. 1: stick-slip std ∝ |dq_i|, ``dq_i = K_i u -
q_i,prev``, eq. 12), so the per-move optimum can leave no quiet way to the next target (an
actuator kept still at 7 µm that must then make the whole move to 14 µm). Given the state s_0
and targets t_1..t_T, :class:`SequenceController` solves

    min_{u_1..u_T}  sum_k r_e(s_{k-1}, u_k)         (sequence_objective "sum": the cumulative
                                                     noise variance, µm²)
               or   max_k r_e(s_{k-1}, u_k)         ("max": the worst move's)
    s.t.  t_mean(s_{k-1}, u_k) = t_k,   lo <= K u_k <= hi,   k = 1..T               (eq. 1, 12)
          s_k = [t_k; K u_k]

with r_e the noise summary of eq. 4 (:class:`~microctl.control.objectives.NoiseVariance`, the same
objects and settings as the single-move controller; 1 - exp(-r) of eq. 4 is monotone, so T = 1
is the paper's problem) and the EAFM mean as the constraint (eq. 1, GP input x = [s_{k-1}; u_k],
eq. 3). The state's pose part is the target: a feasible plan predicts the pose equal to it.

One NLP per horizon T (``nlpsol``/IPOPT, exact Hessian from CasADi's AD, built once per T and
controller; targets, s_0 and an objective scale are parameters). "max" is written with an
epigraph variable z (``r_k <= z``) plus the cumulative r_e with weight :data:`MAX_TIE_WEIGHT`,
which picks one plan among those with the same worst move.

Global seeding (the problem is non-convex over each move's redundant set, and couples moves
through dq): dynamic programming over a grid of each step's redundant set
(:meth:`~microctl.control.controller.EAFMController._on_surface`, the single-move controller's seeding
grid, projected onto the EAFM-mean surface from a nominal previous state). The transition cost
from candidate i of step k-1 to candidate j of step k is r_e([t_{k-1}; K u_i], u_j), computed
for all pairs at once (:meth:`~microctl.control.objectives.NoiseVariance.r_pairs`); the DP's best end
poses (grid local minima of the cost-to-arrive over the last step's grid) are back-tracked into
paths, and the best ``n_polish`` (within ``polish_ratio``) are polished by IPOPT. With T = 1 the
DP values are the single-move seeds, so the starts, and the optimum, are those of
:class:`~microctl.control.controller.OptimalController`.

Receding horizon: ``plan(targets[1:], state_after_move, u_init=previous_plan_u[1:])`` adds the
shifted previous plan (moved onto the new surfaces) as a start; by the principle of optimality
the tail of an optimal plan is optimal for the tail problem, so the warm start is (near) the
answer.

Checks on every returned command, as the other controllers: step by step, ``|t_mean(s_{k-1},
u_k) - t_k| <= constraint_tol`` (NumPy reference; a Newton correction along w first if needed)
and ``lo - range_tol <= K u_k <= hi + range_tol``; q clipped into the ranges. When IPOPT fails
on every start, the best seed path passing the checks is returned (``success=False``, status
``"<IPOPT status>; fallback to seed"``) or SolveError raised; a target no pose reaches raises
UnreachableTargetError naming the step.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, replace

import casadi as ca
import numpy as np

from microctl.control.controller import (
    ControllerSettings,
    ControlResult,
    EAFMController,
    _grid_local_minima,
    _ipopt_options,
    _unreachable,
)
from microctl.errors import ConfigError, SolveError, UnreachableTargetError
from microctl.models.eafm import EAFM
from microctl.util.blas import single_thread_blas

__all__ = ["SequenceController", "SequenceResult", "MAX_TIE_WEIGHT"]

#: Weight of the cumulative r_e (per move) added to the worst move's r_e with
#: ``sequence_objective = "max"``: among plans with the same worst move, the quietest overall.
MAX_TIE_WEIGHT = 1e-3


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
        ``"sum"`` or ``"max"``.
    r_e_um2 : ndarray, shape (T,)
        r_e of each move (µm²), the quantity summed (or maximised).
    total_r_e_um2, worst_r_e_um2 : float
        Their sum and maximum.
    seed_total_r_e_um2 : float
        The DP seed's value of the chosen start (its objective before the polish).
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


class SequenceController(EAFMController):
    """Sequence-optimal control over a target list (module docstring) with the EAFM.

    Parameters
    ----------
    eafm : EAFM
    settings : ControllerSettings, optional
        ``r_e``, ``kappa``, ``epistemic`` choose r_e (:meth:`ControllerSettings.objective`);
        ``sequence_objective`` the sum or the worst move; the seeding/polish/check settings as
        the single-move controller's.

    Notes
    -----
    Satisfies the :class:`~microctl.control.controller.Controller` protocol: :meth:`solve` is the
    plan of one target (T = 1), the paper's eq. 4.
    """

    name = "eafm_sequence"

    def __init__(self, eafm: EAFM, settings: ControllerSettings | None = None):
        settings = settings or ControllerSettings()
        self._nlps: dict[int, tuple[ca.Function, ca.Function]] = {}
        super().__init__(eafm, settings.objective(), settings, name="eafm_sequence")
        self.mode = settings.sequence_objective

    def _build(self) -> None:
        """Nothing at construction: one multi-stage NLP per horizon T, built on first use."""

    # ---- NLP -------------------------------------------------------------------------
    def _nlp(self, T: int) -> tuple[ca.Function, ca.Function]:
        """IPOPT solver and plan function of horizon T (built once per T).

        Solver: x = [u_1; ..; u_T] (+ z for "max"), p = [t_d (T); s_0 (n_s); J_ref],
        g = [t_mean_k - t_k (T); K u_k (T n_q)] (+ r_k / J_ref - z (T)).
        Function ``eafm_sequence_T(u, t_d, s0) -> (r_e, t_mean)``: u (T n_p), t_d (T), s0 (n_s);
        r_e and t_mean of each move (T).
        """
        if T in self._nlps:
            return self._nlps[T]
        afm = self.afm
        n_p = afm.n_p
        x_u = ca.MX.sym("u", n_p * T)
        td = ca.MX.sym("t_d", T)
        s0 = ca.MX.sym("s0", afm.n_s)
        jref = ca.MX.sym("J_ref")
        Kdm = ca.DM(afm.K)
        s = s0
        r, tm, q = [], [], []
        for k in range(T):
            uk = x_u[k * n_p:(k + 1) * n_p]
            e = self.eafm.expressions(s, uk, self.objective.needs)  # eq. 1 with x = [s_{k-1}; u_k] (eq. 3)
            r.append(self.objective.r_mx(s, uk, e, afm.K))
            tm.append(e["t_mean"])
            qk = ca.mtimes(Kdm, uk)  # eq. 12
            q.append(qk)
            s = ca.vertcat(td[k], qk)  # s_k = [t_k; K u_k]
        r_all, tm_all = ca.vertcat(*r), ca.vertcat(*tm)
        fun = ca.Function(f"eafm_sequence_{T}", [x_u, td, s0], [r_all, tm_all], ["u", "t_d", "s0"],
                          ["r_e", "t_mean"])
        g = [tm_all - td, *q]
        if self.mode == "sum":
            x, f = x_u, ca.sum1(r_all) / jref
        else:
            z = ca.MX.sym("z")
            x = ca.vertcat(x_u, z)
            f = z + MAX_TIE_WEIGHT * ca.sum1(r_all) / (T * jref)
            g.append(r_all / jref - z)
        nlp = {"x": x, "p": ca.vertcat(td, s0, jref), "f": f, "g": ca.vertcat(*g)}
        solver = ca.nlpsol(f"eafm_sequence_{T}_ipopt", "ipopt", nlp, _ipopt_options(self.settings))
        self.n_builds += 1
        self._nlps[T] = (solver, fun)
        return self._nlps[T]

    def _value(self, r: np.ndarray) -> float:
        """The sequence objective of per-move r_e values (µm²)."""
        if self.mode == "sum":
            return float(np.sum(r))
        return float(np.max(r) + MAX_TIE_WEIGHT * np.mean(r))

    # ---- NumPy reference of a plan --------------------------------------------------
    def _states(self, s0: np.ndarray, targets: np.ndarray, U: np.ndarray) -> np.ndarray:
        """s_0..s_{T-1} of a plan, shape (T, n_s): s_k = [t_k; K u_k]."""
        S = np.empty((len(targets), self.afm.n_s))
        S[0] = s0
        if len(targets) > 1:
            S[1:, 0] = targets[:-1]
            S[1:, 1:] = U[:-1] @ self.afm.K.T
        return S

    def _plan_r(self, s0: np.ndarray, targets: np.ndarray, U: np.ndarray) -> np.ndarray:
        """r_e of each move of a plan (NumPy reference, exact), shape (T,)."""
        S = self._states(s0, targets, U)
        return np.array([self.objective.r_np(self.eafm, S[k], U[k][None, :])[0] for k in range(len(targets))])

    def _walk(self, s0: np.ndarray, targets: np.ndarray, U: np.ndarray, step) -> np.ndarray | None:
        """A copy of the path U with each pose replaced by ``step(s, u, t)`` from the path's own
        previous state s = [t_{k-1}; K u_{k-1}], in order; None as soon as a step returns None."""
        U = U.copy()
        s = s0
        for k, t in enumerate(targets):
            u = step(s, U[k], float(t))
            if u is None:
                return None
            U[k] = u
            s = np.concatenate([[t], self.afm.K @ u])
        return U

    def _refine_path(self, s0: np.ndarray, targets: np.ndarray, U: np.ndarray) -> np.ndarray | None:
        """Check each move in order (Newton along w if needed); None if one fails."""
        return self._walk(s0, targets, U, self._refine)

    def _project_path(self, s0: np.ndarray, targets: np.ndarray, U: np.ndarray) -> np.ndarray | None:
        """Move each pose of a path onto its surface from the path's own previous state (Newton
        along w, in order); None when a pose then lies outside the ranges or off the surface."""
        def project(s: np.ndarray, u: np.ndarray, t: float) -> np.ndarray | None:
            Un, res = self._newton(s, u[None, :], t)
            return None if res[0] > 1e-6 * max(1.0, abs(t)) or not self._in_range(Un[0]) else Un[0]

        return self._walk(s0, targets, U, project)

    # ---- seeding: dynamic programming over the redundant sets -------------------------
    def _dp(self, s0: np.ndarray, targets: np.ndarray) -> tuple[list[np.ndarray], np.ndarray, np.ndarray,
                                                                 tuple[int, ...], list[np.ndarray]]:
        """Dynamic programming over each step's seeding grid.

        Returns
        -------
        cand : list of ndarray, shape (m_k, n_p)
            Each step's candidate poses (in range, on the surface from the nominal state).
        value_grid : ndarray, shape (grid points of the last step,)
            Cost-to-arrive at each point of the last step's grid (inf: not a candidate).
        last_idx : ndarray of int
            Grid indices of the last step's candidates.
        shape : tuple of int
            The last step's grid shape.
        back : list of ndarray
            back[k][j]: the best predecessor (index into cand[k-1]) of candidate j of step k.

        Raises
        ------
        UnreachableTargetError
            A step's target lies outside what the EAFM reaches from its nominal previous state.
        """
        cfg = self.settings
        T = len(targets)
        s_nom = s0
        cand: list[np.ndarray] = []
        back: list[np.ndarray] = []
        V = np.zeros(1)      # cost-to-arrive of the previous step's candidates ("sum"), or
        Vm = np.zeros(1)     # worst move so far and cumulative ("max")
        Vs = np.zeros(1)
        prev_S = s0[None, :]
        for k in range(T):
            t = float(targets[k])
            Un, idx, shape = self._on_surface(s_nom, t, cfg.grid)
            if idx.size == 0:
                lo, hi = self.reachable_interval(s_nom)
                if not (lo - cfg.constraint_tol <= t <= hi + cfg.constraint_tol):
                    raise UnreachableTargetError(f"step {k + 1} of {T}: {_unreachable(t, s_nom, 'EAFM', lo, hi)}")
                Un, idx, shape = self._on_surface(s_nom, t, 4 * cfg.grid)  # the grid missed a thin section
                if idx.size == 0:
                    raise SolveError(f"step {k + 1} of {T}: no seed reaches target {t:g} µm inside the ranges")
            Uk = Un[idx]
            C = self.objective.r_pairs(self.eafm, prev_S, Uk, seeding=True)  # (m_{k-1}, m_k) transition costs
            if self.mode == "sum":
                tot = V[:, None] + C
                b = np.argmin(tot, axis=0)
                V = tot[b, np.arange(tot.shape[1])]
                score = V
            else:
                # exact minimax (the worst move so far); among predecessors with the same worst
                # move, the smaller cumulative r_e (a tie-break only: (max, sum) has no exact
                # one-label DP)
                M = np.maximum(Vm[:, None], C)
                Ssum = Vs[:, None] + C
                tie = M <= M.min(axis=0) * (1.0 + 1e-12)
                b = np.argmin(np.where(tie, Ssum, np.inf), axis=0)
                cols = np.arange(C.shape[1])
                Vm, Vs = M[b, cols], Ssum[b, cols]
                score = Vm + MAX_TIE_WEIGHT * Vs / T
            cand.append(Uk)
            back.append(b)
            best = int(np.argmin(score))
            # nominal state of the next step: the best arrival here (the EAFM mean depends on
            # the previous state only weakly; the polish enforces the exact constraint)
            s_nom = np.concatenate([[t], self.afm.K @ Uk[best]])
            prev_S = np.column_stack([np.full(Uk.shape[0], t), Uk @ self.afm.K.T])
        value_grid = np.full(Un.shape[0], np.inf)
        value_grid[idx] = score
        return cand, value_grid, idx, shape, back

    @staticmethod
    def _backtrack(cand: list[np.ndarray], back: list[np.ndarray], j: int) -> np.ndarray:
        """The DP path ending at candidate j of the last step, shape (T, n_p)."""
        T = len(cand)
        path = np.empty((T, cand[0].shape[1]))
        for k in range(T - 1, -1, -1):
            path[k] = cand[k][j]
            j = int(back[k][j])
        return path

    # ---- solve -----------------------------------------------------------------------
    def plan(self, targets_um, state: np.ndarray | None = None, *, u_init: np.ndarray | None = None
             ) -> SequenceResult:
        """The sequence-optimal commands for ``targets_um`` from ``state`` (module docstring).

        Parameters
        ----------
        targets_um : sequence of float, length T >= 1
        state : ndarray, shape (n_s,), optional
            s_0 = [t; q] before the first move (default the zero state).
        u_init : ndarray, shape (m, n_p) or (n_p,), optional
            Warm start, e.g. the previous plan without its executed first move (receding
            horizon): rows for the first m moves (m <= T; the DP's best path fills the rest),
            moved onto the surfaces in order and polished besides the global seeds.

        Returns
        -------
        SequenceResult

        Raises
        ------
        ConfigError
            A target that is not a finite number, an empty list, a bad state or u_init.
        UnreachableTargetError
            A target outside what the EAFM reaches (the message names the step and the interval).
        SolveError
            No command sequence passing the checks.
        """
        with single_thread_blas():
            return self._plan(targets_um, state, u_init, time.perf_counter())

    def solve(self, target_um: float, state: np.ndarray | None = None, *,
              u_init: np.ndarray | None = None) -> ControlResult:
        """The plan of one target (T = 1): eq. 4, as :class:`~microctl.control.controller.OptimalController`."""
        return self.plan([target_um], state, u_init=u_init).steps[0]

    def _targets(self, targets_um) -> np.ndarray:
        try:
            t = np.asarray(targets_um, dtype=float).reshape(-1)
        except (TypeError, ValueError):
            raise ConfigError(f"targets must be a list of numbers of µm, got {targets_um!r}") from None
        if t.size == 0:
            raise ConfigError("targets must list at least one target (µm), got none")
        for k, v in enumerate(t):
            if not math.isfinite(v):
                raise ConfigError(f"targets[{k}] must be a finite number of µm, got {v!r}")
        return t

    def _plan(self, targets_um, state, u_init, t0: float) -> SequenceResult:
        cfg = self.settings
        s0 = self._state(state)
        targets = self._targets(targets_um)
        T = len(targets)
        n_p = self.afm.n_p
        cand, value_grid, last_idx, shape, back = self._dp(s0, targets)
        mins = _grid_local_minima(value_grid, shape)
        mins = mins[np.argsort(value_grid[mins])]
        # grid index of the last step -> candidate index
        pos = np.full(value_grid.size, -1)
        pos[last_idx] = np.arange(last_idx.size)
        starts: list[tuple[np.ndarray, bool]] = []
        if u_init is not None:
            W = np.atleast_2d(np.asarray(u_init, dtype=float))
            if W.shape[1] != n_p or W.shape[0] > T or not np.all(np.isfinite(W)):
                raise ConfigError(f"u_init must be up to {T} rows of {n_p} finite numbers (one per move), "
                                  f"got shape {W.shape}")
            path = self._backtrack(cand, back, int(pos[mins[0]])) if mins.size else np.repeat(W[-1:], T, axis=0)
            path[:W.shape[0]] = W
            warm = self._project_path(s0, targets, path)
            if warm is not None:
                starts.append((warm, True))
        best_seed = float(value_grid[mins[0]]) if mins.size else math.inf
        for i in mins[: cfg.n_polish]:
            if value_grid[i] <= cfg.polish_ratio * best_seed or not starts:
                starts.append((self._backtrack(cand, back, int(pos[i])), False))
        attempts = {"status": [], "iter": 0, "n": 0}
        best = self._polish(s0, targets, starts, attempts)
        if best is None and mins.size > cfg.n_polish:
            more = [(self._backtrack(cand, back, int(pos[i])), False) for i in mins[cfg.n_polish: 3 * cfg.n_polish]]
            best = self._polish(s0, targets, more, attempts)
        status = "; ".join(sorted(set(attempts["status"]))) or "no start"
        success = best is not None
        if best is None:
            # IPOPT failed everywhere: the best seed path passing the checks, never a command
            # outside the ranges or off a target
            for i in mins[: 3 * cfg.n_polish]:
                path = self._refine_path(s0, targets, self._backtrack(cand, back, int(pos[i])))
                if path is not None:
                    r = self._plan_r(s0, targets, path)
                    best = (self._value(r), path, f"{status}; fallback to seed", float(value_grid[i]), False, r)
                    break
        if best is None:
            raise SolveError(f"no valid command sequence for targets {targets.tolist()} µm (IPOPT: {status})")
        _, U, st, seed_value, warm_used, r = best
        S = self._states(s0, targets, U)
        self._last_attempts = attempts
        dt = time.perf_counter() - t0
        steps = tuple(replace(self._result(S[k], float(targets[k]), U[k], st, success, t0), solve_time_s=dt)
                      for k in range(T))
        return SequenceResult(
            steps=steps, targets_um=tuple(float(t) for t in targets), sequence_objective=self.mode, r_e_um2=r,
            total_r_e_um2=float(np.sum(r)), worst_r_e_um2=float(np.max(r)), seed_total_r_e_um2=seed_value,
            status=st, success=success, iterations=int(attempts["iter"]), n_starts=int(attempts["n"]),
            warm_started=bool(warm_used), solve_time_s=dt)

    def _polish(self, s0: np.ndarray, targets: np.ndarray, starts: list[tuple[np.ndarray, bool]],
                attempts: dict) -> tuple[float, np.ndarray, str, float, bool, np.ndarray] | None:
        """IPOPT from each start path; the best one passing the checks (value, U, status, seed,
        warm, r_e per move)."""
        T = len(targets)
        solver, _ = self._nlp(T)
        afm = self.afm
        lbx = np.tile(afm.workspace.u_lo, T)
        ubx = np.tile(afm.workspace.u_hi, T)
        lbg = np.concatenate([np.zeros(T), np.tile(afm.lo, T)])
        ubg = np.concatenate([np.zeros(T), np.tile(afm.hi, T)])
        if self.mode == "max":
            lbx, ubx = np.append(lbx, 0.0), np.append(ubx, np.inf)
            lbg, ubg = np.append(lbg, np.full(T, -np.inf)), np.append(ubg, np.zeros(T))
        best: tuple[float, np.ndarray, str, float, bool, np.ndarray] | None = None
        for U0, warm in starts:
            r0 = self._plan_r(s0, targets, U0)
            jref = float(np.sum(r0) if self.mode == "sum" else np.max(r0))
            jref = jref if jref > 1e-300 else 1.0
            x0 = U0.ravel()
            if self.mode == "max":
                x0 = np.append(x0, float(np.max(r0)) / jref)
            x, st = self._run(solver, x0, np.concatenate([targets, s0, [jref]]), lbx, ubx, lbg, ubg)
            attempts["status"].append(st["status"])
            attempts["iter"] += st["iter"]
            attempts["n"] += 1
            if not st["success"]:
                continue
            U = self._refine_path(s0, targets, x[: T * afm.n_p].reshape(T, afm.n_p))
            if U is None:
                continue
            r = self._plan_r(s0, targets, U)
            v = self._value(r)
            if best is None or v < best[0]:
                best = (v, U, st["status"], self._value(r0), warm, r)
        return best
