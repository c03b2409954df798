"""The optimal controller of the paper (eq. 4) and two baselines, behind one interface.

Every controller satisfies the :class:`Controller` protocol: a ``name`` and
``solve(target_um, state=None, *, u_init=None) -> ControlResult``:

- :class:`OptimalController` (EAFM): ``min_u 1 - exp(-r_e(s, u))`` (eq. 4) subject to the
  predicted tool pose ``T_t (f_a(s, u) + g_e(s, u)) = t_d`` and ``lo <= K u <= hi``, with
  ``r_e`` a summary of the predicted noise variance (:mod:`microctl.control.objectives`; default
  its 95 % upper quantile). The problem is non-convex over the redundant poses, so it is
  seeded globally: the redundant set ``{u : t_mean(s, u) = t_d, lo <= K u <= hi}`` has
  dimension n_p - 1 (2 for Table I); a grid in the null-space coordinates of the tool map
  w, each point moved along w by a few Newton steps onto the EAFM-mean surface, is scored
  with vectorised NumPy, and the best local minima of the grid are polished by IPOPT
  (``nlpsol``, built once per model with target and state as parameters).
- :class:`AFMController`: the AFM alone, smallest actuator motion:
  ``min ||K u - q_prev||^2`` s.t. AFM ``t(u) = t_d``, ``lo <= K u <= hi``.
- :class:`EAFMMeanController`: the same objective with the EAFM-mean constraint (accuracy
  without the variance objective).

Any other objective (:class:`~microctl.control.objectives.Objective`) runs through
:class:`EAFMController`. No result ever carries a command outside the actuator ranges:
every returned u is checked (``lo - range_tol <= K u <= hi + range_tol``, q clipped into
the ranges) together with the constraint residual (``<= ControllerSettings.constraint_tol``);
when IPOPT fails, the best feasible seed is returned (``success=False``, status naming
IPOPT's) or SolveError raised. :func:`~microctl.control.baseline.compare_noise` says whether a
chosen pose is credibly quieter than another (the AFM baseline's). See ``docs/controller.md``.

The pieces live in their own modules (settings, result, redundant set, IPOPT, the EAFM-mean
surface, the AFM baseline); the names other packages use are re-exported here.
"""

from __future__ import annotations

import math
import time
from dataclasses import replace
from typing import NamedTuple

import casadi as ca
import numpy as np

from microctl.control.base import BaseController, unreachable
from microctl.control.baseline import AFMController, compare_noise, with_baseline
from microctl.control.credible import prob_better
from microctl.control.fastpath import FastSQP, build_fast_function
from microctl.control.ipopt import ipopt_options
from microctl.control.objectives import NoiseVariance, Objective, PerMoveObjective, SmallestMotion
from microctl.control.redundant import RedundantSet, grid_local_minima
from microctl.control.result import Controller, ControlResult, NoiseComparison
from microctl.control.settings import ControllerSettings
from microctl.control.surface import EAFMSurface
from microctl.errors import ConfigError, SolveError
from microctl.models.eafm import EAFM
from microctl.util.blas import single_thread_blas

#: Two commands closer than this on every actuator (µm) are the same command (the least-motion
#: rule then returns eq. 4's optimum without comparing).
SAME_COMMAND_UM = 1e-6
#: How a result's ``choice`` begins when the least-motion rule returned the least motion instead
#: of eq. 4's optimum (:func:`returned_least_motion` reads it back, e.g. for the experiment's report).
LEAST_MOTION_CHOICE = "least motion:"

__all__ = [
    "ControllerSettings", "ControlResult", "Controller", "EAFMController", "OptimalController", "AFMController",
    "EAFMMeanController", "RedundantSet", "NoiseComparison", "NoiseVariance", "compare_noise", "with_baseline",
    "LEAST_MOTION_CHOICE", "returned_least_motion",
]


class _Least(NamedTuple):
    """The least motion the rule compares eq. 4's optimum with: its command and the solver's account."""

    u: np.ndarray
    status: str
    iterations: int
    n_starts: int


def returned_least_motion(choice: str) -> bool:
    """Whether a result's ``choice`` says the least-motion rule returned the least motion (not eq. 4's
    optimum; :attr:`ControllerSettings.prefer_least_motion`)."""
    return str(choice).startswith(LEAST_MOTION_CHOICE)


class EAFMController(BaseController):
    """A controller minimising ``objective`` subject to the EAFM mean (eq. 4's constraint).

    Parameters
    ----------
    eafm : EAFM
    objective : Objective
        What to minimise (:mod:`microctl.control.objectives`).
    settings : ControllerSettings, optional
        Solver settings (the objective fields of the settings are not used here).
    name : str
        The controller's name in results (default ``"eafm"``).
    """

    name = "eafm"

    def __init__(self, eafm: EAFM, objective: Objective, settings: ControllerSettings | None = None,
                 name: str | None = None):
        super().__init__(eafm.afm, settings)
        if not isinstance(objective, Objective):
            raise ConfigError(f"objective must provide name, needs, mx() and evaluate(); got {type(objective).__name__}")
        if name is not None:
            self.name = name
        self.eafm = eafm
        self.objective = objective
        # A per-move objective is a monotone function of r (eq. 4: 1 - exp(-r)): the same argmin
        # is found by minimising r itself, which does not saturate where r is many µm² (there
        # 1 - exp(-r) is 1 to machine precision at every pose, its gradient ~exp(-r), and the
        # solver cannot tell a pose many times noisier from the quietest one: the paper-scale rig)
        self._per_move = isinstance(objective, PerMoveObjective)
        self.surface = EAFMSurface(eafm, self.settings, self.name)
        self.rset = self.surface.rset
        self._solver: ca.Function | None = None
        self._last_attempts: dict = {"status": [], "iter": 0, "n": 0}
        self._build()

    def _objective_np(self, s: np.ndarray, U: np.ndarray, seeding: bool = False) -> np.ndarray:
        """What the solver minimises at the rows of U: r for a per-move objective, else the objective."""
        if self._per_move:
            return self.objective.r_np(self.eafm, s, U, seeding=seeding)
        return self.objective.evaluate(self.eafm, s, U, seeding=seeding)

    # ---- NLP -------------------------------------------------------------------------
    def _build(self) -> None:
        """Build the NLP once: x = u, p = [t_d; s; J_ref] (eq. 4); IPOPT on it at its first use."""
        afm = self.afm
        u = ca.MX.sym("u", afm.n_p)
        s = ca.MX.sym("s", afm.n_s)
        td = ca.MX.sym("t_d")
        jref = ca.MX.sym("J_ref")
        e = self.eafm.expressions(s, u, self.objective.needs)
        J = (self.objective.r_mx if self._per_move else self.objective.mx)(s, u, e, afm.K)
        g = ca.vertcat(e["t_mean"] - td, ca.mtimes(ca.DM(afm.K), u))  # eq. 4 constraint; lo <= K u <= hi
        self._nlp = {"x": u, "p": ca.vertcat(td, s, jref), "f": J / jref, "g": g}
        self._fast = None
        if self.settings.fast_path:
            fun = build_fast_function(u, s, J, e["t_mean"], f"{self.name}_fast")
            self._fast = FastSQP(fun, afm.K, afm.lo, afm.hi, constraint_tol=self.settings.constraint_tol,
                                 kkt_tol=self.settings.ipopt_tol)
        self._lbg = np.concatenate([[0.0], afm.lo])
        self._ubg = np.concatenate([[0.0], afm.hi])

    def _ipopt(self) -> ca.Function:
        """The IPOPT solver of the NLP, built at its first use (once per controller): most
        solves end on the fast path, and creating an IPOPT instance costs milliseconds."""
        if self._solver is None:
            self._solver = ca.nlpsol(f"{self.name}_ipopt", "ipopt", self._nlp, ipopt_options(self.settings))
            self.n_builds += 1
        return self._solver

    def reachable_interval(self, state: np.ndarray | None = None) -> tuple[float, float]:
        """Interval of EAFM-mean tool poses reachable from ``state`` over the workspace (µm)."""
        return self.surface.reachable_interval(self._state(state))

    # ---- seeding ---------------------------------------------------------------------
    def _seeds(self, s: np.ndarray, target: float, grid: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Feasible seeds on the redundant set, their objective and the grid-local-minimum order."""
        Un, idx, shape = self.surface.on_surface(s, target, grid)
        obj = np.full(Un.shape[0], np.inf)
        if idx.size:
            obj[idx] = self._objective_np(s, Un[idx], seeding=True)
        mins = grid_local_minima(obj, shape)
        mins = mins[np.argsort(obj[mins])]
        return Un, obj, mins

    def candidates(self, target_um: float, state: np.ndarray | None = None, *, max_ratio: float = 2.0,
                   max_count: int = 8) -> tuple[np.ndarray, np.ndarray]:
        """Candidate optimal poses: the local minima of the seeding grid over the redundant set.

        Parameters
        ----------
        target_um : float
        state : ndarray, shape (n_s,), optional
        max_ratio : float
            Keep minima whose objective is at most ``max_ratio`` times the best.
        max_count : int

        Returns
        -------
        U : ndarray, shape (k, n_p)
            On the EAFM-mean surface of the target, inside the ranges (k may be 0).
        objective : ndarray, shape (k,)
        """
        s = self._state(state)
        with single_thread_blas():
            U, obj, mins = self._seeds(s, float(target_um), self.settings.grid)
        if mins.size == 0:
            return np.zeros((0, self.afm.n_p)), np.zeros(0)
        keep = mins[obj[mins] <= max_ratio * obj[mins[0]]][:max_count]
        return U[keep], obj[keep]

    # ---- solve -----------------------------------------------------------------------
    def solve(self, target_um: float, state: np.ndarray | None = None, *,
              u_init: np.ndarray | None = None) -> ControlResult:
        """Control signal for ``target_um`` from ``state`` (default zero state).

        Parameters
        ----------
        target_um : float
        state : ndarray, shape (n_s,), optional
        u_init : ndarray, shape (n_p,), optional
            Warm start (e.g. the previous solution along a target sequence); it is moved onto
            the new target's surface and polished besides the global seeds.

        Raises
        ------
        SolveError
            Unreachable target (message gives the reachable interval from ``state``), or
            no command passing the checks.
        """
        with single_thread_blas():
            return self._solve(target_um, state, u_init, time.perf_counter())

    def _solve(self, target_um: float, state: np.ndarray | None, u_init: np.ndarray | None,
               t0: float) -> ControlResult:
        cfg = self.settings
        s = self._state(state)
        target = float(target_um)
        if not math.isfinite(target):
            raise ConfigError(f"target must be a finite number of µm, got {target_um!r}")
        U, obj, mins = self._seeds(s, target, cfg.grid)
        starts: list[np.ndarray] = []
        if u_init is not None:
            uw, rw = self.surface.newton(s, np.asarray(u_init, dtype=float).reshape(1, -1), target)
            if self.surface.in_range(uw[0]):
                starts.append(uw[0])
        if mins.size == 0 and not starts:
            lo, hi = self.reachable_interval(s)
            if not (lo - cfg.constraint_tol <= target <= hi + cfg.constraint_tol):
                raise unreachable(target, s, "EAFM", lo, hi)
            # reachable but the grid missed the thin section: a dense retry
            U, obj, mins = self._seeds(s, target, 4 * cfg.grid)
        best_seed = float(obj[mins[0]]) if mins.size else math.inf
        for i in mins[: cfg.n_polish]:
            if obj[i] <= cfg.polish_ratio * best_seed or not starts:
                starts.append(U[i])
        result = self._polish(s, target, starts, t0)
        if result is None and mins.size > cfg.n_polish:
            # cold retry from the remaining grid minima
            result = self._polish(s, target, [U[i] for i in mins[cfg.n_polish: 3 * cfg.n_polish]], t0,
                                  prior=self._last_attempts)
        if result is not None:
            return result
        # IPOPT failed everywhere: the best seed that passes the checks (after a Newton
        # refinement), never a command outside the ranges or off the target
        status = "; ".join(sorted(set(self._last_attempts["status"]))) or "no start"
        feas = np.flatnonzero(np.isfinite(obj))
        for i in feas[np.argsort(obj[feas])][: 3 * cfg.n_polish]:
            u = self.surface.refine(s, U[i], target)
            if u is not None:
                return self._result(s, target, u, f"{status}; fallback to seed", False, t0)
        raise SolveError(f"no valid control signal for target {target:g} µm (IPOPT: {status})")

    def _polish(self, s: np.ndarray, target: float, starts: list[np.ndarray], t0: float,
                prior: dict | None = None) -> ControlResult | None:
        best = self._polish_best(s, target, starts, prior)
        if best is None:
            return None
        return self._result(s, target, best[1], best[2], True, t0, objective=best[0])

    def _polish_best(self, s: np.ndarray, target: float, starts: list[np.ndarray],
                     prior: dict | None = None) -> tuple[float, np.ndarray, str] | None:
        """Polish every start; the best passing the checks as (objective, u, status), or None.
        The attempts (statuses, iterations, starts) are left in ``self._last_attempts``."""
        attempts = {"status": list(prior["status"]) if prior else [], "iter": prior["iter"] if prior else 0,
                    "n": prior["n"] if prior else 0}
        best: tuple[float, np.ndarray, str] | None = None
        for u0 in starts:
            x0, st = self._start(u0, s, target)
            attempts["status"].append(st["status"])
            attempts["iter"] += st["iter"]
            attempts["n"] += 1
            if not st["success"]:
                continue
            x = self.surface.refine(s, x0, target)
            if x is None:
                continue
            # the fast path evaluated the objective at its solution already (refine left it there)
            j = st["objective"] if x is x0 and "objective" in st else float(self._objective_np(s, x[None, :])[0])
            if best is None or j < best[0]:
                best = (j, x, st["status"])
        self._last_attempts = attempts
        return best

    def _start(self, u0: np.ndarray, s: np.ndarray, target: float) -> tuple[np.ndarray, dict]:
        """One polish from ``u0``: the fast SQP when it converges (KKT-checked), else IPOPT from ``u0``
        (the objective scaled by its value at ``u0``)."""
        if self._fast is not None:
            x, st = self._fast.solve(u0, s, target)
            if st["success"]:
                return x, {"status": "Solve_Succeeded", "iter": st["iter"], "success": True,
                           "objective": st["objective"]}
        jref = float(self._objective_np(s, u0[None, :], seeding=True)[0])
        jref = jref if jref > 1e-300 else 1.0
        return self._run(self._ipopt(), u0, np.concatenate([[target], s, [jref]]),
                         self.afm.workspace.u_lo, self.afm.workspace.u_hi, self._lbg, self._ubg)

    def _result(self, s: np.ndarray, target: float, u: np.ndarray, status: str, success: bool,
                t0: float, objective: float | None = None) -> ControlResult:
        if objective is None:
            objective = float(self._objective_np(s, u[None, :])[0])
        if self._per_move:  # report the objective itself (eq. 4), from the r that was minimised
            objective = float(self.objective.of_r(np.array([objective]))[0])
        return self.surface.result(self.name, s, target, u, objective, status, success, self._last_attempts, t0)

    def solve_sequence(self, targets: list[float], states: list[np.ndarray] | None = None) -> list[ControlResult]:
        """Solve a target sequence, warm-starting each from the previous solution.

        Parameters
        ----------
        targets : list of float
        states : list of ndarray, optional
            State before each move (default: the zero state, then the predicted state
            ``[predicted_um; q]`` of the previous command).
        """
        out: list[ControlResult] = []
        prev_u = None
        s = self.afm.zero_state()
        for k, tgt in enumerate(targets):
            if states is not None:
                s = np.asarray(states[k], dtype=float)
            r = self.solve(tgt, s, u_init=prev_u)
            out.append(r)
            prev_u = r.u
            s = np.concatenate([[r.predicted_um], r.q])
        return out


class OptimalController(EAFMController):
    """The EAFM optimal controller of eq. 4 with the objective ``settings`` describe.

    Parameters
    ----------
    eafm : EAFM
    settings : ControllerSettings, optional
        ``r_e``, ``kappa`` and ``epistemic`` choose the objective
        (:meth:`ControllerSettings.objective`).
    """

    def __init__(self, eafm: EAFM, settings: ControllerSettings | None = None, baseline: Controller | None = None):
        settings = settings or ControllerSettings()
        super().__init__(eafm, settings.objective(), settings, name="eafm")
        self.baseline = baseline
        self._least: EAFMMeanController | None = None
        self._least_afm: AFMController | None = None

    def solve(self, target_um: float, state: np.ndarray | None = None, *,
              u_init: np.ndarray | None = None) -> ControlResult:
        """As :meth:`EAFMController.solve`; with a ``baseline`` controller, the result also says
        whether the chosen pose is credibly quieter than the baseline's (``vs_baseline``).

        With ``settings.prefer_least_motion`` the smallest motion onto the EAFM-mean surface is
        returned unless eq. 4's optimum has the lower expected squared error once the unselected
        noise sources are weighed in (and, with ``settings.least_motion_credible``, credibly so;
        :mod:`microctl.control.credible`); ``choice`` of the result says which was returned and why.
        """
        with single_thread_blas():  # one limit for both parts (the blocks inside find it set)
            res = super().solve(target_um, state, u_init=u_init)
            if self.settings.prefer_least_motion:
                res = self._unless_better(res, u_init)
        if self.baseline is None:
            return res
        return with_baseline(self.eafm, res, self.baseline, self.settings.credible_level)

    def _least_start(self, res: ControlResult) -> np.ndarray | None:
        """Where to polish the least motion from: the AFM's least motion (a QP) moved along w onto
        the EAFM-mean surface, the smallest motion onto that surface to second order in f; the
        AFM's least motion itself where that leaves the ranges (e.g. from a range's edge); None
        where the AFM does not reach the target."""
        if self._least is None:
            self._least = EAFMMeanController(self.eafm, self.settings)
            self._least_afm = AFMController(self.afm, self.settings)
        try:  # the AFM cannot reach every target the EAFM mean can
            start = self._least_afm.command(res.target_um, res.state)
        except SolveError:
            return None
        moved = self._least.surface.refine(res.state, start, res.target_um)
        return start if moved is None else moved

    def _least_motion(self, res: ControlResult, start: np.ndarray | None,
                      u_init: np.ndarray | None) -> _Least | None:
        """The smallest motion onto the EAFM-mean surface for ``res``'s target and state (None if
        none passes the checks). ``||K u - q_prev||^2`` is convex and the surface is the AFM's plane
        bent by f, so one polish from :meth:`_least_start` finds it; the EAFM-mean controller's
        global seeding runs only when there is no start or its polish fails. Only the command and
        the solver's account are kept: the result returned for it is this controller's (eq. 4's
        objective), built only when the least motion is returned."""
        if start is not None:
            best = self._least._polish_best(res.state, res.target_um, [start])
            if best is not None:
                at = self._least._last_attempts
                return _Least(best[1], best[2], int(at.get("iter", 0)), int(at.get("n", 0)))
        try:
            least = self._least.solve(res.target_um, res.state, u_init=u_init)
        except SolveError:
            return None
        return _Least(least.u, least.status, least.iterations, least.n_starts) if least.success else None

    def _unless_better(self, res: ControlResult, u_init: np.ndarray | None) -> ControlResult:
        """``res`` if its pose is better than the least motion's (the settings' test), else the least
        motion (reported as this controller's result: eq. 4's objective at it).

        The comparison is made with the least motion that would be returned (polished from
        :meth:`_least_start`): the start alone, the AFM's least motion moved along w onto the
        surface, can differ from it by tenths of a µm where f bends the surface, and a decision
        by expected squared error can turn on that.
        """
        t0 = time.perf_counter() - res.solve_time_s
        with single_thread_blas():
            least = self._least_motion(res, self._least_start(res), u_init)
            if least is None:
                return res
            u_least = least.u
            if np.abs(self.afm.K @ (res.u - u_least)).max() <= SAME_COMMAND_UM:
                return replace(res, choice="optimum: it is the least motion",
                               solve_time_s=time.perf_counter() - t0)
            p, r_opt, r_least = prob_better(self.eafm, res.state, res.u, u_least)
            excess = self.eafm.alternatives.expected_excess(res.state, res.u, u_least)
            credible = p >= self.settings.credible_level or not self.settings.least_motion_credible
            lower = r_opt + excess < r_least
            if credible and lower:
                return replace(res, choice=f"optimum: lower expected squared error than the least motion ({r_opt:.3g} vs "
                                           f"{r_least:.3g} µm², the unselected sources add {excess:+.3g} µm² to the "
                                           f"difference; P = {p:.3f})",
                               solve_time_s=time.perf_counter() - t0)
        self._last_attempts = {"status": [least.status], "iter": res.iterations + least.iterations,
                               "n": res.n_starts + least.n_starts}
        why = (f"better with P = {p:.3f} < {self.settings.credible_level:g}" if not credible
               else f"not better once the sources the data did not select are weighed in (expected squared "
                    f"error {r_opt:.3g} vs {r_least:.3g} µm², they add {excess:+.3g} µm² to the difference; "
                    f"P = {p:.3f})")
        out = self._result(res.state, res.target_um, least.u, least.status, True, t0)
        return replace(out, choice=f"{LEAST_MOTION_CHOICE} eq. 4's optimum {why}")


class EAFMMeanController(EAFMController):
    """EAFM-mean baseline: ``min ||K u - q_prev||^2`` s.t. EAFM mean = target, in range.

    Parameters
    ----------
    eafm : EAFM
    settings : ControllerSettings, optional
    """

    def __init__(self, eafm: EAFM, settings: ControllerSettings | None = None):
        super().__init__(eafm, SmallestMotion(), settings, name="eafm_mean")

