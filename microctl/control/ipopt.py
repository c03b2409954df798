"""IPOPT as the controllers use it: the solver options and one call of a built ``nlpsol``."""

from __future__ import annotations

import casadi as ca
import numpy as np

__all__ = ["ipopt_options", "run_ipopt"]

_IPOPT_OPTS = {
    "ipopt.print_level": 0, "ipopt.sb": "yes", "print_time": False, "error_on_fail": False,
    # no relaxation of the actuator ranges: a returned K u must lie inside them
    "ipopt.bound_relax_factor": 0.0,
}


def ipopt_options(settings) -> dict:
    """``nlpsol`` options from :class:`~microctl.control.settings.ControllerSettings` (tolerances, iterations)."""
    opts = dict(_IPOPT_OPTS)
    opts["ipopt.tol"] = settings.ipopt_tol
    opts["ipopt.constr_viol_tol"] = settings.constraint_tol * 0.1
    opts["ipopt.max_iter"] = int(settings.max_iter)
    opts["ipopt.mu_strategy"] = "adaptive"
    opts["ipopt.mu_init"] = 1e-4  # starts are near-optimal seeds: a small barrier keeps them there
    return opts


def run_ipopt(solver: ca.Function, x0: np.ndarray, p: np.ndarray, lbx, ubx, lbg, ubg) -> tuple[np.ndarray, dict]:
    """One IPOPT run: the solution x, shape (n_x,), and ``{"status", "iter", "success"}``."""
    sol = solver(x0=x0, p=p, lbx=lbx, ubx=ubx, lbg=lbg, ubg=ubg)
    st = solver.stats()
    return np.array(sol["x"]).ravel(), {"status": st.get("return_status", "unknown"),
                                         "iter": int(st.get("iter_count", 0)),
                                         "success": bool(st.get("success", False))}
