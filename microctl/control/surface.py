"""The EAFM-mean surface of a target: where a command of an EAFM controller must lie.

:class:`EAFMSurface` holds what the single-move controller
(:class:`~microctl.control.controller.EAFMController`) and the sequence controller
(:class:`~microctl.control.sequence.SequenceController`) share: Newton steps along w onto
``t_mean(s, u) = t_d`` (eq. 1's constraint), the seeding grid of the redundant set moved onto
that surface, the interval of tool poses the EAFM reaches from a state, the check of a returned
command and the :class:`~microctl.control.result.ControlResult` of an EAFM command.
"""

from __future__ import annotations

import math
import time

import casadi as ca
import numpy as np

from microctl.control.base import in_range, parse_state
from microctl.control.ipopt import ipopt_options, run_ipopt
from microctl.control.redundant import RedundantSet
from microctl.control.result import ControlResult
from microctl.control.settings import ControllerSettings
from microctl.models.eafm import EAFM

__all__ = ["EAFMSurface"]


class EAFMSurface:
    """Newton projection, seeding grid, reachable interval and checks on the EAFM-mean surface.

    Parameters
    ----------
    eafm : EAFM
    settings : ControllerSettings
        ``newton_steps``, ``constraint_tol``, ``range_tol``, ``kappa`` and the IPOPT settings.
    name : str
        The owning controller's name (its range NLP is ``"<name>_range"``).
    """

    def __init__(self, eafm: EAFM, settings: ControllerSettings, name: str):
        self.eafm = eafm
        self.afm = eafm.afm
        self.settings = settings
        self.name = name
        self.rset = RedundantSet(eafm.afm)
        self._range_solver: ca.Function | None = None

    def in_range(self, u: np.ndarray) -> bool:
        """``lo - range_tol <= K u <= hi + range_tol``."""
        return in_range(self.afm, u, self.settings.range_tol)

    def _range_nlp(self) -> ca.Function:
        if self._range_solver is None:
            afm = self.afm
            u = ca.MX.sym("u", afm.n_p)
            s = ca.MX.sym("s", afm.n_s)
            sign = ca.MX.sym("sign")
            t = self.eafm.expressions(s, u, ("t_mean",))["t_mean"]
            nlp = {"x": u, "p": ca.vertcat(s, sign), "f": sign * t, "g": ca.mtimes(ca.DM(afm.K), u)}
            self._range_solver = ca.nlpsol(f"{self.name}_range", "ipopt", nlp, ipopt_options(self.settings))
        return self._range_solver

    def reachable_interval(self, state: np.ndarray | None = None) -> tuple[float, float]:
        """Interval of EAFM-mean tool poses reachable from ``state`` over the workspace (µm)."""
        s = parse_state(self.afm, state)
        V = self.rset.vertices
        tv, _ = self.eafm.mean_and_grad_u(s, V)
        out = []
        for sign in (1.0, -1.0):
            best = float(np.min(sign * tv))
            x0 = V[np.argmin(sign * tv)] * 0.999  # just inside (the origin is interior for Table I)
            x0 = x0 if self.afm.workspace.contains(x0) else V[np.argmin(sign * tv)]
            x, st = run_ipopt(self._range_nlp(), x0, np.concatenate([s, [sign]]),
                              self.afm.workspace.u_lo, self.afm.workspace.u_hi, self.afm.lo, self.afm.hi)
            if st["success"] and self.in_range(x):
                best = min(best, float(sign * self.eafm.mean_and_grad_u(s, x[None, :])[0][0]))
            out.append(sign * best)
        return out[0], out[1]

    def newton(self, s: np.ndarray, U: np.ndarray, target: float,
               at_start: tuple[np.ndarray, np.ndarray] | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Move each row of U along w onto t_mean(s, u) = target; return U and |residual|.

        At most ``newton_steps`` steps; it stops as soon as every residual is below 1e-11 max(1,
        |target|) µm (one step with an affine mean correction), so an evaluation of the mean and
        its gradient (an m x n kernel) is not repeated once it would change nothing.
        ``at_start``: ``eafm.mean_and_grad_u(s, U)`` when the caller has it (not evaluated again).
        """
        dirn = self.rset.dir_u
        U = U.copy()
        done = 1e-11 * max(1.0, abs(target))
        for k in range(self.settings.newton_steps):
            if k == 0 and at_start is not None:
                (t, dt), grad = at_start, None
            else:  # the gradient only where a step is taken (the last evaluation is a check)
                t, grad = self.eafm.mean_lazy_grad_u(s, U)
            if (np.abs(t - target) <= done).all():
                return U, np.abs(t - target)
            if grad is not None:
                dt = grad()
            slope = dt @ dirn
            slope = np.where(np.abs(slope) > 1e-12, slope, 1e-12)
            U += ((target - t) / slope)[:, None] * dirn[None, :]
        t, _ = self.eafm.mean_lazy_grad_u(s, U)
        return U, np.abs(t - target)

    def on_surface(self, s: np.ndarray, target: float, grid: int) -> tuple[np.ndarray, np.ndarray, tuple[int, ...]]:
        """The seeding grid of the redundant set moved onto the EAFM-mean surface from state s.

        Returns
        -------
        U : ndarray, shape (grid**(n_p-1), n_p)
            Grid points (those near the workspace Newton-projected onto t_mean(s, u) = target).
        feasible : ndarray of int
            Indices of the points on the surface (|residual| <= 1e-6 max(1, |target|)) and in range.
        shape : tuple of int
            The grid's shape.
        """
        U, shape = self.rset.grid(target, grid)
        # drop points far outside the workspace before the GP work (Newton moves along w only slightly)
        q = U @ self.afm.K.T
        span = self.afm.hi - self.afm.lo
        near = np.all((q >= self.afm.lo - 0.05 * span) & (q <= self.afm.hi + 0.05 * span), axis=1)
        Un = U.copy()
        idx = np.zeros(0, dtype=int)
        if np.any(near):
            Un[near], res = self.newton(s, U[near], target)
            qn = Un[near] @ self.afm.K.T
            feas = (res <= 1e-6 * max(1.0, abs(target))) & np.all(
                (qn >= self.afm.lo) & (qn <= self.afm.hi), axis=1)
            idx = np.flatnonzero(near)[feas]
        return Un, idx, shape

    def refine(self, s: np.ndarray, u: np.ndarray, target: float) -> np.ndarray | None:
        """Check (and if needed Newton-correct along w) the constraint residual and ranges."""
        t, grad = self.eafm.mean_lazy_grad_u(s, u[None, :])
        if abs(t[0] - target) > self.settings.constraint_tol:
            U, res = self.newton(s, u[None, :], target, at_start=(t, grad()))
            if res[0] > self.settings.constraint_tol:
                return None
            u = U[0]
        return u if self.in_range(u) else None

    def result(self, controller: str, s: np.ndarray, target: float, u: np.ndarray, objective: float,
               status: str, success: bool, attempts: dict, t0: float) -> ControlResult:
        """The result of the EAFM command u for ``target`` from s (EAFM prediction at u).

        Parameters
        ----------
        objective : float
            The controller's objective at u.
        attempts : dict
            ``{"iter", "n"}``: IPOPT iterations and starts of the call.
        t0 : float
            ``time.perf_counter()`` at the start of the call.
        """
        p = self.eafm.predict(s, u)
        g, gv = float(p.g_mean[0]), float(p.g_var[0])
        return ControlResult(
            controller=controller, target_um=target, state=s.copy(), u=u.copy(),
            q=np.clip(self.afm.K @ u, self.afm.lo, self.afm.hi),
            predicted_um=float(p.t_mean[0]), predicted_std_um=float(math.sqrt(p.t_var[0])),
            objective=objective, status=status,
            iterations=int(attempts.get("iter", 0)), solve_time_s=time.perf_counter() - t0, success=success,
            constraint_residual=float(abs(p.t_mean[0] - target)), n_starts=int(attempts.get("n", 0)),
            noise_std_um=math.exp(0.5 * (g + 0.5 * gv)),
            noise_upper_std_um=math.exp(0.5 * (g + self.settings.kappa * math.sqrt(gv))),
            bias_std_um=math.sqrt(max(float(p.f_var[0]), 0.0)),
        )
