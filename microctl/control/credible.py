"""Is one pose credibly better than another in expected squared error? (the least-motion rule)

The expected squared error of a move about its target is ``r = f_var + exp(g)`` (the mean
correction's posterior variance plus the noise variance; eq. 4's r_e with ``epistemic``). The
model knows f_var at a pose; g, the log noise variance, it knows only as a Gaussian posterior
(notes/vhgpr.md, prediction; its joint at two poses is :meth:`microctl.models.eafm.EAFM.g_joint`,
the prior mean's parameter covariance included). So "pose a is better than pose b" is an
event with a posterior probability,

    P(f_var_a + exp(g_a) < f_var_b + exp(g_b)),   (g_a, g_b) ~ N(mean, cov),

computed here by Monte Carlo with fixed common draws (:data:`DRAWS`, :data:`SEED`: the same
call gives the same answer). With equal f_var it is ``Phi((mean_b - mean_a) / sd)``, the
probability :func:`~microctl.control.baseline.compare_noise` gives in closed form (tested).

That probability is conditional on the noise model the data selected. A source the selection
did not take can still be there at a size the data cannot rule out (a log of 125 moves does not
see a creep of 0.1 µm on one actuator), and g's posterior then says "flat, and certain". So the
comparison also averages over the alternatives: each candidate source j of the stage's
dictionary (:mod:`microctl.models.noise_dictionary`) added alone at its best size c_j, with
the likelihood gain G_j it had on the training residuals (``info["noise_selection"]
["alternatives"]`` of the model, computed at training; :func:`~microctl.models.noise_dictionary.
alternatives`). With BIC weights ``w_j = exp(G_j - log(n) / 2)`` against 1 for the selected
model, the expected extra squared error of pose a over pose b is

    E = sum_j w_j c_j (phi_j(a) - phi_j(b)) / (1 + sum_j w_j),

and the optimum a is returned instead of the least motion b only if ``r_a + E < r_b``: the lower
posterior expected squared error, averaged over the noise models (E =
``EAFM.alternatives.expected_excess``, :class:`~microctl.models.alternatives.Alternatives`,
re-exported here). With ``ControllerSettings.least_motion_credible`` the probability above must
also reach ``credible_level`` (the previous release's rule). A model file written before the
alternatives were stored has no E term.

Why the controller asks (``ControllerSettings.prefer_least_motion``): where the noise model has
no evidence that one redundant pose is quieter than another, eq. 4's optimum is decided by which
pose the training data cover best (g's and f's posterior variance are smallest there), and that
can be a pose far from where the actuators are, a long move for a gain the model itself cannot
tell from zero. Nearly every piezo scatter source that depends on the move grows with the
distance moved (stick-slip, creep, stiction past breakaway, the turning point of a hysteresis
loop), and E carries those the data did not select, so a long move must buy its gain against
them. Why not the probability as well: it is low wherever g's posterior at either pose is wide,
also where the data show that the least motion is the noisy one (a stick-slip actuator near a
ball's touchdown, the paper-scale rig), and there the least motion is the wrong default
(measured over the rig families and the paper-scale rig: ``scripts/bench_rigs.py --methods
default,credible``, docs/generated/bench_rigs.md and docs/generated/paper_scale.md).
"""

from __future__ import annotations

import numpy as np

from microctl.models.alternatives import Alternatives
from microctl.models.eafm import EAFM

__all__ = ["DRAWS", "SEED", "prob_lower", "prob_better", "Alternatives"]

#: Monte Carlo draws of (g_a, g_b) and their seed (standard error of a probability <= 0.008).
DRAWS, SEED = 4096, 20_261_126
_Z = np.random.default_rng(SEED).standard_normal((DRAWS, 2))


def prob_lower(mean: np.ndarray, cov: np.ndarray, f_var: np.ndarray) -> float:
    """``P(f_var[0] + exp(g[0]) < f_var[1] + exp(g[1]))`` for ``g ~ N(mean, cov)``.

    Parameters
    ----------
    mean : ndarray, shape (2,)
        Posterior mean of the log noise variance at the two poses.
    cov : ndarray, shape (2, 2)
        Its posterior covariance (symmetric positive semi-definite; round-off below zero is
        clipped).
    f_var : ndarray, shape (2,)
        The mean correction's posterior variance at the two poses, µm².

    Returns
    -------
    float
        In [0, 1]; ties count as not lower.
    """
    mean = np.asarray(mean, dtype=float).reshape(2)
    cov = np.asarray(cov, dtype=float).reshape(2, 2)
    f_var = np.asarray(f_var, dtype=float).reshape(2)
    w, V = np.linalg.eigh(0.5 * (cov + cov.T))
    root = V * np.sqrt(np.clip(w, 0.0, None))  # cov = root root^T
    # r = f_var + exp(mean + Z root^T), in one buffer (the same sums: addition commutes); each
    # column's scalar added alone (the same additions: a length-2 row broadcast down 4096 rows
    # runs numpy's inner loop 4096 times over 2 elements, several times slower)
    r = _Z @ root.T
    r0, r1 = r[:, 0], r[:, 1]
    r0 += mean[0]
    r1 += mean[1]
    np.exp(r, out=r)
    r0 += f_var[0]
    r1 += f_var[1]
    return np.count_nonzero(r0 < r1) / DRAWS  # the mean of the indicator, exactly


def prob_better(eafm: EAFM, state: np.ndarray, u_a: np.ndarray, u_b: np.ndarray) -> tuple[float, float, float]:
    """Posterior probability that pose ``u_a`` has a lower expected squared error than ``u_b``.

    Parameters
    ----------
    eafm : EAFM
    state : ndarray, shape (n_s,)
        The state both moves start from.
    u_a, u_b : ndarray, shape (n_p,)

    Returns
    -------
    p : float
        :func:`prob_lower` of the two poses.
    r_a, r_b : float
        Their posterior expected squared errors ``f_var + E[exp(g)] = f_var + exp(mu_g + s_g^2 / 2)``, µm².
    """
    s = np.asarray(state, dtype=float)
    U = np.vstack([np.asarray(u_a, dtype=float), np.asarray(u_b, dtype=float)])
    mean, cov, f_var = eafm.g_joint_and_f_var(s, U)
    r = f_var + np.exp(mean + 0.5 * np.diag(cov))
    return prob_lower(mean, cov, f_var), float(r[0]), float(r[1])
