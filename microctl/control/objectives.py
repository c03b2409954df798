"""Objectives of the EAFM controllers, as objects (paper eq. 4 and the baselines).

An objective knows which EAFM quantities it needs (so the NLP graph holds only those),
builds its CasADi expression for IPOPT, and evaluates itself in NumPy at many candidate
poses for the controller's global seeding. :class:`~microctl.control.controller.EAFMController`
takes any object with this interface (:class:`Objective`); sequence control
(:class:`~microctl.control.sequence.SequenceController`) takes one that is a monotone function
of a per-move quantity r (:class:`PerMoveObjective`), which it sums or maximises over the moves.

The paper's objective (eq. 4) is ``1 - exp(-r_e(s, u))`` with ``r_e`` a summary of the
log-normal noise variance (:class:`NoiseVariance`); the summaries (``noise_quantile``,
``noise_mean``, ``noise_median``) are the registered classes of
:mod:`microctl.control.noise_summaries`.

``epistemic=True`` (the default) adds f's posterior variance (the uncertainty of the mean
correction) to ``r_e``, i.e. the expected squared error of the pose about the target;
``epistemic=False`` is the paper's objective.

``alternatives=True`` adds the model-averaged extra noise variance of the noise sources the
data did not select (:mod:`microctl.models.alternatives`, ``EAFM.alt_var``): the expected
squared error averaged over the selected noise model and the alternatives the data cannot rule
out, so the optimum does not move an actuator far when a source on it is plausible but not
significant.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import casadi as ca
import numpy as np

from microctl.control.noise_summaries import R_E_SUMMARIES, NoiseSummary
from microctl.models.eafm import EAFM
from microctl.util.fields import setting, validate_settings

__all__ = ["Objective", "PerMoveObjective", "NoiseVariance", "SmallestMotion", "CHEAP_SEEDING_WORK"]

#: Above this much work (candidates x training points^2), seeding scores the summaries that use
#: g's variance with its parameter variance only (O(m n)), leaving the GP's O(m n^2) variance
#: term to IPOPT's polish of the best seeds (at the default 15 x 15 grid: n > ~520).
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


@runtime_checkable
class PerMoveObjective(Objective, Protocol):
    """An :class:`Objective` that is a monotone function of a per-move quantity r (µm², >= 0):
    what sequence control sums or maximises over the moves (eq. 4 is ``1 - exp(-r)``)."""

    def r_mx(self, s: ca.MX, u: ca.MX, e: dict, K: np.ndarray) -> ca.MX:
        """r as a CasADi expression (the per-move quantity of the sequence NLP)."""
        ...

    def r_np(self, eafm: EAFM, s: np.ndarray, U: np.ndarray, *, seeding: bool = False) -> np.ndarray:
        """r at the rows of U (shape (m, n_p)) from state s, shape (m,)."""
        ...

    def r_pairs(self, eafm: EAFM, S: np.ndarray, U: np.ndarray, *, seeding: bool = False) -> np.ndarray:
        """r of a move to each pose U[j] from each state S[i], shape (m1, m2) (row i = ``r_np`` from S[i])."""
        ...

    def of_r(self, r: np.ndarray) -> np.ndarray:
        """The objective's value for r (the monotone function; elementwise)."""
        ...


@dataclass(frozen=True)
class NoiseVariance:
    """eq. 4: ``1 - exp(-r_e)`` with r_e a summary of the predicted noise variance (module docstring).

    Attributes
    ----------
    r_e : str
        A name registered in :data:`~microctl.control.noise_summaries.R_E_SUMMARIES`.
    kappa : float
        Standard normal quantile of the summaries that use one (``noise_quantile``; 1.645: 95 %).
    epistemic : bool
        Add f's posterior variance to r_e (default: the expected squared error about the target
        is f's variance plus the noise's, so the controller does not park where f is
        extrapolated; issue 18).
    alternatives : bool
        Add the unselected noise sources' model-averaged variance (module docstring).
    """

    r_e: str = R_E_SUMMARIES.setting("noise_quantile")
    kappa: float = setting(1.645, lo=0.0, hi=5.0)
    epistemic: bool = setting(True)
    alternatives: bool = setting(False)

    def __post_init__(self) -> None:
        validate_settings(self, "objective setting")

    @property
    def summary(self) -> NoiseSummary:
        """The r_e summary object named by ``r_e``."""
        return R_E_SUMMARIES[self.r_e]()

    @property
    def name(self) -> str:
        return self.r_e + ("+epistemic" if self.epistemic else "") + ("+alternatives" if self.alternatives else "")

    @property
    def needs(self) -> tuple[str, ...]:
        return ("t_mean", "g_mean") + (("g_var",) if self.summary.needs_g_var else ()) + (
            ("f_var",) if self.epistemic else ()) + (("alt_var",) if self.alternatives else ())

    def r_mx(self, s: ca.MX, u: ca.MX, e: dict, K: np.ndarray) -> ca.MX:
        """r_e (µm²) as a CasADi expression (the summed quantity of sequence control)."""
        r = self.summary.mx(e["g_mean"], e.get("g_var"), self.kappa)
        if self.epistemic:
            r = r + e["f_var"]
        if self.alternatives:
            r = r + e["alt_var"]
        return r

    def mx(self, s: ca.MX, u: ca.MX, e: dict, K: np.ndarray) -> ca.MX:
        return -ca.expm1(-self.r_mx(s, u, e, K))  # eq. 4: 1 - exp(-r_e)

    def r_np(self, eafm: EAFM, s: np.ndarray, U: np.ndarray, *, seeding: bool = False) -> np.ndarray:
        """r_e (µm²) at the rows of U, shape (m,)."""
        cheap = seeding and U.shape[0] * float(eafm.n_train) ** 2 > CHEAP_SEEDING_WORK
        r = self.summary.at(eafm, s, U, self.kappa, cheap)
        if self.epistemic:
            r = r + eafm.f_var_np(s, U)
        if self.alternatives:
            r = r + eafm.alt_var(s, U)
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
        r = self.summary.pairs(eafm, S, U, self.kappa, cheap)
        if self.epistemic:
            if cheap:
                r = r + eafm.predict(S.mean(axis=0), U).f_var[None, :]
            else:
                r = r + np.vstack([eafm.predict(s, U).f_var for s in S])
        if self.alternatives:
            r = r + np.vstack([eafm.alt_var(s, U) for s in S])
        return r

    def of_r(self, r: np.ndarray) -> np.ndarray:
        """eq. 4's value ``1 - exp(-r)``, elementwise."""
        return -np.expm1(-np.asarray(r, dtype=float))

    def evaluate(self, eafm: EAFM, s: np.ndarray, U: np.ndarray, *, seeding: bool = False) -> np.ndarray:
        return self.of_r(self.r_np(eafm, s, U, seeding=seeding))


@dataclass(frozen=True)
class SmallestMotion:
    """The baselines' objective: ``||K u - q_prev||^2`` (µm²), the smallest actuator motion."""

    name: str = "smallest_motion"
    needs: tuple[str, ...] = ("t_mean",)

    def mx(self, s: ca.MX, u: ca.MX, e: dict, K: np.ndarray) -> ca.MX:
        return ca.sumsqr(ca.mtimes(ca.DM(K), u) - s[1:])

    def evaluate(self, eafm: EAFM, s: np.ndarray, U: np.ndarray, *, seeding: bool = False) -> np.ndarray:
        return np.sum((U @ eafm.afm.K.T - s[None, 1:]) ** 2, axis=1)
