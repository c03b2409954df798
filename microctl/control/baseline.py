"""The baselines beside the optimal controller: the AFM controller (smallest actuator motion under
the AFM alone) and the credibility test of a chosen pose against a baseline's (the noise
posterior of g)."""

from __future__ import annotations

import math
import time
from dataclasses import replace

import casadi as ca
import numpy as np

from microctl.control.base import BaseController, unreachable
from microctl.control.fastpath import ActiveSetQP
from microctl.control.ipopt import ipopt_options
from microctl.control.redundant import RedundantSet
from microctl.control.result import Controller, ControlResult, NoiseComparison
from microctl.control.settings import ControllerSettings
from microctl.errors import SolveError
from microctl.models.afm import AnalyticForwardModel
from microctl.models.eafm import EAFM

__all__ = ["AFMController", "compare_noise", "with_baseline"]


def with_baseline(eafm: EAFM, res: ControlResult, baseline: Controller, level: float = 0.95,
                  memory: np.ndarray | None = None) -> ControlResult:
    """``res`` with the ``baseline`` controller's result from the same state and whether ``res.u``
    is credibly quieter than the baseline's command (:func:`compare_noise`). ``memory``: the
    hysteresis play states both start from, for a baseline wrapped by
    :class:`~microctl.control.memory.MemoryCompensated`."""
    b = baseline.solve(res.target_um, res.state) if memory is None else \
        baseline.solve(res.target_um, res.state, memory=memory)
    return replace(res, vs_baseline=compare_noise(eafm, res.state, res.u, b.u, level), baseline=b)


def compare_noise(eafm: EAFM, state: np.ndarray, u_a: np.ndarray, u_b: np.ndarray,
                  level: float = 0.95) -> NoiseComparison:
    """Is the noise at pose ``u_a`` credibly below that at ``u_b`` (both from ``state``)?

    Parameters
    ----------
    eafm : EAFM
    state : ndarray, shape (n_s,)
    u_a, u_b : ndarray, shape (n_p,)
    level : float
        Credibility level.
    """
    mean, cov = eafm.g_joint(np.asarray(state, dtype=float), np.vstack([u_a, u_b]))
    d = float(mean[0] - mean[1])
    sd = math.sqrt(max(float(cov[0, 0] + cov[1, 1] - 2.0 * cov[0, 1]), 1e-18))
    p = 0.5 * math.erfc(d / (sd * math.sqrt(2.0)))  # Phi(-d / sd), no scipy.special at start-up
    return NoiseComparison(prob_quieter=p, log_ratio_mean=d, log_ratio_std=sd, credible=p >= level, level=level)


class AFMController(BaseController):
    """AFM baseline: smallest actuator motion ``min ||K u - q_prev||^2`` s.t. AFM t(u) = target.

    The AFM tool map is linear up to the sensor polynomial, so the constraint is the plane
    ``w·u = d`` with d the inverted gauge reading: a convex QP, solved by IPOPT from the
    unconstrained minimiser (one start).

    Parameters
    ----------
    afm : AnalyticForwardModel
    settings : ControllerSettings, optional
    reporter : EAFM, optional
        When given, ``predicted_um`` / ``predicted_std_um`` of the result are the EAFM's at
        the AFM command (what the AFM command is expected to do); otherwise AFM t(u) and NaN.
    """

    name = "afm"

    def __init__(self, afm: AnalyticForwardModel, settings: ControllerSettings | None = None,
                 reporter: EAFM | None = None):
        super().__init__(afm, settings)
        self.reporter = reporter
        self.rset = RedundantSet(afm)
        self._t_range = afm.t_range()  # the AFM is absolute: the same from every state
        u = ca.MX.sym("u", afm.n_p)
        p = ca.MX.sym("p", 1 + afm.n_q)  # [d; q_prev]
        Ku = ca.mtimes(ca.DM(afm.K), u)
        scale = float(np.mean((afm.hi - afm.lo) ** 2))
        self._nlp = {"x": u, "p": p, "f": ca.sumsqr(Ku - p[1:]) / scale,
                     "g": ca.vertcat(ca.dot(ca.DM(afm.w_pred), u) - p[0], Ku)}
        self._solver: ca.Function | None = None
        self._qp = ActiveSetQP(afm.K, afm.lo, afm.hi)
        # the plane minimiser's KKT matrix and 2 K^T depend on the stage alone: formed once
        K, w = afm.K, afm.w_pred
        self._two_kt = 2 * K.T
        self._kkt = np.block([[self._two_kt @ K, w[:, None]], [w[None, :], np.zeros((1, 1))]])

    def _ipopt(self) -> ca.Function:
        """IPOPT on the QP, built at its first use: only a command whose plane minimiser leaves
        the ranges needs it."""
        if self._solver is None:
            self._solver = ca.nlpsol("afm_ipopt", "ipopt", self._nlp, ipopt_options(self.settings))
            self.n_builds += 1
        return self._solver

    def _exact(self, u0: np.ndarray, d: float, qp: np.ndarray) -> tuple[np.ndarray | None, str]:
        """The convex QP's optimum without IPOPT, or None.

        ``u0`` minimises ``||K u - q_prev||^2`` on the plane ``w·u = d``: inside every range it is
        the optimum (no inequality active); otherwise one step of the enumerated active-set QP
        (:class:`ActiveSetQP`, exact for a QP) from it, kept only inside the ranges and the
        workspace box and on the plane (else IPOPT decides).
        """
        ws, K, w = self.afm.workspace, self.afm.K, self.afm.w_pred
        tol = self.settings.constraint_tol

        def valid(u: np.ndarray) -> bool:
            # an active range is met to round-off, as IPOPT meets it to its tolerance
            return bool(self._in_range(u) and np.all(u >= ws.u_lo - 1e-9) and np.all(u <= ws.u_hi + 1e-9)
                         and abs(float(w @ u) - d) <= tol)

        if valid(u0):
            return u0, "closed form: no range active"
        step = self._qp.solve(2.0 * K.T @ K, 2.0 * K.T @ (K @ u0 - qp), w, float(w @ u0) - d,
                           self._qp.b - self._qp.A @ u0)
        if step is not None and valid(u0 + step[0]):
            return u0 + step[0], f"active-set QP: {int(np.count_nonzero(step[2]))} range(s) active"
        return None, ""

    def solve(self, target_um: float, state: np.ndarray | None = None, *,
              u_init: np.ndarray | None = None) -> ControlResult:
        """AFM command for ``target_um`` from ``state`` (``u_init`` is ignored: convex)."""
        t0 = time.perf_counter()
        s = self._state(state)
        target = float(target_um)
        x, status, st, ok = self._command(target, s)
        K, qp = self.afm.K, s[1:]
        if self.reporter is not None:
            p = self.reporter.predict(s, x)
            pred, std = float(p.t_mean[0]), float(math.sqrt(p.t_var[0]))
        else:
            pred, std = float(self.afm.t_of(x)), float("nan")
        return ControlResult(
            controller=self.name, target_um=target, state=s.copy(), u=x.copy(), q=self._q(x), predicted_um=pred,
            predicted_std_um=std, objective=float(np.sum((K @ x - qp) ** 2)), status=status,
            iterations=st["iter"], solve_time_s=time.perf_counter() - t0, success=bool(ok),
            constraint_residual=float(abs(float(self.afm.t_of(x)) - target)), n_starts=1,
        )

    def command(self, target_um: float, state: np.ndarray | None = None) -> np.ndarray:
        """The command :meth:`solve` returns, without its result (the least-motion rule's start).

        Raises
        ------
        SolveError
            As :meth:`solve`.
        """
        return self._command(float(target_um), self._state(state))[0]

    def _command(self, target: float, s: np.ndarray) -> tuple[np.ndarray, str, dict, bool]:
        """The command, its status, the solver's account and whether it passed the checks."""
        lo, hi = self._t_range
        if not (lo - self.settings.constraint_tol <= target <= hi + self.settings.constraint_tol):
            raise unreachable(target, s, "AFM", lo, hi)
        d = self.rset.d_of_target(target)
        K, qp = self.afm.K, s[1:]
        # unconstrained-in-range minimiser of ||K u - q_prev||^2 on the plane w·u = d (KKT system)
        n = K.shape[1]
        u0 = np.linalg.solve(self._kkt, np.concatenate([self._two_kt @ qp, [d]]))[:n]
        ws = self.afm.workspace
        x, how = self._exact(u0, d, qp)
        if x is not None:
            st = {"status": f"Solve_Succeeded ({how})", "iter": 0, "success": True}
        else:
            x, st = self._run(self._ipopt(), u0, np.concatenate([[d], qp]), ws.u_lo, ws.u_hi,
                              np.concatenate([[0.0], self.afm.lo]), np.concatenate([[0.0], self.afm.hi]))
        ok = st["success"] and self._in_range(x) and abs(float(self.afm.t_of(x)) - target) <= self.settings.constraint_tol
        status = st["status"]
        if not ok:
            if self._in_range(u0) and abs(float(self.afm.t_of(u0)) - target) <= self.settings.constraint_tol:
                x, status = u0, f"{status}; fallback to seed"
            else:
                raise SolveError(f"AFM controller: no valid control signal for target {target:g} µm (IPOPT: {status})")
        return x, status, st, ok

