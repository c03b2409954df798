"""Could the training readings have shown what a trained model gets wrong? The truth's evidence.

A rig the method fails is either one whose training data carry the structure the model missed
(the method's fault) or one whose data cannot tell the model from the truth (no method trained
on them could do better, short of knowing the answer). On a simulated rig the truth is known at
every training move: the reading's true mean m_i and variance v_i (the family's exact moments,
Monte Carlo where a ball may change contact). The model's predictive distribution of the same
reading is N(t_AFM,i + f_i, F_i + V_i) (f's posterior mean and variance, and the noise variance
E[exp(g)] = exp(g_mean + g_var / 2) that the controller's result states). The expected
log-likelihood ratio of the truth against the model, summed over the training moves,

    E = sum_i KL(N(m_i, v_i) || N(t_AFM,i + f_i, F_i + V_i))
      = sum_i 1/2 [log((F_i + V_i) / v_i) + (v_i + (m_i - t_AFM,i - f_i)^2) / (F_i + V_i) - 1]   (nats)

is how strongly the readings could reject the model in expectation. It is compared with the
evidence one candidate source must bring to enter the noise selection at the selection's level
with a Bonferroni correction over the candidates (a likelihood-ratio statistic of one parameter:
chi2(1) / 2 at alpha / m): below it the data cannot be expected to show the model's error
to any selection of this size. Above it they show that a better model of these data exists,
which does not make a failure the method's: the sum counts the model's errors at every training
move, not only those that decide the controller's choice.

``training_evidence`` replays the training moves on a fresh copy of the rig's stage with the
collection's seed (the stage is deterministic given its seed, so the replay passes through the
same states, which the family's truth reads: the actuators' last directions, the hinge's
nominal pose), the truth taken before each move.
"""

from __future__ import annotations

import math

import numpy as np
from scipy import stats

__all__ = ["training_evidence", "entry_evidence"]


def entry_evidence(alpha: float, candidates: int) -> float:
    """The log-likelihood gain (nats) one source needs to enter at family-wise level ``alpha``
    over ``candidates`` candidates (Bonferroni; one parameter)."""
    return 0.5 * float(stats.chi2.isf(alpha / max(candidates, 1), 1))


def training_evidence(stage, moves: np.ndarray, t_um: np.ndarray, data, model) -> dict:
    """The truth's expected evidence against ``model`` at the training moves (module docstring).

    Parameters
    ----------
    stage : FamilyStage or SimulatedStage
        A fresh stage with the seed the training moves were collected with (``true_mean``,
        ``true_var``, ``move``, ``state``).
    moves : ndarray, shape (n, n_p)
        The training commands, in the order they were executed.
    t_um : ndarray, shape (n,)
        The logged readings (y = t - t_AFM gives t_AFM).
    data : ResidualData
        The training data built from that log.
    model : FittedVHGPR
        The trained residual model.

    Returns
    -------
    dict
        ``evidence_nats`` (E), ``mean_part_nats`` (the part of E from the squared mean error),
        ``replay_max_dev_um`` (largest difference between the replayed and the logged readings:
        0 when the replay is faithful).
    """
    mean_t, var_t, t_re = [], [], []
    for u in np.atleast_2d(moves):
        s = stage.state
        mean_t.append(float(stage.true_mean(s, u)))
        var_t.append(float(stage.true_var(s, u)))
        t_re.append(stage.move(u).t_um)
    m, v = np.array(mean_t), np.array(var_t)
    p = model.predict(data.inputs_for(model))
    V = p.f_var + np.exp(p.g_mean + 0.5 * p.g_var)
    dm = (m - (np.asarray(t_um) - data.y)) - p.f_mean  # true mean of y = t - t_AFM, less f
    kl = 0.5 * (np.log(V / v) + (v + dm * dm) / V - 1.0)
    return {"evidence_nats": float(np.sum(kl)), "mean_part_nats": float(np.sum(0.5 * dm * dm / V)),
            "replay_max_dev_um": float(np.max(np.abs(np.array(t_re) - np.asarray(t_um)))) if len(t_re) else math.nan}
