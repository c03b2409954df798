"""Objectives of the EAFM controllers, as objects (paper eq. 4 and the baselines).

An objective knows which EAFM quantities it needs (so the NLP graph holds only those),
builds its CasADi expression for IPOPT, and evaluates itself in NumPy at many candidate
poses for the controller's global seeding. :class:`~microctl.control.controller.EAFMController`
takes any object with this interface (:class:`Objective`).

The paper's objective (eq. 4) is ``1 - exp(-r_e(s, u))`` with ``r_e`` the noise variance.
The learned log noise variance g has a posterior ``N(mu_g, s_g^2)`` (VHGPR), so ``r_e =
exp(g)`` is log-normal; :class:`NoiseVariance` offers three summaries of it:

- ``noise_quantile`` (default): its upper quantile ``exp(mu_g + kappa s_g)`` (kappa = 1.645,
  the 95 % quantile). A pose is then preferred for low noise only where the data support
  it: where g is uncertain (few training moves, an actuator whose friction the data barely
  determined) its upper quantile is high, so eq. 4 cannot exploit an under-predicted noise
  there (the optimiser's curse: the minimum of noisy estimates is biased low).
- ``noise_mean``: ``exp(mu_g + s_g^2 / 2)``, the expected noise variance.
- ``noise_median``: ``exp(mu_g)``; ignores the uncertainty (O(n) per evaluation).

``epistemic=True`` adds f's posterior variance (the uncertainty of the mean correction) to
``r_e``, i.e. the expected squared error of the pose about the target.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import casadi as ca
import numpy as np

from microctl.models.eafm import EAFM
from microctl.util.fields import setting, validate_settings

__all__ = ["R_E_SETTINGS", "Objective", "NoiseVariance", "SmallestMotion"]

#: Summaries of the log-normal noise variance usable as r_e in eq. 4.
R_E_SETTINGS = ("noise_quantile", "noise_mean", "noise_median")

#: Above this much work (candidates x training points^2), seeding scores ``noise_quantile``
#: and ``noise_mean`` with g's parameter variance only (O(m n)), leaving the GP's O(m n^2)
#: variance term to IPOPT's polish of the best seeds (at the default 15 x 15 grid: n > ~520).
CHEAP_SEEDING_WORK = 6.0e7


@runtime_checkable
class Objective(Protocol):
    """What an EAFM controller minimises.

    Attributes
    ----------
    name : str
    needs : tuple of str
        EAFM quantities the expression uses (:meth:`microctl.models.eafm.EAFM.expressions`).
    """

    name: str
    needs: tuple[str, ...]

    def mx(self, s: ca.MX, u: ca.MX, e: dict, K: np.ndarray) -> ca.MX:
        """The objective as a CasADi expression of the state, the pose and the EAFM quantities."""
        ...

    def evaluate(self, eafm: EAFM, s: np.ndarray, U: np.ndarray, *, seeding: bool = False) -> np.ndarray:
        """The objective at the rows of U (shape (m, n_p)) from state s, shape (m,)."""
        ...


@dataclass(frozen=True)
class NoiseVariance:
    """eq. 4: ``1 - exp(-r_e)`` with r_e a summary of the predicted noise variance (module docstring).

    Attributes
    ----------
    r_e : str
        One of :data:`R_E_SETTINGS`.
    kappa : float
        Standard normal quantile of ``noise_quantile`` (1.645: 95 %).
    epistemic : bool
        Add f's posterior variance to r_e.
    """

    r_e: str = setting("noise_quantile", choices=R_E_SETTINGS)
    kappa: float = setting(1.645, lo=0.0, hi=5.0)
    epistemic: bool = setting(False)

    def __post_init__(self) -> None:
        validate_settings(self, "objective setting")

    @property
    def name(self) -> str:
        return self.r_e + ("+epistemic" if self.epistemic else "")

    @property
    def needs(self) -> tuple[str, ...]:
        return ("t_mean", "g_mean") + (("g_var",) if self.r_e != "noise_median" else ()) + (
            ("f_var",) if self.epistemic else ())

    def log_r(self, g_mean, g_var, sqrt):
        """log of the noise summary from g's mean and variance (NumPy or CasADi)."""
        if self.r_e == "noise_median":
            return g_mean
        if self.r_e == "noise_mean":
            return g_mean + 0.5 * g_var
        return g_mean + self.kappa * sqrt(g_var + 1e-12)

    def r_mx(self, s: ca.MX, u: ca.MX, e: dict, K: np.ndarray) -> ca.MX:
        """r_e (µm²) as a CasADi expression (the summed quantity of sequence control)."""
        r = ca.exp(self.log_r(e["g_mean"], e.get("g_var"), ca.sqrt))
        if self.epistemic:
            r = r + e["f_var"]
        return r

    def mx(self, s: ca.MX, u: ca.MX, e: dict, K: np.ndarray) -> ca.MX:
        return -ca.expm1(-self.r_mx(s, u, e, K))  # eq. 4: 1 - exp(-r_e)

    def r_np(self, eafm: EAFM, s: np.ndarray, U: np.ndarray, *, seeding: bool = False) -> np.ndarray:
        """r_e (µm²) at the rows of U, shape (m,)."""
        if self.r_e == "noise_median":
            r = np.exp(eafm.g_mean_np(s, U))  # O(m n): the median needs no variance
        else:
            cheap = seeding and U.shape[0] * float(eafm.n_train) ** 2 > CHEAP_SEEDING_WORK
            mean, var = eafm.g_np(s, U, with_gp_var=not cheap)
            r = np.exp(self.log_r(mean, var, np.sqrt))
        if self.epistemic:
            r = r + eafm.predict(s, U).f_var
        return r

    def r_pairs(self, eafm: EAFM, S: np.ndarray, U: np.ndarray, *, seeding: bool = False) -> np.ndarray:
        """r_e (µm²) of a move to each pose U[j] from each state S[i], shape (m1, m2).

        Row i equals ``r_np(eafm, S[i], U)`` (:meth:`EAFM.g_np_pairs`). With ``seeding`` and
        more than :data:`CHEAP_SEEDING_WORK` of work (m1 m2 n^2), the proxy of :meth:`r_np`:
        g's GP variance term left out (its parameter variance kept), and f's variance
        (``epistemic``) taken from the mean state of S for every row.

        Parameters
        ----------
        eafm : EAFM
        S : ndarray, shape (m1, n_s)
        U : ndarray, shape (m2, n_p)
        """
        S, U = np.atleast_2d(S), np.atleast_2d(U)
        cheap = seeding and S.shape[0] * U.shape[0] * float(eafm.n_train) ** 2 > CHEAP_SEEDING_WORK
        mean, var = eafm.g_np_pairs(S, U, with_gp_var=not cheap and self.r_e != "noise_median")
        r = np.exp(self.log_r(mean, var, np.sqrt))
        if self.epistemic:
            if cheap:
                r = r + eafm.predict(S.mean(axis=0), U).f_var[None, :]
            else:
                r = r + np.vstack([eafm.predict(s, U).f_var for s in S])
        return r

    def evaluate(self, eafm: EAFM, s: np.ndarray, U: np.ndarray, *, seeding: bool = False) -> np.ndarray:
        return -np.expm1(-self.r_np(eafm, s, U, seeding=seeding))


@dataclass(frozen=True)
class SmallestMotion:
    """The baselines' objective: ``||K u - q_prev||^2`` (µm²), the smallest actuator motion."""

    name: str = "smallest_motion"
    needs: tuple[str, ...] = ("t_mean",)

    def mx(self, s: ca.MX, u: ca.MX, e: dict, K: np.ndarray) -> ca.MX:
        return ca.sumsqr(ca.mtimes(ca.DM(K), u) - s[1:])

    def evaluate(self, eafm: EAFM, s: np.ndarray, U: np.ndarray, *, seeding: bool = False) -> np.ndarray:
        return np.sum((U @ eafm.afm.K.T - s[None, 1:]) ** 2, axis=1)
