"""Control with the hysteresis memory: the play states the model carries beside the state.

With ``hysteresis`` in ``stage.corrections`` the predicted reading at a command depends on the
play states before the move (:mod:`microctl.models.memory`), which the state s = [t; q_prev] of
eq. 3 does not hold. :class:`MemoryCompensated` wraps any controller (the optimal one, the AFM
or EAFM-mean baselines): the loop's reading shift ``σ(u) = sensor(w_pred.u + d_h(u, z)) -
sensor(w_pred.u)`` is piecewise linear and small (at most the loop's half-width times the tool
map), so the controller solves for the target ``t_d - σ`` and the shift is re-evaluated at its
answer until it no longer moves (a secant iteration on ``σ = σ(u*(t_d - σ))``). At the fixed point
the predicted reading with the loop is the target: eq. 4's constraint with the memory, without
changing the controller's graph (whose GP was trained on the residual with the loop taken out,
:func:`microctl.models.training.residual_dataset`).

A sequence controller's plan (``plan``) is wrapped the same way, the shift of every step run
along the planned commands (:meth:`MemoryCompensated.plan`).

Who moves the stage knows the command history and passes the play states (``memory=``):
:class:`microctl.api.Operator`, the experiments' runner and :meth:`MemoryCompensated.solve_sequence`
step them with every executed command (:meth:`~microctl.models.memory.ActuatorMemory.step`, from
the commands sent, never from the simulator's truth). Without them (``microctl solve`` from a
given state) the stage is taken to have come straight from the zero state to the state's q.
"""

from __future__ import annotations

import time
from dataclasses import replace

import numpy as np

from microctl.control.base import parse_state
from microctl.control.result import Controller, ControlResult, SequenceResult
from microctl.errors import SolveError
from microctl.models.afm import AnalyticForwardModel

__all__ = ["MemoryCompensated", "with_memory", "MEMORY_MAX_ITER", "MEMORY_TOL_UM"]

#: Most solves of the fixed-point iteration on the loop's shift (each a full controller solve).
MEMORY_MAX_ITER = 12
#: How far the loop's shift may still move when the iteration stops, µm (0.1 nm: a hundred times
#: below the quietest gauge the package has met). Each iteration re-solves the whole problem, so
#: the shift moves by the solver's own tolerance in u times the loop's slope; a plan's global
#: seeding can even switch between nearby optima, so ``constraint_tol`` (1e-8 µm) is not reached
#: reliably. The result's ``constraint_residual`` is measured with the loop, and stays within
#: this plus the controller's ``constraint_tol``.
MEMORY_TOL_UM = 1e-4


def with_memory(controller: Controller, afm: AnalyticForwardModel) -> Controller:
    """``controller`` wrapped in :class:`MemoryCompensated` when the AFM carries a hysteresis memory,
    else ``controller`` itself (no change at all for a stage without hysteresis corrections)."""
    if not afm.memory.active or isinstance(controller, MemoryCompensated):
        return controller
    return MemoryCompensated(controller, afm)


class MemoryCompensated:
    """A controller that meets the target with the hysteresis loop's memory (see the module).

    Parameters
    ----------
    inner : Controller
        Any controller on ``afm`` (``solve(target_um, state, *, u_init) -> ControlResult``).
    afm : AnalyticForwardModel
        Its ``memory`` must be active.
    """

    def __init__(self, inner: Controller, afm: AnalyticForwardModel):
        if not afm.memory.active:
            raise ValueError("MemoryCompensated needs an AFM with hysteresis corrections (afm.memory.active)")
        self.inner = inner
        self.afm = afm
        self.name = inner.name
        self.settings = getattr(inner, "settings", None)

    def __getattr__(self, item):  # the wrapped controller's other attributes (eafm, baseline, ...)
        if item == "inner":
            raise AttributeError(item)
        return getattr(self.inner, item)

    def default_memory(self, state: np.ndarray | None) -> np.ndarray:
        """Play states when none are given: one move from the zero state to the state's q."""
        s = parse_state(self.afm, state)
        return self.afm.memory.step(None, s[1:])

    def shift_um(self, z: np.ndarray, u: np.ndarray) -> float:
        """The loop's reading shift σ at pose u (n_p,) from the play states z, µm."""
        return self.afm.memory.shift_at(z, self.afm.K @ u)

    def solve(self, target_um: float, state: np.ndarray | None = None, *, u_init: np.ndarray | None = None,
              memory: np.ndarray | None = None) -> ControlResult:
        """The inner controller's answer for ``target_um`` with the loop's shift met.

        Parameters
        ----------
        target_um : float
        state : ndarray, shape (n_s,), optional
        u_init : ndarray, shape (n_p,), optional
        memory : ndarray, shape (n_q, N_PLAY), optional
            Play states before the move (default :meth:`default_memory`).

        Returns
        -------
        ControlResult
            ``predicted_um`` includes the loop (``hysteresis_um`` says by how much);
            ``success`` is False with the status saying so if the shift did not settle.

        Raises
        ------
        SolveError
            From the inner controller.
        """
        t0 = time.perf_counter()
        target = float(target_um)
        z = self.default_memory(state) if memory is None else self.afm.memory.check(memory)
        tol = MEMORY_TOL_UM
        sigma, u0 = 0.0, u_init
        hist: list[tuple[float, float]] = []  # (σ tried, F = σ(u*) - σ)
        res: ControlResult | None = None
        iters = 0
        for _ in range(MEMORY_MAX_ITER):
            res = self.inner.solve(target - sigma, state, u_init=u0)
            iters += res.iterations
            f = self.shift_um(z, res.u) - sigma
            hist.append((sigma, f))
            if abs(f) <= tol:
                break
            u0 = res.u
            sigma = _next_sigma(hist)
        if res is None:  # pragma: no cover - MEMORY_MAX_ITER >= 1
            raise SolveError("no solve was made")
        sig_u = hist[-1][0] + hist[-1][1]
        residual = abs(res.predicted_um + sig_u - target)
        ok = abs(hist[-1][1]) <= tol
        status = res.status if ok else (f"{res.status}; the hysteresis shift did not settle in "
                                        f"{MEMORY_MAX_ITER} solves (|Δ| = {abs(hist[-1][1]):.2g} µm)")
        return replace(res, target_um=target, predicted_um=res.predicted_um + sig_u, hysteresis_um=sig_u,
                       constraint_residual=residual, success=res.success and ok, status=status, iterations=iters,
                       solve_time_s=time.perf_counter() - t0)

    def plan(self, targets_um, state: np.ndarray | None = None, *, u_init: np.ndarray | None = None,
             memory: np.ndarray | None = None) -> SequenceResult:
        """A sequence controller's plan (``inner.plan``) with the loop's shift met at every step.

        The shift of step k depends on the play states the planned commands before it leave, so
        the plan is made for the targets ``t_k - σ_k``, the shifts are run along its commands
        from ``memory`` (default :meth:`default_memory`), and it is made again (warm-started) until
        no shift moves by more than the tolerance (at most :data:`MEMORY_MAX_ITER` plans).

        Returns
        -------
        SequenceResult
            Steps as :meth:`solve` returns them (``predicted_um`` with the loop, ``hysteresis_um``).
            Each step's ``state`` is the inner plan's: its t is the previous step's prediction
            without the loop (the residual GP's t_prev input is off by that step's shift).
        """
        t0 = time.perf_counter()
        targets = np.asarray(targets_um, dtype=float).reshape(-1)
        z0 = self.default_memory(state) if memory is None else self.afm.memory.check(memory)
        tol = MEMORY_TOL_UM
        sigma, u0, iters = np.zeros(targets.size), u_init, 0
        broyden = _Broyden(targets.size)
        for _ in range(MEMORY_MAX_ITER):
            res = self.inner.plan(targets - sigma, state, u_init=u0)
            iters += res.iterations
            shifts, z = np.empty(targets.size), z0
            for k, step in enumerate(res.steps):
                shifts[k] = self.shift_um(z, step.u)
                z = self.afm.memory.step(z, step.q)
            moved = float(np.max(np.abs(shifts - sigma)))
            if moved <= tol:
                break
            sigma, u0 = broyden.step(sigma, shifts - sigma), res.u
        ok = moved <= tol
        steps = tuple(replace(st, target_um=float(t), predicted_um=st.predicted_um + float(sh), hysteresis_um=float(sh),
                              constraint_residual=abs(st.predicted_um + float(sh) - float(t)))
                      for st, t, sh in zip(res.steps, targets, shifts))
        status = res.status if ok else (f"{res.status}; the hysteresis shifts did not settle in "
                                        f"{MEMORY_MAX_ITER} plans (|Δ| = {moved:.2g} µm)")
        return replace(res, steps=steps, targets_um=tuple(float(t) for t in targets), status=status,
                       success=res.success and ok, iterations=iters, solve_time_s=time.perf_counter() - t0)

    def solve_sequence(self, targets: list[float], states: list[np.ndarray] | None = None,
                       memory: np.ndarray | None = None) -> list[ControlResult]:
        """As :meth:`EAFMController.solve_sequence`, the play states stepped with each command
        (starting from ``memory``, default the zero state's)."""
        out: list[ControlResult] = []
        prev_u = None
        s = self.afm.zero_state()
        z = self.afm.memory.check(memory)
        for k, tgt in enumerate(targets):
            if states is not None:
                s = np.asarray(states[k], dtype=float)
            r = self.solve(tgt, s, u_init=prev_u, memory=z)
            out.append(r)
            prev_u = r.u
            z = self.afm.memory.step(z, r.q)
            s = np.concatenate([[r.predicted_um], r.q])
        return out


def _next_sigma(hist: list[tuple[float, float]]) -> float:
    """Next shift to try: the plain fixed-point step first, then secant steps on F(σ) = 0."""
    s1, f1 = hist[-1]
    if len(hist) < 2:
        return s1 + f1
    s0, f0 = hist[-2]
    if f1 == f0:
        return s1 + f1
    return s1 - f1 * (s1 - s0) / (f1 - f0)


class _Broyden:
    """Broyden's method on F(σ) = σ(u*(t - σ)) - σ for the T shifts of a plan: step k's shift
    depends on the planned commands before it, so F's Jacobian is lower triangular and the
    steps are coupled. Starts from J = -I (the first step is the plain fixed-point step)."""

    def __init__(self, n: int):
        self.J = -np.eye(n)
        self.last: tuple[np.ndarray, np.ndarray] | None = None

    def step(self, sigma: np.ndarray, F: np.ndarray) -> np.ndarray:
        if self.last is not None:
            ds, dF = sigma - self.last[0], F - self.last[1]
            nn = float(ds @ ds)
            if nn > 0:
                self.J = self.J + np.outer(dF - self.J @ ds, ds) / nn
        self.last = (sigma, F)
        try:
            return sigma - np.linalg.solve(self.J, F)
        except np.linalg.LinAlgError:
            return sigma + F
