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
controller; targets, s_0 and an objective scale are parameters). The sum and the max are objects
(:mod:`microctl.control.sequence_objectives`, shared with the sequence oracle): "max" is written
with an epigraph variable z (``r_k <= z``) plus the cumulative r_e with weight
:data:`~microctl.control.sequence_objectives.MAX_TIE_WEIGHT`, which picks one plan among those
with the same worst move.

Global seeding (the problem is non-convex over each move's redundant set, and couples moves
through dq): dynamic programming over a grid of each step's redundant set
(:meth:`~microctl.control.surface.EAFMSurface.on_surface`, the single-move controller's seeding
grid, projected onto the EAFM-mean surface from a nominal previous state). The transition cost
from candidate i of step k-1 to candidate j of step k is r_e([t_{k-1}; K u_i], u_j), computed
for all pairs at once (:meth:`~microctl.control.objectives.PerMoveObjective.r_pairs`); the DP's best end
poses (grid local minima of the cost-to-arrive over the last step's grid) are back-tracked into
paths, and the best ``n_polish`` (within ``polish_ratio``) are polished by IPOPT. With T = 1 the
DP values are the single-move seeds, so the starts, and the optimum, are those of
:class:`~microctl.control.controller.OptimalController`.

Receding horizon: ``plan(targets[1:], state_after_move, u_init=previous_plan_u[1:])`` adds the
shifted previous plan (moved onto the new surfaces) as a start; by the principle of optimality
the tail of an optimal plan is optimal for the tail problem, so the warm start is (near) the
answer.

The controller holds what it uses (composition): the EAFM, the per-move objective
(:class:`~microctl.control.objectives.PerMoveObjective`), the sequence objective and the EAFM-mean
surface helpers (:class:`~microctl.control.surface.EAFMSurface`: Newton projection, seeding grid,
reachable interval, checks), the same ones :class:`~microctl.control.controller.EAFMController`
uses.

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
from dataclasses import replace

import casadi as ca
import numpy as np

from microctl.control.base import BaseController, unreachable
from microctl.control.ipopt import ipopt_options
from microctl.control.objectives import PerMoveObjective
from microctl.control.redundant import grid_local_minima
from microctl.control.result import ControlResult, SequenceResult
from microctl.control.settings import ControllerSettings
from microctl.control.surface import EAFMSurface
from microctl.errors import ConfigError, SolveError, UnreachableTargetError
from microctl.models.eafm import EAFM
from microctl.util.blas import single_thread_blas

__all__ = ["SequenceController", "SequenceResult"]


class SequenceController(BaseController):
    """Sequence-optimal control over a target list (module docstring) with the EAFM.

    Parameters
    ----------
    eafm : EAFM
    settings : ControllerSettings, optional
        ``r_e``, ``kappa``, ``epistemic`` choose r_e (:meth:`ControllerSettings.objective`);
        ``sequence_objective`` the sum or the worst move (:meth:`ControllerSettings.sequence`);
        the seeding/polish/check settings as the single-move controller's.
    objective : PerMoveObjective, optional
        The per-move objective instead of the one the settings describe.

    Attributes
    ----------
    eafm : EAFM
    objective : PerMoveObjective
    sequence_objective : SequenceObjective
    surface : EAFMSurface
        Newton projection, seeding grid, reachable interval and checks on the EAFM-mean surface.

    Notes
    -----
    Satisfies the :class:`~microctl.control.result.Controller` protocol: :meth:`solve` is the
    plan of one target (T = 1), the paper's eq. 4.
    """

    name = "eafm_sequence"

    def __init__(self, eafm: EAFM, settings: ControllerSettings | None = None,
                 objective: PerMoveObjective | None = None):
        super().__init__(eafm.afm, settings)
        objective = self.settings.objective() if objective is None else objective
        if not isinstance(objective, PerMoveObjective):
            raise ConfigError("objective must provide name, needs, mx(), evaluate(), r_mx(), r_np() and r_pairs(); "
                              f"got {type(objective).__name__}")
        self.eafm = eafm
        self.objective = objective
        self.sequence_objective = self.settings.sequence()
        self.surface = EAFMSurface(eafm, self.settings, self.name)
        self._nlps: dict[int, tuple[ca.Function, ca.Function]] = {}

    # ---- NLP -------------------------------------------------------------------------
    def _nlp(self, T: int) -> tuple[ca.Function, ca.Function]:
        """IPOPT solver and plan function of horizon T (built once per T).

        Solver: x = [u_1; ..; u_T] (+ the sequence objective's variables, z for "max"),
        p = [t_d (T); s_0 (n_s); J_ref], g = [t_mean_k - t_k (T); K u_k (T n_q)] (+ its
        constraints, r_k / J_ref - z (T) for "max").
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
        x, f, extra = self.sequence_objective.nlp(x_u, r_all, jref, T)
        g = [tm_all - td, *q, *extra]
        nlp = {"x": x, "p": ca.vertcat(td, s0, jref), "f": f, "g": ca.vertcat(*g)}
        solver = ca.nlpsol(f"eafm_sequence_{T}_ipopt", "ipopt", nlp, ipopt_options(self.settings))
        self.n_builds += 1
        self._nlps[T] = (solver, fun)
        return self._nlps[T]

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
        return self._walk(s0, targets, U, self.surface.refine)

    def _project_path(self, s0: np.ndarray, targets: np.ndarray, U: np.ndarray) -> np.ndarray | None:
        """Move each pose of a path onto its surface from the path's own previous state (Newton
        along w, in order); None when a pose then lies outside the ranges or off the surface."""
        def project(s: np.ndarray, u: np.ndarray, t: float) -> np.ndarray | None:
            Un, res = self.surface.newton(s, u[None, :], t)
            return None if res[0] > 1e-6 * max(1.0, abs(t)) or not self.surface.in_range(Un[0]) else Un[0]

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
        seq = self.sequence_objective
        Vm = np.zeros(1)     # DP labels of the previous step's candidates: worst move so far
        Vs = np.zeros(1)     # and cumulative r_e
        prev_S = s0[None, :]
        for k in range(T):
            t = float(targets[k])
            Un, idx, shape = self.surface.on_surface(s_nom, t, cfg.grid)
            if idx.size == 0:
                lo, hi = self.surface.reachable_interval(s_nom)
                if not (lo - cfg.constraint_tol <= t <= hi + cfg.constraint_tol):
                    raise UnreachableTargetError(f"step {k + 1} of {T}: {unreachable(t, s_nom, 'EAFM', lo, hi)}")
                Un, idx, shape = self.surface.on_surface(s_nom, t, 4 * cfg.grid)  # the grid missed a thin section
                if idx.size == 0:
                    raise SolveError(f"step {k + 1} of {T}: no seed reaches target {t:g} µm inside the ranges")
            Uk = Un[idx]
            C = self.objective.r_pairs(self.eafm, prev_S, Uk, seeding=True)  # (m_{k-1}, m_k) transition costs
            M = np.maximum(Vm[:, None], C)  # labels of arriving at candidate j from predecessor i
            Ssum = Vs[:, None] + C
            b = seq.predecessor(M, Ssum)
            cols = np.arange(C.shape[1])
            Vm, Vs = M[b, cols], Ssum[b, cols]
            score = seq.score(Vm, Vs, T)
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
        mins = grid_local_minima(value_grid, shape)
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
                    best = (self.sequence_objective.value(r), path, f"{status}; fallback to seed",
                            float(value_grid[i]), False, r)
                    break
        if best is None:
            raise SolveError(f"no valid command sequence for targets {targets.tolist()} µm (IPOPT: {status})")
        _, U, st, seed_value, warm_used, r = best
        S = self._states(s0, targets, U)
        dt = time.perf_counter() - t0
        steps = tuple(replace(self._result(S[k], float(targets[k]), U[k], st, success, attempts, t0), solve_time_s=dt)
                      for k in range(T))
        return SequenceResult(
            steps=steps, targets_um=tuple(float(t) for t in targets),
            sequence_objective=self.sequence_objective.name, r_e_um2=r,
            total_r_e_um2=float(np.sum(r)), worst_r_e_um2=float(np.max(r)), seed_total_r_e_um2=seed_value,
            status=st, success=success, iterations=int(attempts["iter"]), n_starts=int(attempts["n"]),
            warm_started=bool(warm_used), solve_time_s=dt)

    def _result(self, s: np.ndarray, target: float, u: np.ndarray, status: str, success: bool, attempts: dict,
                t0: float) -> ControlResult:
        """The step result of the command u from s (eq. 4 of the move as its ``objective``)."""
        objective = float(self.objective.evaluate(self.eafm, s, u[None, :])[0])
        return self.surface.result(self.name, s, target, u, objective, status, success, attempts, t0)

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
        seq = self.sequence_objective
        lbx, ubx, lbg, ubg = seq.bounds(lbx, ubx, lbg, ubg, T)
        best: tuple[float, np.ndarray, str, float, bool, np.ndarray] | None = None
        for U0, warm in starts:
            r0 = self._plan_r(s0, targets, U0)
            jref = seq.scale(r0)
            jref = jref if jref > 1e-300 else 1.0
            x0 = seq.x0(U0.ravel(), r0, jref)
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
            v = seq.value(r)
            if best is None or v < best[0]:
                best = (v, U, st["status"], seq.value(r0), warm, r)
        return best
