"""Noise causes, fitted by maximum likelihood on the residual of the mean model.

Variance model of reading k (shared/spec/diagnosis.md, noise vocabulary)::

    v_k = σ₀² + Σ_{i ∈ F} (J_ki · s_i · |Δq_ki|)²

σ₀ is the ``homoscedastic`` base noise (gauge + driver accuracy), F the actuators with
``actuator_friction`` (stick-slip std s_i per µm moved), J_ki = ∂reading/∂q_act,i the
contact sensitivity of the fitted mean model at move k (:func:`microctl.stage.physics.tool_sensitivity`,
the same propagation the simulator's ``true_var`` uses). The log-likelihood
ℓ = −½ Σ (log 2π v_k + r_k²/v_k) is maximised over (log σ₀², s_i²) with L-BFGS-B and
analytic gradients; standard errors come from the expected Fisher information
I_ab = ½ Σ_k (∂v_k/∂a)(∂v_k/∂b)/v_k² (delta method to std units).

Friction causes are added greedily while ΔBIC < 0 and the likelihood-ratio test
(χ²₁, halved for the boundary s_i² = 0, Bonferroni over the actuators) has p < α. What is
left is checked with a Breusch–Pagan test of the standardised residual r/√v against
|Δq|, u and u²: significant → ``unexplained_heteroscedastic``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import stats
from scipy.optimize import minimize

from microctl.diagnosis.residuals import Test, breusch_pagan


@dataclass(frozen=True, eq=False)
class NoiseFit:
    """A fitted variance model.

    Attributes
    ----------
    friction : tuple of int
        1-based actuators with ``actuator_friction``.
    std_um : float
        Base (homoscedastic) std σ₀, µm.
    std_per_um : ndarray, shape (len(friction),)
        Friction coefficients s_i.
    stderr_std_um : float
    stderr_per_um : ndarray, shape (len(friction),)
    loglik : float
    n : int
    var : ndarray, shape (n,)
        Fitted variance of every reading, µm².
    """

    friction: tuple[int, ...]
    std_um: float
    std_per_um: np.ndarray
    stderr_std_um: float
    stderr_per_um: np.ndarray
    loglik: float
    n: int
    var: np.ndarray

    @property
    def k(self) -> int:
        """Number of variance parameters."""
        return 1 + len(self.friction)

    def variance(self, J: np.ndarray, dq: np.ndarray) -> np.ndarray:
        """The fitted variance model at other moves: σ₀² + Σ_{i∈F} (J_i s_i Δq_i)², µm², shape (m,).

        Parameters
        ----------
        J : ndarray, shape (m, n_q)
            Reading sensitivity to each actuator at those moves.
        dq : ndarray, shape (m, n_q)
            Their actuator steps, µm.
        """
        idx = [a - 1 for a in self.friction]
        return self.std_um**2 + np.sum((J[:, idx] * self.std_per_um * dq[:, idx]) ** 2, axis=1)

    @property
    def bic(self) -> float:
        """−2ℓ + k log n."""
        return -2.0 * self.loglik + self.k * np.log(self.n)


def fit_noise(resid: np.ndarray, J: np.ndarray, dq: np.ndarray, friction: tuple[int, ...] = ()) -> NoiseFit:
    """Maximum-likelihood variance model with friction on the actuators ``friction``.

    Parameters
    ----------
    resid : ndarray, shape (n,)
        Residual of the mean model, µm.
    J : ndarray, shape (n, n_q)
        Reading sensitivity to each actuator's actual displacement.
    dq : ndarray, shape (n, n_q)
        Actuator steps, µm.
    friction : tuple of int
        1-based actuators given friction.

    Returns
    -------
    NoiseFit
    """
    r2 = resid**2
    n = resid.size
    idx = [a - 1 for a in friction]
    G = (J[:, idx] * dq[:, idx]) ** 2  # (n, m): v = σ₀² + G @ b, b = s²

    def nll(x):
        s0, b = np.exp(x[0]), x[1:]
        v = s0 + G @ b
        v = np.maximum(v, 1e-300)
        f = 0.5 * np.sum(np.log(2 * np.pi * v) + r2 / v)
        dv = 0.5 * (1.0 / v - r2 / v**2)
        return f, np.concatenate([[np.sum(dv) * s0], G.T @ dv])

    v0 = float(np.mean(r2)) or 1e-12
    best = None
    for frac in (1.0, 0.3):
        gscale = np.maximum(np.mean(G, axis=0), 1e-12)
        x0 = np.concatenate([[np.log(v0 * frac)], (1 - frac + 0.1) * v0 / gscale / max(len(idx), 1)])
        res = minimize(nll, x0, jac=True, method="L-BFGS-B",
                       bounds=[(np.log(v0) - 30, np.log(v0) + 5)] + [(0.0, None)] * len(idx),
                       options={"maxiter": 500, "ftol": 1e-14, "gtol": 1e-10})
        if best is None or res.fun < best.fun:
            best = res
    s0, b = np.exp(best.x[0]), best.x[1:]
    v = s0 + G @ b
    # expected Fisher information in (σ₀², b): I = ½ Σ ∂v ∂vᵀ / v²
    dV = np.column_stack([np.ones(n), G])
    info = 0.5 * (dV / v[:, None] ** 2).T @ dV
    cov = np.linalg.pinv(info)
    se = np.sqrt(np.maximum(np.diag(cov), 0.0))
    std = np.sqrt(s0)
    s = np.sqrt(b)
    se_std = se[0] / (2 * std)  # delta method: d√x = dx / (2√x)
    with np.errstate(divide="ignore", invalid="ignore"):
        se_s = np.where(s > 0, se[1:] / (2 * np.where(s > 0, s, 1.0)), np.sqrt(se[1:]))
    return NoiseFit(tuple(friction), float(std), s, float(se_std), se_s, float(-best.fun), n, v)


@dataclass(frozen=True, eq=False)
class NoiseSelection:
    """Result of the greedy noise-cause selection.

    Attributes
    ----------
    fit : NoiseFit
        The accepted variance model.
    entries : list of dict
        Report entries (``cause``, ``params``, ``stderr``, ``delta_bic`` (as
        :data:`microctl.diagnosis.selection.DELTA_BIC`; 0 for the homoscedastic base model), ``equivalent``,
        ``accepted``), ranked best first.
    accepted : list of str
        Accepted noise causes, in order (``homoscedastic`` first).
    heteroscedasticity : Test
        Breusch–Pagan of the raw residual against |Δq_i| (before any noise model).
    leftover : Test
        Breusch–Pagan of the standardised residual after the accepted model.
    """

    fit: NoiseFit
    entries: list
    accepted: list
    heteroscedasticity: Test
    leftover: Test


def _variance_regressors(dq: np.ndarray, u: np.ndarray) -> np.ndarray:
    uz = (u - u.mean(0)) / np.where(u.std(0) > 0, u.std(0), 1.0)
    return np.column_stack([np.abs(dq), uz, uz**2])


def select_noise(resid: np.ndarray, J: np.ndarray, dq: np.ndarray, u: np.ndarray, *, alpha: float = 1e-3) -> NoiseSelection:
    """Greedy forward selection of noise causes by BIC (see the module docstring).

    Parameters
    ----------
    resid : ndarray, shape (n,)
    J : ndarray, shape (n, n_q)
    dq : ndarray, shape (n, n_q)
    u : ndarray, shape (n, n_p)
    alpha : float
        Significance level of each acceptance (after Bonferroni).
    """
    n_q = dq.shape[1]
    het = breusch_pagan(resid, np.abs(dq), "Breusch-Pagan (Koenker) of r² on abs(Δq_i)")
    current = fit_noise(resid, J, dq)
    entries = [{"cause": "homoscedastic", "params": {"std_um": current.std_um},
                "stderr": {"std_um": current.stderr_std_um}, "delta_bic": 0.0, "equivalent": [], "accepted": True}]
    accepted = ["homoscedastic"]
    tried: dict[int, NoiseFit] = {}
    while len(current.friction) < n_q:
        cands = {a: fit_noise(resid, J, dq, current.friction + (a,)) for a in range(1, n_q + 1)
                 if a not in current.friction}
        tried.update(cands)
        a_best = min(cands, key=lambda a: cands[a].bic)
        best = cands[a_best]
        lr = max(2 * (best.loglik - current.loglik), 0.0)
        p = min(0.5 * stats.chi2.sf(lr, 1) * len(cands), 1.0)
        if not (best.bic < current.bic and p < alpha):
            break
        d_bic = best.bic - current.bic
        current = best
        j = current.friction.index(a_best)
        entries.insert(len(accepted) - 1, {
            "cause": "actuator_friction", "params": {"actuator": a_best, "std_per_um": float(current.std_per_um[j])},
            "stderr": {"std_per_um": float(current.stderr_per_um[j])}, "delta_bic": float(d_bic),
            "p_value": float(p), "equivalent": [], "accepted": True})
        accepted.insert(len(accepted) - 1, "actuator_friction")
    # homoscedastic std of the final model
    entries[-1]["params"]["std_um"] = current.std_um
    entries[-1]["stderr"]["std_um"] = current.stderr_std_um
    # candidates not accepted: ΔBIC against the final model (their last fits are final + them)
    for a, f in sorted(tried.items(), key=lambda kv: kv[1].bic):
        if a in current.friction:
            continue
        j = f.friction.index(a)
        entries.append({"cause": "actuator_friction", "params": {"actuator": a, "std_per_um": float(f.std_per_um[j])},
                        "stderr": {"std_per_um": float(f.stderr_per_um[j])}, "delta_bic": float(f.bic - current.bic),
                        "equivalent": [], "accepted": False})
    z = resid / np.sqrt(current.var)
    left = breusch_pagan(z, _variance_regressors(dq, u), "Breusch-Pagan (Koenker) of standardised r² on abs(Δq), u, u²")
    if left.p_value < alpha:
        accepted.append("unexplained_heteroscedastic")
        entries.append({"cause": "unexplained_heteroscedastic", "params": {}, "stderr": {}, "delta_bic": None,
                        "p_value": left.p_value, "equivalent": [], "accepted": True})
    # order: accepted first (friction before homoscedastic as the stronger statement), then the rest
    entries.sort(key=lambda e: (not e["accepted"],))
    return NoiseSelection(current, entries, accepted, het, left)
