"""What every controller on the AFM shares: state parsing, the range check of a command, the
clipped actuator commands, the IPOPT call and the error of an unreachable target."""

from __future__ import annotations

import casadi as ca
import numpy as np

from microctl.control.ipopt import run_ipopt
from microctl.control.settings import ControllerSettings
from microctl.errors import ConfigError, UnreachableTargetError
from microctl.models.afm import AnalyticForwardModel

__all__ = ["BaseController", "parse_state", "in_range", "unreachable"]


def unreachable(target: float, s: np.ndarray, model: str, lo: float, hi: float) -> UnreachableTargetError:
    """The error for a target outside the interval ``model`` reaches from state ``s``."""
    state = ", ".join(f"{v:g}" for v in s)
    return UnreachableTargetError(
        f"target {target!r} µm is unreachable from state [{state}]: the {model} reaches [{lo!r}, {hi!r}] µm")


def parse_state(afm: AnalyticForwardModel, state: np.ndarray | None) -> np.ndarray:
    """s = [t; q], shape (n_s,) (default the zero state); ConfigError unless n_s finite numbers."""
    if state is None:
        return afm.zero_state()
    s = np.asarray(state, dtype=float).ravel()
    if s.shape != (afm.n_s,) or not np.all(np.isfinite(s)):
        raise ConfigError(f"state must be {afm.n_s} finite numbers "
                          f"({', '.join(afm.state_names)}), got {np.asarray(state).tolist()}")
    return s


def in_range(afm: AnalyticForwardModel, u: np.ndarray, tol: float) -> bool:
    """``lo - tol <= K u <= hi + tol`` for the pose u, shape (n_p,)."""
    q = afm.K @ u
    return bool((q >= afm.lo - tol).all() and (q <= afm.hi + tol).all())


class BaseController:
    """Shared machinery: state parsing, range checks, IPOPT call and clipped actuator commands.

    Parameters
    ----------
    afm : AnalyticForwardModel
    settings : ControllerSettings or None
        Default :class:`ControllerSettings`.
    """

    name = "base"

    def __init__(self, afm: AnalyticForwardModel, settings: ControllerSettings | None):
        self.afm = afm
        self.settings = settings or ControllerSettings()
        self.n_builds = 0  # how many NLP solvers this controller has built (test: once)

    def _state(self, state: np.ndarray | None) -> np.ndarray:
        return parse_state(self.afm, state)

    def _in_range(self, u: np.ndarray) -> bool:
        return in_range(self.afm, u, self.settings.range_tol)

    def _q(self, u: np.ndarray) -> np.ndarray:
        return np.clip(self.afm.K @ u, self.afm.lo, self.afm.hi)

    @staticmethod
    def _run(solver: ca.Function, x0: np.ndarray, p: np.ndarray, lbx, ubx, lbg, ubg) -> tuple[np.ndarray, dict]:
        return run_ipopt(solver, x0, p, lbx, ubx, lbg, ubg)
