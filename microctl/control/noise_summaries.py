"""The r_e summaries of eq. 4: what "the noise variance" of a move means to the controller.

The learned log noise variance g has a posterior ``N(mu_g, s_g^2)`` (VHGPR), so the noise
variance ``exp(g)`` is log-normal. A summary turns it into one number r_e (µm²). Each is a
class registered in :data:`R_E_SUMMARIES` under the name the settings use
(``ControllerSettings.r_e``, ``--r-e``), with its CasADi form (the IPOPT graph), its NumPy
form at many poses from one state (seeding) and its pairwise form (every state x every pose:
the sequence DP's transition costs):

- ``noise_quantile`` (default): the upper quantile ``exp(mu_g + kappa s_g)`` (kappa = 1.645,
  the 95 % quantile). A pose is then preferred for low noise only where the data support
  it: where g is uncertain (few training moves, an actuator whose friction the data barely
  determined) its upper quantile is high, so eq. 4 cannot exploit an under-predicted noise
  there (the optimiser's curse: the minimum of noisy estimates is biased low).
- ``noise_mean``: ``exp(mu_g + s_g^2 / 2)``, the expected noise variance.
- ``noise_median``: ``exp(mu_g)``; ignores the uncertainty (O(n) per evaluation).

A new summary is one subclass of :class:`NoiseSummary` with a ``name``, a ``description``
and :meth:`NoiseSummary.log_r`, decorated with ``@R_E_SUMMARIES.register``.
"""

from __future__ import annotations

from typing import Any, Callable, ClassVar

import casadi as ca
import numpy as np

from microctl.control.registry import Registry
from microctl.models.eafm import EAFM

__all__ = ["R_E_SUMMARIES", "NoiseSummary", "NoiseQuantile", "NoiseMean", "NoiseMedian"]

#: The r_e summaries by setting name (``ControllerSettings.r_e``).
R_E_SUMMARIES: Registry = Registry("r_e summary")


class NoiseSummary:
    """A summary r_e (µm²) of the log-normal noise variance ``exp(g)``, ``g ~ N(mu_g, s_g^2)``.

    Attributes
    ----------
    name : str
        The setting's name (``ControllerSettings.r_e``).
    description : str
        The formula in words (help texts, docs).
    needs_g_var : bool
        The summary uses g's variance ``s_g^2`` (else the graph and the NumPy forms skip it).
    uses_kappa : bool
        The summary uses the quantile ``kappa`` (``ControllerSettings.kappa``).
    """

    name: ClassVar[str]
    description: ClassVar[str]
    needs_g_var: ClassVar[bool] = True
    uses_kappa: ClassVar[bool] = False

    def log_r(self, g_mean: Any, g_var: Any, kappa: float, sqrt: Callable[[Any], Any]) -> Any:
        """log r_e from g's mean and variance, NumPy arrays or CasADi expressions alike.

        Parameters
        ----------
        g_mean, g_var : ndarray or casadi.MX
            Same shapes; ``g_var`` is None when ``needs_g_var`` is False (CasADi form).
        kappa : float
        sqrt : callable
            ``np.sqrt`` or ``ca.sqrt``.
        """
        raise NotImplementedError

    def mx(self, g_mean: ca.MX, g_var: ca.MX | None, kappa: float) -> ca.MX:
        """r_e as a CasADi expression of g's mean and variance (the IPOPT graph)."""
        return ca.exp(self.log_r(g_mean, g_var, kappa, ca.sqrt))

    def at(self, eafm: EAFM, s: np.ndarray, U: np.ndarray, kappa: float, cheap: bool) -> np.ndarray:
        """r_e at the rows of U (shape (m, n_p)) from state s, shape (m,).

        ``cheap``: g's GP variance term left out (its parameter variance kept), the seeding proxy.
        """
        mean, var = eafm.g_np(s, U, with_gp_var=not cheap)
        return np.exp(self.log_r(mean, var, kappa, np.sqrt))

    def pairs(self, eafm: EAFM, S: np.ndarray, U: np.ndarray, kappa: float, cheap: bool) -> np.ndarray:
        """r_e of a move to each pose U[j] (shape (m2, n_p)) from each state S[i] (shape (m1, n_s)),
        shape (m1, m2); row i equals :meth:`at` from S[i] (:meth:`EAFM.g_np_pairs`)."""
        mean, var = eafm.g_np_pairs(S, U, with_gp_var=not cheap and self.needs_g_var)
        return np.exp(self.log_r(mean, var, kappa, np.sqrt))


@R_E_SUMMARIES.register
class NoiseQuantile(NoiseSummary):
    """Upper quantile ``exp(mu_g + kappa s_g)`` (cautious where the noise model is uncertain)."""

    name = "noise_quantile"
    description = "exp(mu_g + kappa s_g): the upper kappa-quantile of the noise variance"
    uses_kappa = True

    def log_r(self, g_mean, g_var, kappa, sqrt):
        return g_mean + kappa * sqrt(g_var + 1e-12)


@R_E_SUMMARIES.register
class NoiseMean(NoiseSummary):
    """Expected noise variance ``exp(mu_g + s_g^2 / 2)``."""

    name = "noise_mean"
    description = "exp(mu_g + s_g^2 / 2): the expected noise variance"

    def log_r(self, g_mean, g_var, kappa, sqrt):
        return g_mean + 0.5 * g_var


@R_E_SUMMARIES.register
class NoiseMedian(NoiseSummary):
    """Median noise variance ``exp(mu_g)`` (ignores g's uncertainty; O(m n) per evaluation)."""

    name = "noise_median"
    description = "exp(mu_g): the median noise variance (ignores its uncertainty)"
    needs_g_var = False

    def log_r(self, g_mean, g_var, kappa, sqrt):
        return g_mean

    def at(self, eafm: EAFM, s: np.ndarray, U: np.ndarray, kappa: float, cheap: bool) -> np.ndarray:
        return np.exp(eafm.g_mean_np(s, U))  # O(m n): the median needs no variance
