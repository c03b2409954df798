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

Where a rig fails on the mean, ``mean_error_parts`` asks whether the model's form or the training
noise's draw made the error. f's posterior mean at a pose x* is linear in the training outputs,
``f(x*) = w . y`` with ``w = 1/n + (I - 1 1^T / n) (K_f + R)^-1 k_f(X, x*)`` (the exact posterior of
notes/vhgpr.md with y standardised by its mean; the scale cancels), its hyperparameters held at
their fitted values. With the truth's noise-free residuals y_true (the replay's true means less
the AFM) in place of y, the error f(x*) - y_true(x*) splits exactly into

    bias  = w . y_true - y_true(x*)     what the model's form and weights leave with noise-free data
    noise = w . (y - y_true)            what the training readings' noise draws add,

the noise part with standard deviation ``sqrt(sum_i w_i^2 v_i)`` under the truth's variances v.
A mean failure with a small bias part and a noise part of a few standard deviations is the
data's draw: an estimator of this form trained on these readings would have made it. (The
hyperparameters and the selected noise sources were fitted to the same draws; the split holds
them fixed.)

What did the noise model's weighting cost? The same form with the truth's variances in place of
the model's R, ``w* = 1/n + (I - 1 1^T / n) (K_f + V)^-1 k_f(X, x*)`` (``f_weights(..., noise_var=v)``),
weighs the readings as the truth would (for the trend, generalised least squares with the true
weights: the best linear unbiased estimate): ``sqrt(sum_i w*_i^2 v_i)`` against the model's own
noise-part std says how much.

Could the noise model's sources have described the truth's scatter at all? ``dictionary_fit``
fits the truth's variances v_i at the training moves by a floor plus non-negative multiples of
the candidate sources (non-negative least squares on v_fit / v - 1, so every move counts by its
relative error, as in a likelihood), once with every candidate of the dictionary and once with
the selected ones. A small relative error with every candidate and a large one with the selected
ones says the dictionary holds the shape and the selection missed it (from these draws: the
readings scatter about v); a large error with every candidate says the dictionary lacks the
shape. The fit is to noise-free variances, and with many candidates and few moves it can
describe more than a selection of a few sources could: it bounds what the dictionary offers.
Neither reading is by itself a failure's cause (a controller needs the scatter ranked at the
poses it compares, not described at every training move): ``scripts/bench_rigs.py`` counts the
same class over the passing rigs as its base rate.
"""

from __future__ import annotations

import math

import numpy as np
from scipy import stats

__all__ = ["training_evidence", "entry_evidence", "replay_truth", "f_weights", "mean_error_parts", "dictionary_fit"]


def entry_evidence(alpha: float, candidates: int) -> float:
    """The log-likelihood gain (nats) one source needs to enter at family-wise level ``alpha``
    over ``candidates`` candidates (Bonferroni; one parameter)."""
    return 0.5 * float(stats.chi2.isf(alpha / max(candidates, 1), 1))


def replay_truth(stage, moves: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Replay the training moves on ``stage`` (a fresh stage with the collection's seed): the true
    mean and variance of each reading, taken before its move, and the replayed readings, each (n,)."""
    mean_t, var_t, t_re = [], [], []
    for u in np.atleast_2d(moves):
        s = stage.state
        mean_t.append(float(stage.true_mean(s, u)))
        var_t.append(float(stage.true_var(s, u)))
        t_re.append(stage.move(u).t_um)
    return np.array(mean_t), np.array(var_t), np.array(t_re)


def training_evidence(stage, moves: np.ndarray, t_um: np.ndarray, data, model,
                      truth: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None) -> dict:
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
    truth : tuple of ndarray, optional
        :func:`replay_truth` of ``stage`` and ``moves`` when the caller has it (``stage`` is
        then not moved).

    Returns
    -------
    dict
        ``evidence_nats`` (E), ``mean_part_nats`` (the part of E from the squared mean error),
        ``replay_max_dev_um`` (largest difference between the replayed and the logged readings:
        0 when the replay is faithful).
    """
    m, v, t_re = replay_truth(stage, moves) if truth is None else truth
    p = model.predict(data.inputs_for(model))
    V = p.f_var + np.exp(p.g_mean + 0.5 * p.g_var)
    dm = (m - (np.asarray(t_um) - data.y)) - p.f_mean  # true mean of y = t - t_AFM, less f
    kl = 0.5 * (np.log(V / v) + (v + dm * dm) / V - 1.0)
    return {"evidence_nats": float(np.sum(kl)), "mean_part_nats": float(np.sum(0.5 * dm * dm / V)),
            "replay_max_dev_um": float(np.max(np.abs(np.array(t_re) - np.asarray(t_um)))) if len(t_re) else math.nan}


def f_weights(model, y: np.ndarray, x_star: np.ndarray, noise_var: np.ndarray | None = None) -> np.ndarray | None:
    """The weights w of f's posterior mean at ``x_star`` in the training outputs: ``f(x*) = w . y``
    (module docstring), shape (n,); None for a model without the exact posterior, fitted to
    another number of rows than y has (a reading set aside), or whose mean the weights do not
    reproduce (to 1e-6 of y's spread).

    Parameters
    ----------
    model : FittedVHGPR
    y : ndarray, shape (n,)
        The training outputs the model was fitted to.
    x_star : ndarray, shape (d,)
        The pose's input as the model reads it ([s; u], then the context if the model has one).
    noise_var : ndarray, shape (n,), optional
        The readings' noise variances (units of y²) to weigh them by instead of the model's R:
        the weights of f's form told the true variances (the check against f is then skipped).
    """
    post = model.posterior
    if getattr(model, "posterior_form", "exact") != "exact" or post.X.shape[0] != len(y):
        return None
    k = post.train_rows("f", post.standardise(np.atleast_2d(np.asarray(x_star, dtype=float))))[0]
    if noise_var is None:
        Li = post.chol_inverse("f")
        a = Li.T @ (Li @ k)  # (K_f + R)^-1 k_f(X, x*), standardised units: y's scale cancels
    else:  # K_f at the training inputs (post.X: standardised) plus the given variances, standardised
        Kf = post.train_rows("f", post.X)
        a = np.linalg.solve(Kf + np.diag(np.asarray(noise_var, dtype=float) / model.y_scale ** 2), k)
    n = len(y)
    w = np.full(n, 1.0 / n) + a - a.sum() / n
    if noise_var is not None:
        return w
    f_star = float(model.predict(np.atleast_2d(x_star)).f_mean[0])
    # the inverse's round-off is far below this; a wrong form (another y_mean, a sparse posterior) is not
    return w if abs(float(w @ y) - f_star) <= 1e-6 * (float(np.std(y)) + abs(f_star)) + 1e-12 else None


def mean_error_parts(w: np.ndarray, y: np.ndarray, y_true: np.ndarray, var_true: np.ndarray,
                     y_true_star: float) -> dict:
    """f's error at a pose split into its bias and noise parts (module docstring).

    Parameters
    ----------
    w : ndarray, shape (n,)
        :func:`f_weights` at the pose.
    y, y_true, var_true : ndarray, shape (n,)
        The training residuals, the truth's noise-free residuals and the readings' true variances.
    y_true_star : float
        The truth's residual at the pose.

    Returns
    -------
    dict
        ``bias_um``, ``noise_um`` (they sum to f's error ``w . y - y_true_star``) and
        ``noise_std_um`` (the noise part's standard deviation under the truth).
    """
    w, y, y_true, v = (np.asarray(a, dtype=float) for a in (w, y, y_true, var_true))
    return {"bias_um": float(w @ y_true - y_true_star), "noise_um": float(w @ (y - y_true)),
            "noise_std_um": float(math.sqrt(float(np.sum(w * w * v))))}


def dictionary_fit(var_true: np.ndarray, candidates: np.ndarray, selected) -> dict:
    """How closely a floor and non-negative multiples of the candidate sources describe the truth's
    variances at the training moves (module docstring): with every candidate, and with the
    selected ones.

    Parameters
    ----------
    var_true : ndarray, shape (n,)
        The readings' true variances (µm², > 0).
    candidates : ndarray, shape (n, P)
        Every candidate source at the training moves (non-negative).
    selected : sequence of int
        Columns of ``candidates`` the noise selection chose (may be empty: the floor alone).

    Returns
    -------
    dict
        ``all_rel_rms`` and ``selected_rel_rms``: the root mean square of ``v_fit / v - 1`` over
        the moves for each fit.
    """
    from scipy.optimize import nnls

    v = np.asarray(var_true, dtype=float)
    Phi = np.asarray(candidates, dtype=float).reshape(len(v), -1)

    def rel_rms(cols) -> float:
        A = np.column_stack([np.ones(len(v)), Phi[:, list(cols)]]) / v[:, None]
        scale = np.maximum(np.max(np.abs(A), axis=0), 1e-300)  # columns of unit size: nnls's conditioning
        c, _ = nnls(A / scale, np.ones(len(v)), maxiter=50 * A.shape[1])
        return float(np.sqrt(np.mean(((A / scale) @ c - 1.0) ** 2)))

    return {"all_rel_rms": rel_rms(range(Phi.shape[1])), "selected_rel_rms": rel_rms(selected)}
