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
   :class:`~microctl.controller.RedundantSet`), plus, for each actuator i, points on the line
   where it stands still (K_i u = q_prev,i) — the kinks;
2. each candidate is moved onto the true-mean surface by Newton steps along a direction that
   keeps the still actuator still (finite-difference slope), then checked for range;
3. the grid is refined ``zooms`` times around the best feasible candidate.

It has the controllers' interface: ``solve(target_um, state, u_init=None) -> ControlResult``.
"""

from __future__ import annotations

import math
import time

import numpy as np

from microctl.afm import AnalyticForwardModel
from microctl.controller import ControlResult, RedundantSet
from microctl.errors import SolveError

__all__ = ["OracleController"]

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

    def _evaluate(self, s: np.ndarray, U: np.ndarray, D: np.ndarray, target: float) -> tuple[np.ndarray, np.ndarray]:
        """Project candidates and score them; infeasible ones get +inf."""
        if U.shape[0] == 0:
            return U, np.zeros(0)
        U, res = self._project(s, U, D, target)
        ok = (res <= _CONSTRAINT_TOL * max(1.0, abs(target))) & self._in_range(U)
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
            c0 = (U[k] / rs.D) @ N
            axes = [np.linspace(c - 2 * h, c + 2 * h, 9) for c, h in zip(c0, step)]
            C = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, N.shape[1])
            Uz = (C @ N.T) * rs.D + (U[k] / rs.D @ rs.v_hat) * rs.v_hat * rs.D
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
