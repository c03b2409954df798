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
IPOPT's) or SolveError raised. :func:`compare_noise` says whether a chosen pose is credibly
quieter than another (the AFM baseline's). See ``docs/controller.md``.
"""

from __future__ import annotations

import itertools
import math
import time
from dataclasses import dataclass, replace
from typing import Protocol, runtime_checkable

import casadi as ca
import numpy as np
from scipy.special import ndtr

from microctl.control.objectives import (
    R_E_SETTINGS,
    NoiseVariance,
    Objective,
    SmallestMotion,
)
from microctl.errors import ConfigError, SolveError, UnreachableTargetError
from microctl.models.afm import AnalyticForwardModel
from microctl.models.eafm import EAFM
from microctl.util.blas import single_thread_blas
from microctl.util.fields import same_setting, setting, validate_settings

#: What sequence control minimises over the moves' r_e (``ControllerSettings.sequence_objective``).
SEQUENCE_OBJECTIVES = ("sum", "max")

__all__ = [
    "R_E_SETTINGS", "SEQUENCE_OBJECTIVES", "ControllerSettings", "ControlResult", "Controller", "EAFMController",
    "OptimalController", "AFMController", "EAFMMeanController", "RedundantSet", "NoiseComparison", "compare_noise",
    "with_baseline",
]


@dataclass(frozen=True)
class ControllerSettings:
    """Settings of the controllers: the one set of defaults of ``solve``, ``experiment`` and the API.

    Each field is declared once with its default and its rule (:func:`microctl.util.fields.setting`):
    validated here, and read from YAML by :func:`microctl.util.fields.read_settings`.

    Attributes
    ----------
    r_e : str
        Noise summary of eq. 4, one of :data:`~microctl.control.objectives.R_E_SETTINGS` (default
        ``"noise_quantile"``: the upper quantile, cautious where the noise model is uncertain).
    kappa : float
        Standard normal quantile of ``noise_quantile`` (1.645: the 95 % quantile).
    epistemic : bool
        Add the mean correction's posterior variance to r_e.
    credible_level : float
        Probability above which the chosen pose counts as credibly quieter than the AFM
        baseline's (:func:`compare_noise`).
    grid : int
        Grid points per null-space axis of the global seeding (``grid**(n_p-1)`` points).
    newton_steps : int
        Newton steps along w that move each grid point onto the EAFM-mean surface.
    n_polish : int
        Largest number of grid local minima polished by IPOPT.
    polish_ratio : float
        Only local minima with seed objective ``<= polish_ratio * best`` are polished.
    constraint_tol : float
        Largest accepted ``|t_mean(s, u) - t_d|`` (µm) of a returned command.
    range_tol : float
        Largest accepted excursion of ``K u`` beyond the actuator ranges (µm) before q is
        clipped into them.
    ipopt_tol : float
        IPOPT ``tol``.
    max_iter : int
        IPOPT ``max_iter`` per start.
    sequence_objective : str
        What sequence control (:mod:`microctl.control.sequence`) minimises over a target list:
        ``"sum"`` (default) the cumulative r_e of the moves, ``"max"`` the worst move's.
    """

    r_e: str = same_setting(NoiseVariance, "r_e")
    kappa: float = same_setting(NoiseVariance, "kappa")
    epistemic: bool = same_setting(NoiseVariance, "epistemic")
    credible_level: float = setting(0.95, lo=0.5, hi=1.0, lo_open=True)
    grid: int = setting(15, lo=2, hi=201)
    newton_steps: int = setting(4, lo=1, hi=50)
    n_polish: int = setting(2, lo=1, hi=50)
    polish_ratio: float = setting(1.1, lo=1.0, hi=1e6)
    constraint_tol: float = setting(1e-8, lo=0.0, hi=1e-3, lo_open=True)  # µm: a command must meet the target
    range_tol: float = setting(1e-9, lo=0.0, hi=1e-3)                     # µm: round-off only
    ipopt_tol: float = setting(1e-8, lo=0.0, hi=1e-2, lo_open=True)
    max_iter: int = setting(200, lo=1, hi=100_000)
    sequence_objective: str = setting("sum", choices=SEQUENCE_OBJECTIVES)

    def __post_init__(self) -> None:
        validate_settings(self, "controller setting")

    def objective(self) -> NoiseVariance:
        """The objective of eq. 4 these settings describe."""
        return NoiseVariance(r_e=self.r_e, kappa=float(self.kappa), epistemic=self.epistemic)


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
            "vs_baseline": None if self.vs_baseline is None else self.vs_baseline.to_dict(),
        }


_IPOPT_OPTS = {
    "ipopt.print_level": 0, "ipopt.sb": "yes", "print_time": False, "error_on_fail": False,
    # no relaxation of the actuator ranges: a returned K u must lie inside them
    "ipopt.bound_relax_factor": 0.0,
}


def _ipopt_options(settings: ControllerSettings) -> dict:
    opts = dict(_IPOPT_OPTS)
    opts["ipopt.tol"] = settings.ipopt_tol
    opts["ipopt.constr_viol_tol"] = settings.constraint_tol * 0.1
    opts["ipopt.max_iter"] = int(settings.max_iter)
    opts["ipopt.mu_strategy"] = "adaptive"
    opts["ipopt.mu_init"] = 1e-4  # starts are near-optimal seeds: a small barrier keeps them there
    return opts




def _unreachable(target: float, s: np.ndarray, model: str, lo: float, hi: float) -> UnreachableTargetError:
    """The error for a target outside the interval ``model`` reaches from state ``s``."""
    state = ", ".join(f"{v:g}" for v in s)
    return UnreachableTargetError(
        f"target {target!r} µm is unreachable from state [{state}]: the {model} reaches [{lo!r}, {hi!r}] µm")


# --------------------------------------------------------------------------- redundant set


class RedundantSet:
    """Null-space coordinates of the tool map over the workspace polytope (for seeding).

    With ``D = diag(u_hi - u_lo) / 2`` and ``u = D v``, the AFM tool constraint is
    ``(D w)·v = d``; ``v = v_hat d / |D w| + N c`` with N an orthonormal basis of the null
    space of ``D w``. The section of the workspace polytope by that plane is bounded by the
    crossings of the polytope's edges with the plane (vertices and edges precomputed).

    Parameters
    ----------
    afm : AnalyticForwardModel
    """

    def __init__(self, afm: AnalyticForwardModel):
        self.afm = afm
        ws = afm.workspace
        self.D = np.maximum((ws.u_hi - ws.u_lo) / 2.0, 1e-12)
        self.w = np.asarray(afm.w_pred, dtype=float)
        wt = self.D * self.w
        self.wt_norm = float(np.linalg.norm(wt))
        self.v_hat = wt / self.wt_norm
        # orthonormal complement of v_hat
        _, _, Vt = np.linalg.svd(self.v_hat[None, :])
        self.N = Vt[1:].T  # (n_p, n_p - 1)
        self.dir_u = self.D * self.v_hat  # moving u along D v_hat changes w·u by wt_norm per unit
        self.vertices, self.edges = self._polytope(afm)

    @staticmethod
    def _polytope(afm: AnalyticForwardModel) -> tuple[np.ndarray, np.ndarray]:
        """Vertices (m, n_p) of {lo <= K u <= hi} and edges as index pairs (e, 2)."""
        K, lo, hi = afm.K, afm.lo, afm.hi
        A = np.vstack([K, -K])
        b = np.concatenate([hi, -lo])
        n_p = K.shape[1]
        verts: list[np.ndarray] = []
        active: list[frozenset] = []
        for combo in itertools.combinations(range(A.shape[0]), n_p):
            Ac = A[list(combo)]
            if abs(np.linalg.det(Ac)) < 1e-12:
                continue
            v = np.linalg.solve(Ac, b[list(combo)])
            if np.all(A @ v <= b + 1e-9):
                act = frozenset(np.flatnonzero(np.abs(A @ v - b) <= 1e-9).tolist())
                if not any(np.allclose(v, w) for w in verts):
                    verts.append(v)
                    active.append(act)
        edges = [(i, j) for i, j in itertools.combinations(range(len(verts)), 2)
                 if len(active[i] & active[j]) >= n_p - 1
                 and np.linalg.matrix_rank(A[sorted(active[i] & active[j])]) >= n_p - 1]
        return np.array(verts), np.array(edges, dtype=int).reshape(-1, 2)

    def d_of_target(self, target: float) -> float:
        """Linear tool displacement d = w·u whose gauge reading is ``target`` (:meth:`Sensor.inverse`)."""
        return float(self.afm.sensor.inverse(target))

    def section_box(self, d: float) -> tuple[np.ndarray, np.ndarray] | None:
        """Bounding box of the plane section {w·u = d} of the workspace in c coordinates."""
        V = self.vertices
        vals = V @ self.w - d
        pts = [V[vals == 0.0]]
        i, j = self.edges[:, 0], self.edges[:, 1]
        cross = (vals[i] * vals[j]) < 0
        if np.any(cross):
            a, b = vals[i[cross]], vals[j[cross]]
            lam = (a / (a - b))[:, None]
            pts.append(V[i[cross]] + lam * (V[j[cross]] - V[i[cross]]))
        P = np.vstack(pts)
        if P.shape[0] == 0:
            return None
        C = (P / self.D) @ self.N
        return C.min(axis=0), C.max(axis=0)

    def grid(self, target: float, n: int, margin: float = 0.02) -> tuple[np.ndarray, tuple[int, ...]]:
        """Grid of u on the AFM plane section for ``target``.

        Returns
        -------
        U : ndarray, shape (n**(n_p-1), n_p)
            Grid points (row-major over the null axes), possibly outside the workspace.
        shape : tuple of int
            The grid's shape (for neighbour tests).
        """
        d = self.d_of_target(target)
        r = self.N.shape[1]
        v0 = self.v_hat * d / self.wt_norm
        if r == 0:
            return (self.D * v0)[None, :], (1,)
        box = self.section_box(d)
        if box is None:
            # beyond the AFM's range: grid the nearest section (Newton decides reachability)
            ends = self.vertices @ self.w
            box = self.section_box(float(np.clip(d, ends.min(), ends.max())))
        lo, hi = box
        pad = margin * np.maximum(hi - lo, 1e-9)
        axes = [np.linspace(a - p, b + p, n) for a, b, p in zip(lo, hi, pad)]
        C = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, r)
        V = v0[None, :] + C @ self.N.T
        return V * self.D, tuple([n] * r)


def _grid_local_minima(obj: np.ndarray, shape: tuple[int, ...]) -> np.ndarray:
    """Indices of grid points not larger than any finite neighbour (inf = infeasible)."""
    J = obj.reshape(shape)
    padded = np.pad(J, 1, constant_values=np.inf)
    is_min = np.isfinite(J)
    r = len(shape)
    for off in itertools.product((-1, 0, 1), repeat=r):
        if not any(off):
            continue
        sl = tuple(slice(1 + o, 1 + o + s) for o, s in zip(off, shape))
        is_min &= J <= padded[sl]
    return np.flatnonzero(is_min.ravel())


# --------------------------------------------------------------------------- base


class _BaseController:
    """Shared machinery: state parsing, range checks, IPOPT call and result assembly."""

    name = "base"

    def __init__(self, afm: AnalyticForwardModel, settings: ControllerSettings | None):
        self.afm = afm
        self.settings = settings or ControllerSettings()
        self.n_builds = 0  # how many NLP solvers this controller has built (test: once)

    def _state(self, state: np.ndarray | None) -> np.ndarray:
        if state is None:
            return self.afm.zero_state()
        s = np.asarray(state, dtype=float).ravel()
        if s.shape != (self.afm.n_s,) or not np.all(np.isfinite(s)):
            raise ConfigError(f"state must be {self.afm.n_s} finite numbers "
                              f"({', '.join(self.afm.state_names)}), got {np.asarray(state).tolist()}")
        return s

    def _in_range(self, u: np.ndarray) -> bool:
        q = self.afm.K @ u
        tol = self.settings.range_tol
        return bool(np.all(q >= self.afm.lo - tol) and np.all(q <= self.afm.hi + tol))

    def _q(self, u: np.ndarray) -> np.ndarray:
        return np.clip(self.afm.K @ u, self.afm.lo, self.afm.hi)

    @staticmethod
    def _run(solver: ca.Function, x0: np.ndarray, p: np.ndarray, lbx, ubx, lbg, ubg) -> tuple[np.ndarray, dict]:
        sol = solver(x0=x0, p=p, lbx=lbx, ubx=ubx, lbg=lbg, ubg=ubg)
        st = solver.stats()
        return np.array(sol["x"]).ravel(), {"status": st.get("return_status", "unknown"),
                                             "iter": int(st.get("iter_count", 0)),
                                             "success": bool(st.get("success", False))}


# --------------------------------------------------------------------------- EAFM controllers


class EAFMController(_BaseController):
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
        self.rset = RedundantSet(eafm.afm)
        self._solver: ca.Function | None = None
        self._range_solver: ca.Function | None = None
        self._last_attempts: dict = {"status": [], "iter": 0, "n": 0}
        self._build()

    def _objective_np(self, s: np.ndarray, U: np.ndarray, seeding: bool = False) -> np.ndarray:
        return self.objective.evaluate(self.eafm, s, U, seeding=seeding)

    # ---- NLP -------------------------------------------------------------------------
    def _build(self) -> None:
        """Build the IPOPT solver once: x = u, p = [t_d; s; J_ref] (eq. 4)."""
        afm = self.afm
        u = ca.MX.sym("u", afm.n_p)
        s = ca.MX.sym("s", afm.n_s)
        td = ca.MX.sym("t_d")
        jref = ca.MX.sym("J_ref")
        e = self.eafm.expressions(s, u, self.objective.needs)
        J = self.objective.mx(s, u, e, afm.K)
        g = ca.vertcat(e["t_mean"] - td, ca.mtimes(ca.DM(afm.K), u))  # eq. 4 constraint; lo <= K u <= hi
        nlp = {"x": u, "p": ca.vertcat(td, s, jref), "f": J / jref, "g": g}
        self._solver = ca.nlpsol(f"{self.name}_ipopt", "ipopt", nlp, _ipopt_options(self.settings))
        self._lbg = np.concatenate([[0.0], afm.lo])
        self._ubg = np.concatenate([[0.0], afm.hi])
        self.n_builds += 1

    def _range_nlp(self) -> ca.Function:
        if self._range_solver is None:
            afm = self.afm
            u = ca.MX.sym("u", afm.n_p)
            s = ca.MX.sym("s", afm.n_s)
            sign = ca.MX.sym("sign")
            t = self.eafm.expressions(s, u, ("t_mean",))["t_mean"]
            nlp = {"x": u, "p": ca.vertcat(s, sign), "f": sign * t, "g": ca.mtimes(ca.DM(afm.K), u)}
            self._range_solver = ca.nlpsol(f"{self.name}_range", "ipopt", nlp, _ipopt_options(self.settings))
        return self._range_solver

    def reachable_interval(self, state: np.ndarray | None = None) -> tuple[float, float]:
        """Interval of EAFM-mean tool poses reachable from ``state`` over the workspace (µm)."""
        s = self._state(state)
        V = self.rset.vertices
        tv, _ = self.eafm.mean_and_grad_u(s, V)
        out = []
        for sign in (1.0, -1.0):
            best = float(np.min(sign * tv))
            x0 = V[np.argmin(sign * tv)] * 0.999  # just inside (the origin is interior for Table I)
            x0 = x0 if self.afm.workspace.contains(x0) else V[np.argmin(sign * tv)]
            x, st = self._run(self._range_nlp(), x0, np.concatenate([s, [sign]]),
                              self.afm.workspace.u_lo, self.afm.workspace.u_hi, self.afm.lo, self.afm.hi)
            if st["success"] and self._in_range(x):
                best = min(best, float(sign * self.eafm.mean_and_grad_u(s, x[None, :])[0][0]))
            out.append(sign * best)
        return out[0], out[1]

    # ---- seeding ---------------------------------------------------------------------
    def _newton(self, s: np.ndarray, U: np.ndarray, target: float) -> tuple[np.ndarray, np.ndarray]:
        """Move each row of U along w onto t_mean(s, u) = target; return U and |residual|."""
        dirn = self.rset.dir_u
        U = U.copy()
        for _ in range(self.settings.newton_steps):
            t, dt = self.eafm.mean_and_grad_u(s, U)
            slope = dt @ dirn
            slope = np.where(np.abs(slope) > 1e-12, slope, 1e-12)
            U += ((target - t) / slope)[:, None] * dirn[None, :]
        t, _ = self.eafm.mean_and_grad_u(s, U)
        return U, np.abs(t - target)

    def _on_surface(self, s: np.ndarray, target: float, grid: int) -> tuple[np.ndarray, np.ndarray, tuple[int, ...]]:
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
            Un[near], res = self._newton(s, U[near], target)
            qn = Un[near] @ self.afm.K.T
            feas = (res <= 1e-6 * max(1.0, abs(target))) & np.all(
                (qn >= self.afm.lo) & (qn <= self.afm.hi), axis=1)
            idx = np.flatnonzero(near)[feas]
        return Un, idx, shape

    def _seeds(self, s: np.ndarray, target: float, grid: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Feasible seeds on the redundant set, their objective and the grid-local-minimum order."""
        Un, idx, shape = self._on_surface(s, target, grid)
        obj = np.full(Un.shape[0], np.inf)
        if idx.size:
            obj[idx] = self._objective_np(s, Un[idx], seeding=True)
        mins = _grid_local_minima(obj, shape)
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
            uw, rw = self._newton(s, np.asarray(u_init, dtype=float).reshape(1, -1), target)
            if self._in_range(uw[0]):
                starts.append(uw[0])
        if mins.size == 0 and not starts:
            lo, hi = self.reachable_interval(s)
            if not (lo - cfg.constraint_tol <= target <= hi + cfg.constraint_tol):
                raise _unreachable(target, s, "EAFM", lo, hi)
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
            u = self._refine(s, U[i], target)
            if u is not None:
                return self._result(s, target, u, f"{status}; fallback to seed", False, t0)
        raise SolveError(f"no valid control signal for target {target:g} µm (IPOPT: {status})")

    def _polish(self, s: np.ndarray, target: float, starts: list[np.ndarray], t0: float,
                prior: dict | None = None) -> ControlResult | None:
        attempts = {"status": list(prior["status"]) if prior else [], "iter": prior["iter"] if prior else 0,
                    "n": prior["n"] if prior else 0}
        best: tuple[float, np.ndarray, str] | None = None
        for u0 in starts:
            jref = float(self._objective_np(s, u0[None, :], seeding=True)[0])
            jref = jref if jref > 1e-300 else 1.0
            x, st = self._run(self._solver, u0, np.concatenate([[target], s, [jref]]),
                              self.afm.workspace.u_lo, self.afm.workspace.u_hi, self._lbg, self._ubg)
            attempts["status"].append(st["status"])
            attempts["iter"] += st["iter"]
            attempts["n"] += 1
            if not st["success"]:
                continue
            x = self._refine(s, x, target)
            if x is None:
                continue
            j = float(self._objective_np(s, x[None, :])[0])
            if best is None or j < best[0]:
                best = (j, x, st["status"])
        self._last_attempts = attempts
        if best is None:
            return None
        return self._result(s, target, best[1], best[2], True, t0)

    def _refine(self, s: np.ndarray, u: np.ndarray, target: float) -> np.ndarray | None:
        """Check (and if needed Newton-correct along w) the constraint residual and ranges."""
        t, _ = self.eafm.mean_and_grad_u(s, u[None, :])
        if abs(t[0] - target) > self.settings.constraint_tol:
            U, res = self._newton(s, u[None, :], target)
            if res[0] > self.settings.constraint_tol:
                return None
            u = U[0]
        return u if self._in_range(u) else None

    def _result(self, s: np.ndarray, target: float, u: np.ndarray, status: str, success: bool,
                t0: float) -> ControlResult:
        p = self.eafm.predict(s, u)
        a = self._last_attempts
        g, gv = float(p.g_mean[0]), float(p.g_var[0])
        return ControlResult(
            controller=self.name, target_um=target, state=s.copy(), u=u.copy(), q=self._q(u),
            predicted_um=float(p.t_mean[0]), predicted_std_um=float(math.sqrt(p.t_var[0])),
            objective=float(self._objective_np(s, u[None, :])[0]), status=status,
            iterations=int(a.get("iter", 0)), solve_time_s=time.perf_counter() - t0, success=success,
            constraint_residual=float(abs(p.t_mean[0] - target)), n_starts=int(a.get("n", 0)),
            noise_std_um=math.exp(0.5 * (g + 0.5 * gv)),
            noise_upper_std_um=math.exp(0.5 * (g + self.settings.kappa * math.sqrt(gv))),
        )

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

    def solve(self, target_um: float, state: np.ndarray | None = None, *,
              u_init: np.ndarray | None = None) -> ControlResult:
        """As :meth:`EAFMController.solve`; with a ``baseline`` controller, the result also says
        whether the chosen pose is credibly quieter than the baseline's (``vs_baseline``)."""
        res = super().solve(target_um, state, u_init=u_init)
        if self.baseline is None:
            return res
        return with_baseline(self.eafm, res, self.baseline, self.settings.credible_level)


class EAFMMeanController(EAFMController):
    """EAFM-mean baseline: ``min ||K u - q_prev||^2`` s.t. EAFM mean = target, in range.

    Parameters
    ----------
    eafm : EAFM
    settings : ControllerSettings, optional
    """

    def __init__(self, eafm: EAFM, settings: ControllerSettings | None = None):
        super().__init__(eafm, SmallestMotion(), settings, name="eafm_mean")


# --------------------------------------------------------------------------- comparing noise


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


def with_baseline(eafm: EAFM, res: ControlResult, baseline: Controller, level: float = 0.95) -> ControlResult:
    """``res`` with the ``baseline`` controller's result from the same state and whether ``res.u``
    is credibly quieter than the baseline's command (:func:`compare_noise`)."""
    b = baseline.solve(res.target_um, res.state)
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
    p = float(ndtr(-d / sd))
    return NoiseComparison(prob_quieter=p, log_ratio_mean=d, log_ratio_std=sd, credible=p >= level, level=level)


# --------------------------------------------------------------------------- AFM baseline


class AFMController(_BaseController):
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
        nlp = {"x": u, "p": p, "f": ca.sumsqr(Ku - p[1:]) / scale,
               "g": ca.vertcat(ca.dot(ca.DM(afm.w_pred), u) - p[0], Ku)}
        self._solver = ca.nlpsol("afm_ipopt", "ipopt", nlp, _ipopt_options(self.settings))
        self.n_builds += 1

    def solve(self, target_um: float, state: np.ndarray | None = None, *,
              u_init: np.ndarray | None = None) -> ControlResult:
        """AFM command for ``target_um`` from ``state`` (``u_init`` is ignored: convex)."""
        t0 = time.perf_counter()
        s = self._state(state)
        target = float(target_um)
        lo, hi = self._t_range
        if not (lo - self.settings.constraint_tol <= target <= hi + self.settings.constraint_tol):
            raise _unreachable(target, s, "AFM", lo, hi)
        d = self.rset.d_of_target(target)
        K, w, qp = self.afm.K, self.afm.w_pred, s[1:]
        # unconstrained-in-range minimiser of ||K u - q_prev||^2 on the plane w·u = d (KKT system)
        n = K.shape[1]
        kkt = np.block([[2 * K.T @ K, w[:, None]], [w[None, :], np.zeros((1, 1))]])
        u0 = np.linalg.solve(kkt, np.concatenate([2 * K.T @ qp, [d]]))[:n]
        x, st = self._run(self._solver, u0, np.concatenate([[d], qp]), self.afm.workspace.u_lo,
                          self.afm.workspace.u_hi, np.concatenate([[0.0], self.afm.lo]),
                          np.concatenate([[0.0], self.afm.hi]))
        ok = st["success"] and self._in_range(x) and abs(float(self.afm.t_of(x)) - target) <= self.settings.constraint_tol
        status = st["status"]
        if not ok:
            if self._in_range(u0) and abs(float(self.afm.t_of(u0)) - target) <= self.settings.constraint_tol:
                x, status = u0, f"{status}; fallback to seed"
            else:
                raise SolveError(f"AFM controller: no valid control signal for target {target:g} µm (IPOPT: {status})")
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

