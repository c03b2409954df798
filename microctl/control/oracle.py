"""The oracle controller: eq. 4 solved against the simulator's true mean and variance.

On the simulated stage the noise-free expected reading ``true_mean(s, u)`` and the reading
variance ``true_var(s, u)`` of the next move are known
(:class:`~microctl.backends.simulated.SimulatedStage`). The oracle solves

    min_u  true_var(s, u)   s.t.  true_mean(s, u) = t_d,   lo <= K u <= hi

i.e. the paper's optimal control problem (eq. 4; 1 - exp(-r) is monotone in r) with the
learned g_e, r_e replaced by the truth: the best any learned model can do, the limit the
EAFM is measured against.

The truth is a black box (contact equilibrium, not a CasADi graph) and its variance has kinks
where an actuator stands still (stick-slip scatter ∝ |Δq_i|), so the search is direct:

1. candidates: a grid over the redundant set (null-space coordinates of the AFM tool map,
   :class:`~microctl.control.redundant.RedundantSet`), plus, for each actuator i, points on the line
   where it stands still (K_i u = q_prev,i) — the kinks;
2. each candidate is moved onto the true-mean surface by Newton steps along a direction that
   keeps the still actuator still (finite-difference slope), then checked for range;
3. the grid is refined ``zooms`` times around the best feasible candidate.

It has the controllers' interface: ``solve(target_um, state, u_init=None) -> ControlResult``;
:class:`OracleSequenceController` plans a target list on the truth and returns, as the EAFM
sequence controller, a :class:`~microctl.control.result.SequenceResult`.
"""

from __future__ import annotations

import math
import time

import numpy as np

from microctl.control.redundant import RedundantSet
from microctl.control.result import ControlResult, SequenceResult
from microctl.control.sequence_objectives import SEQUENCE_OBJECTIVES
from microctl.errors import SolveError
from microctl.models.afm import AnalyticForwardModel

__all__ = ["OracleController", "OracleSequenceController"]

_FD_STEP = 1e-4
#: Largest accepted |true_mean − target| of a returned command (µm).
_CONSTRAINT_TOL = 1e-6


class OracleController:
    """eq. 4 against the simulator's truth (see the module docstring).

    Parameters
    ----------
    afm : AnalyticForwardModel
        Gives K, the ranges and the redundant-set coordinates.
    stage : SimulatedStage
        The simulated stage whose ``true_mean`` / ``true_var`` are optimised; rebind with
        :meth:`bind` when the experiment opens a fresh stage.
    grid, line_points, zooms, newton_steps : int
        Search settings (:class:`~microctl.experiments.config.Oracle`).
    """

    name = "oracle"

    def __init__(self, afm: AnalyticForwardModel, stage, *, grid: int = 31, line_points: int = 61,
                 zooms: int = 2, newton_steps: int = 6):
        self.afm = afm
        self.stage = stage
        self.grid = int(grid)
        self.line_points = int(line_points)
        self.zooms = int(zooms)
        self.newton_steps = int(newton_steps)
        self.rset = RedundantSet(afm)

    def bind(self, stage) -> None:
        """Optimise against another simulated stage from now on."""
        self.stage = stage

    # ---- helpers -------------------------------------------------------------------
    def _mean(self, s: np.ndarray, U: np.ndarray) -> np.ndarray:
        return np.atleast_1d(np.asarray(self.stage.true_mean(s, U), dtype=float))

    def _var(self, s: np.ndarray, U: np.ndarray) -> np.ndarray:
        return np.atleast_1d(np.asarray(self.stage.true_var(s, U), dtype=float))

    def _project(self, s: np.ndarray, U: np.ndarray, D: np.ndarray, target: float) -> tuple[np.ndarray, np.ndarray]:
        """Newton along the rows of D onto true_mean = target; returns U and |residual|.

        Parameters
        ----------
        U, D : ndarray, shape (m, n_p)
        """
        U = U.copy()
        for _ in range(self.newton_steps):
            t = self._mean(s, U)
            slope = (self._mean(s, U + _FD_STEP * D) - t) / _FD_STEP
            slope = np.where(np.abs(slope) > 1e-9, slope, 1e-9)
            U += ((target - t) / slope)[:, None] * D
        return U, np.abs(self._mean(s, U) - target)

    def _in_range(self, U: np.ndarray, tol: float = 1e-9) -> np.ndarray:
        q = U @ self.afm.K.T
        return np.all((q >= self.afm.lo - tol) & (q <= self.afm.hi + tol), axis=1)

    def _feasible(self, s: np.ndarray, U: np.ndarray, D: np.ndarray, target: float) -> tuple[np.ndarray, np.ndarray]:
        """The rows of U moved (along the rows of D) onto true_mean(s, .) = target, and which of
        them reach it and lie in range (bool, shape (m,))."""
        U, res = self._project(s, U, D, target)
        return U, (res <= _CONSTRAINT_TOL * max(1.0, abs(target))) & self._in_range(U)

    def _zoom_grid(self, u: np.ndarray, step: np.ndarray) -> np.ndarray:
        """A 9 x 9 grid (null-space coordinates, ±2 ``step``) around the pose u, shape (81, n_p)."""
        rs = self.rset
        c0 = (u / rs.D) @ rs.N
        axes = [np.linspace(c - 2 * h, c + 2 * h, 9) for c, h in zip(c0, step)]
        C = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, rs.N.shape[1])
        return (C @ rs.N.T) * rs.D + (u / rs.D @ rs.v_hat) * rs.v_hat * rs.D

    def _evaluate(self, s: np.ndarray, U: np.ndarray, D: np.ndarray, target: float) -> tuple[np.ndarray, np.ndarray]:
        """Project candidates and score them; infeasible ones get +inf."""
        if U.shape[0] == 0:
            return U, np.zeros(0)
        U, ok = self._feasible(s, U, D, target)
        obj = np.full(U.shape[0], np.inf)
        if np.any(ok):
            obj[ok] = self._var(s, U[ok])
        return U, obj

    def _still_lines(self, s: np.ndarray, target: float, n: int, box: tuple[np.ndarray, np.ndarray] | None
                     ) -> tuple[np.ndarray, np.ndarray]:
        """Candidates with one actuator still (K_i u = q_prev,i) and their Newton directions."""
        K, rs = self.afm.K, self.rset
        d = rs.d_of_target(target)
        Us, Ds = [], []
        for i in range(self.afm.n_q):
            Ki = K[i]
            # direction keeping actuator i still that changes the tool pose: dir_u minus its K_i part
            Dn = rs.dir_u - (Ki @ rs.dir_u) / (Ki @ Ki) * Ki
            if abs(rs.w @ Dn) < 1e-9 * np.linalg.norm(rs.w) * max(np.linalg.norm(Dn), 1e-300):
                continue
            # the line {w·u = d, K_i u = q_prev,i}: a point on it and its direction
            A = np.vstack([rs.w, Ki])
            u0 = np.linalg.lstsq(A, np.array([d, s[1 + i]]), rcond=None)[0]
            _, _, Vt = np.linalg.svd(A)
            e = Vt[-1]
            # extent along e: crossings of the line with the workspace slab constraints
            q0, qe = K @ u0, K @ e
            with np.errstate(divide="ignore", invalid="ignore"):
                a = (self.afm.lo - q0) / qe
                b = (self.afm.hi - q0) / qe
            lo = np.where(qe > 1e-12, a, np.where(qe < -1e-12, b, -np.inf))
            hi = np.where(qe > 1e-12, b, np.where(qe < -1e-12, a, np.inf))
            lam_lo, lam_hi = float(np.max(lo)), float(np.min(hi))
            if not (np.isfinite(lam_lo) and np.isfinite(lam_hi)) or lam_hi < lam_lo:
                # the AFM plane misses this actuator's still line inside the ranges: widen a little
                span = float(np.max(self.afm.hi - self.afm.lo))
                lam_lo, lam_hi = -span, span
            pad = 0.05 * max(lam_hi - lam_lo, 1e-6)
            lam = np.linspace(lam_lo - pad, lam_hi + pad, n)
            Us.append(u0[None, :] + lam[:, None] * e[None, :])
            Ds.append(np.repeat(Dn[None, :], n, axis=0))
        if not Us:
            return np.zeros((0, self.afm.n_p)), np.zeros((0, self.afm.n_p))
        return np.vstack(Us), np.vstack(Ds)

    # ---- solve ---------------------------------------------------------------------
    def solve(self, target_um: float, state: np.ndarray | None = None, *,
              u_init: np.ndarray | None = None) -> ControlResult:
        """The truly variance-optimal command for ``target_um`` from ``state``.

        Parameters
        ----------
        target_um : float
        state : ndarray, shape (n_s,), optional
            s = [t; q] (default zero state).
        u_init : ndarray, shape (n_p,), optional
            An extra candidate (e.g. the previous command).

        Returns
        -------
        ControlResult
            ``predicted_um`` / ``predicted_std_um`` are the true mean and std at u.

        Raises
        ------
        SolveError
            No candidate reaches the target inside the ranges.
        """
        t0 = time.perf_counter()
        target = float(target_um)
        s = self.afm.zero_state() if state is None else np.asarray(state, dtype=float).reshape(-1)
        rs = self.rset
        U, _ = rs.grid(target, self.grid)
        D = np.repeat(rs.dir_u[None, :], U.shape[0], axis=0)
        Ul, Dl = self._still_lines(s, target, self.line_points, None)
        U, D = np.vstack([U, Ul]), np.vstack([D, Dl])
        if u_init is not None:
            U = np.vstack([U, np.asarray(u_init, dtype=float).reshape(1, -1)])
            D = np.vstack([D, rs.dir_u[None, :]])
        U, obj = self._evaluate(s, U, D, target)
        if not np.any(np.isfinite(obj)):
            raise SolveError(f"oracle: no command reaches {target:g} µm inside the actuator ranges from state "
                             f"[{', '.join(f'{v:g}' for v in s)}]")
        # zoom: a finer grid (in null-space coordinates) around the best candidate, same direction rules
        N = rs.N
        step = np.max(np.abs((U[np.isfinite(obj)] / rs.D) @ N), axis=0) / max(self.grid - 1, 1) * 2.0
        for _ in range(self.zooms):
            k = int(np.argmin(obj))
            Uz = self._zoom_grid(U[k], step)
            Dz = np.repeat(rs.dir_u[None, :], Uz.shape[0], axis=0)
            # keep the best candidate's own direction too (it may be a still-actuator point)
            Uz2, obj2 = self._evaluate(s, Uz, Dz, target)
            U, obj = np.vstack([U, Uz2]), np.concatenate([obj, obj2])
            step = step / 2.0
        k = int(np.argmin(obj))
        u = U[k]
        mean = float(self._mean(s, u[None, :])[0])
        var = float(obj[k])
        q = np.clip(self.afm.K @ u, self.afm.lo, self.afm.hi)
        return ControlResult(
            controller=self.name, target_um=target, state=s.copy(), u=u.copy(), q=q, predicted_um=mean,
            predicted_std_um=math.sqrt(var), objective=var, status="oracle grid search", iterations=0,
            solve_time_s=time.perf_counter() - t0, success=True, constraint_residual=abs(mean - target),
            n_starts=int(U.shape[0]),
        )


class OracleSequenceController:
    """Sequence-optimal control against the simulator's truth: the counterpart of
    :class:`~microctl.control.sequence.SequenceController` with the learned mean and noise replaced by
    ``true_mean`` / ``true_var`` (the best any learned model can do over a target list).

    Solves ``min sum_k true_var(s_{k-1}, u_k)`` (or the worst move's) subject to
    ``true_mean(s_{k-1}, u_k) = t_k`` and the ranges, ``s_k = [t_k; K u_k]``, by dynamic
    programming over candidate sets of each step's redundant set; the transition cost from
    candidate i of step k-1 to candidate j of step k is ``true_var([t_{k-1}; K u_i], u_j)``.
    Each step's candidates, every one moved onto the true-mean surface by Newton steps
    (:class:`OracleController`'s rules): the grid of the redundant set; the lines where one
    actuator stands still relative to the nominal previous pose, and where one sits at either
    end of its range (the variance's optimum lies on such lines when an actuator with friction
    stays put or one runs out of range); and the pose the greedy oracle (eq. 4 on the truth,
    move by move) chooses, so the plan is never worse than the greedy oracle's. The path is then
    refined ``zooms`` times: a 9 x 9 grid around each step's pose at half the spacing each time,
    plus the still lines relative to the path's previous pose, and DP again.

    The truth depends on the previous state only through q (``SimulatedStage.true_mean``), so a
    plan stays valid whatever the gauge read after each move: the runner plans once per trial.
    Later moves are evaluated at the stage's current clock and, for an actuator that stands
    still, its current backlash direction: exact without drift and backlash (the shipped
    simulated configs and the bench rigs).

    Parameters
    ----------
    afm : AnalyticForwardModel
    stage : SimulatedStage
        Rebind with :meth:`bind` when the experiment opens a fresh stage.
    grid, line_points, zooms, newton_steps : int
        As :class:`OracleController`.
    sequence_objective : str
        A name registered in :data:`~microctl.control.sequence_objectives.SEQUENCE_OBJECTIVES`:
        ``"sum"`` (cumulative true variance) or ``"max"`` (the worst move's; ties broken by
        the cumulative one with weight ``MAX_TIE_WEIGHT`` per move). The DP keeps, for each
        candidate, the predecessor of the best label score (:meth:`SequenceObjective.score`),
        exact for the sum.
    """

    name = "oracle_sequence"

    def __init__(self, afm: AnalyticForwardModel, stage, *, grid: int = 31, line_points: int = 61, zooms: int = 2,
                 newton_steps: int = 6, sequence_objective: str = "sum"):
        self.afm = afm
        self.one = OracleController(afm, stage, grid=grid, line_points=line_points, zooms=zooms,
                                    newton_steps=newton_steps)
        self.sequence_objective = SEQUENCE_OBJECTIVES[sequence_objective]()

    @property
    def stage(self):
        return self.one.stage

    def bind(self, stage) -> None:
        """Optimise against another simulated stage from now on."""
        self.one.bind(stage)

    def _candidates(self, s: np.ndarray, target: float, U: np.ndarray, D: np.ndarray) -> np.ndarray:
        """The rows of U moved (along the rows of D) onto true_mean(s, .) = target and in range."""
        if U.shape[0] == 0:
            return U
        U, ok = self.one._feasible(s, U, D, target)
        return U[ok]

    def _lines(self, s_prev: np.ndarray, target: float) -> tuple[np.ndarray, np.ndarray]:
        """Still lines relative to s_prev and the range-end lines, with their Newton directions."""
        Us, Ds = [], []
        for q in (s_prev[1:], self.afm.lo, self.afm.hi):
            U, D = self.one._still_lines(np.concatenate([[s_prev[0]], q]), target, self.one.line_points, None)
            Us.append(U)
            Ds.append(D)
        return np.vstack(Us), np.vstack(Ds)

    def _dp(self, s0: np.ndarray, targets: np.ndarray, sets: list[np.ndarray]
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Best path over the candidate sets (T arrays of poses), its per-move true variance and
        the states it moves from, shapes (T, n_p), (T,), (T, n_s)."""
        K = self.afm.K
        T = len(targets)
        seq = self.sequence_objective
        prev = s0[None, :]
        Vm, Vs = np.zeros(1), np.zeros(1)
        back = []
        for k in range(T):
            C = np.vstack([self.one._var(p, sets[k]) for p in prev])  # (m_{k-1}, m_k) true variances
            Ssum = Vs[:, None] + C
            M = np.maximum(Vm[:, None], C)
            b = np.argmin(seq.score(M, Ssum, T), axis=0)
            cols = np.arange(C.shape[1])
            Vm, Vs = M[b, cols], Ssum[b, cols]
            back.append(b)
            prev = np.column_stack([np.full(sets[k].shape[0], targets[k]), sets[k] @ K.T])
        j = int(np.argmin(seq.score(Vm, Vs, T)))
        path = np.empty((T, self.afm.n_p))
        for k in range(T - 1, -1, -1):
            path[k] = sets[k][j]
            j = int(back[k][j])
        S = self._states(s0, targets, path)
        var = np.array([float(self.one._var(S[k], path[k][None, :])[0]) for k in range(T)])
        return path, var, S

    def _states(self, s0: np.ndarray, targets: np.ndarray, path: np.ndarray) -> np.ndarray:
        """s_0..s_{T-1} of a path, shape (T, n_s)."""
        return np.vstack([s0] + [np.concatenate([[targets[k]], self.afm.K @ path[k]]) for k in range(len(targets) - 1)])

    def _first_sets(self, s0: np.ndarray, targets: np.ndarray) -> list[np.ndarray]:
        """Each step's candidates from the nominal previous state (the greedy oracle's moves):
        the greedy pose, the grid of the redundant set and the still and range-end lines."""
        rs, K = self.one.rset, self.afm.K
        T = len(targets)
        sets = []
        s_nom = s0
        for k, t in enumerate(targets):
            t = float(t)
            try:
                greedy = self.one.solve(t, s_nom).u  # the greedy oracle's move from the nominal state
            except SolveError:
                raise SolveError(f"oracle_sequence: step {k + 1} of {T}: no command reaches {t:g} µm inside the "
                                 f"actuator ranges from state [{', '.join(f'{v:g}' for v in s_nom)}]") from None
            G, _ = rs.grid(t, self.one.grid)
            L, DL = self._lines(s_nom, t)
            U = np.vstack([greedy[None, :], G, L])
            D = np.vstack([np.repeat(rs.dir_u[None, :], 1 + G.shape[0], axis=0), DL])
            Uk = self._candidates(s_nom, t, U, D)
            sets.append(np.vstack([greedy[None, :], Uk]))
            s_nom = np.concatenate([[t], K @ greedy])
        return sets

    def _zoom_sets(self, s0: np.ndarray, targets: np.ndarray, path: np.ndarray, spacing: np.ndarray
                   ) -> list[np.ndarray]:
        """Each step's candidates around the path: its pose, a 9 x 9 grid at ``spacing`` and the
        still lines relative to the path's previous pose."""
        rs, K = self.one.rset, self.afm.K
        sets = []
        for k, t in enumerate(targets):
            t = float(t)
            s_prev = s0 if k == 0 else np.concatenate([[targets[k - 1]], K @ path[k - 1]])
            Uz = self.one._zoom_grid(path[k], spacing)
            L, DL = self.one._still_lines(s_prev, t, self.one.line_points, None)
            U = np.vstack([Uz, L])
            D = np.vstack([np.repeat(rs.dir_u[None, :], Uz.shape[0], axis=0), DL])
            sets.append(np.vstack([path[k][None, :], self._candidates(s_prev, t, U, D)]))
        return sets

    def plan(self, targets_um, state: np.ndarray | None = None) -> SequenceResult:
        """The truly sequence-optimal commands for ``targets_um`` from ``state``.

        Parameters
        ----------
        targets_um : sequence of float, length T
        state : ndarray, shape (n_s,), optional
            s_0 = [t; q] (default zero state).

        Returns
        -------
        SequenceResult
            One step per move; a step's ``predicted_um`` / ``predicted_std_um`` are the true mean
            and std from the planned previous state, its ``objective`` the true variance (also
            ``r_e_um2``); ``seed_total_r_e_um2`` the objective of the first DP's path (before the
            zooms); no IPOPT (``iterations`` and ``n_starts`` 0).

        Raises
        ------
        SolveError
            A step whose target no candidate reaches inside the ranges (the message names it).
        """
        t0 = time.perf_counter()
        targets = np.asarray(targets_um, dtype=float).reshape(-1)
        s0 = self.afm.zero_state() if state is None else np.asarray(state, dtype=float).reshape(-1)
        rs, K = self.one.rset, self.afm.K
        sets = self._first_sets(s0, targets)
        path, var, S = self._dp(s0, targets, sets)
        seed_value = self.sequence_objective.value(var)
        N = rs.N
        spacing = np.max(np.abs(np.vstack([(S / rs.D) @ N for S in sets])), axis=0) / max(self.one.grid - 1, 1) * 2.0
        for _ in range(self.one.zooms):
            path, var, S = self._dp(s0, targets, self._zoom_sets(s0, targets, path, spacing))
            spacing = spacing / 2.0
        out = []
        dt = time.perf_counter() - t0
        for k, t in enumerate(targets):
            mean = float(self.one._mean(S[k], path[k][None, :])[0])
            q = np.clip(K @ path[k], self.afm.lo, self.afm.hi)
            out.append(ControlResult(
                controller=self.name, target_um=float(t), state=S[k].copy(), u=path[k].copy(), q=q, predicted_um=mean,
                predicted_std_um=math.sqrt(var[k]), objective=float(var[k]), status="oracle sequence DP",
                iterations=0, solve_time_s=dt, success=True, constraint_residual=abs(mean - float(t)),
                n_starts=0))
        return SequenceResult(
            steps=tuple(out), targets_um=tuple(float(t) for t in targets),
            sequence_objective=self.sequence_objective.name, r_e_um2=var, total_r_e_um2=float(np.sum(var)),
            worst_r_e_um2=float(np.max(var)), seed_total_r_e_um2=seed_value, status="oracle sequence DP",
            success=True, iterations=0, n_starts=0, warm_started=False, solve_time_s=dt)

    def solve(self, target_um: float, state: np.ndarray | None = None, *,
              u_init: np.ndarray | None = None) -> ControlResult:
        """The plan of one target (``u_init`` is ignored)."""
        return self.plan([target_um], state).steps[0]
