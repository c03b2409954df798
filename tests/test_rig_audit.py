"""scripts/rig_audit.py: the truth's evidence against a model at its training moves.

Checked against sums worked out here from the Gaussian KL divergence, on a stand-in stage with
a known mean and variance and a stand-in model with given predictions; and against the scipy
quantile for the entry level.
"""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest
from script_loader import load_script

from microctl.models.training import ResidualData


def _audit():
    return load_script("rig_audit")


class _Stage:
    """A stage whose next reading has mean 2 u_0 + t_prev / 10 and variance 0.01 (1 + u_0^2); a
    move reads its mean plus a seeded draw."""

    def __init__(self, seed):
        self.state = np.zeros(2)
        self.rng = np.random.default_rng(seed)

    def true_mean(self, s, u):
        return 2.0 * u[0] + s[0] / 10.0

    def true_var(self, s, u):
        return 0.01 * (1.0 + u[0] ** 2)

    def move(self, u):
        t = self.true_mean(self.state, u) + math.sqrt(self.true_var(self.state, u)) * self.rng.standard_normal()
        self.state = np.array([t, u[0]])
        return SimpleNamespace(t_um=t)


class _Model:
    n_context = 0

    def __init__(self, f_mean, f_var, g_mean, g_var):
        self.p = SimpleNamespace(f_mean=np.asarray(f_mean), f_var=np.asarray(f_var), g_mean=np.asarray(g_mean),
                                 g_var=np.asarray(g_var))

    def predict(self, X):
        return self.p


def _logged(moves, seed):
    stage, t, m, v = _Stage(seed), [], [], []
    for u in moves:
        m.append(stage.true_mean(stage.state, u))
        v.append(stage.true_var(stage.state, u))
        t.append(stage.move(u).t_um)
    return np.array(t), np.array(m), np.array(v)


def test_evidence_is_the_summed_gaussian_kl_and_zero_for_the_truth():
    audit = _audit()
    moves = np.array([[0.5], [1.5], [-1.0], [2.0]])
    t, m, v = _logged(moves, 3)
    t_afm = 1.9 * moves[:, 0]  # a wrong AFM: y = t - t_afm
    data = ResidualData(X=np.zeros((4, 3)), y=t - t_afm, x_names=("t_prev", "q_prev", "u"))
    # the truth as the model: f = m - t_afm exactly, no f variance, noise exp(g) = v exactly
    exact = _Model(m - t_afm, np.zeros(4), np.log(v), np.zeros(4))
    out = audit.training_evidence(_Stage(3), moves, t, data, exact)
    assert out["evidence_nats"] == pytest.approx(0.0, abs=1e-12)
    assert out["replay_max_dev_um"] == 0.0  # the same seed: the replay meets the logged readings
    # a model off in the mean by 0.1 µm and in the variance by a factor 2 at every move:
    # each move adds 1/2 [log 2 + (v + 0.01) / (2 v) - 1]
    off = _Model(m - t_afm + 0.1, np.zeros(4), np.log(2 * v), np.zeros(4))
    out = audit.training_evidence(_Stage(3), moves, t, data, off)
    hand = sum(0.5 * (math.log(2.0) + (vi + 0.01) / (2 * vi) - 1.0) for vi in v)
    assert out["evidence_nats"] == pytest.approx(hand, rel=1e-12)
    assert out["mean_part_nats"] == pytest.approx(sum(0.5 * 0.01 / (2 * vi) for vi in v), rel=1e-12)
    # f's variance and g's variance enter the predictive variance: F + exp(g_mean + g_var / 2)
    wide = _Model(m - t_afm, np.full(4, 0.02), np.log(v) - 0.5, np.ones(4))
    out = audit.training_evidence(_Stage(3), moves, t, data, wide)
    hand = sum(0.5 * (math.log((0.02 + vi) / vi) + vi / (0.02 + vi) - 1.0) for vi in v)
    assert out["evidence_nats"] == pytest.approx(hand, rel=1e-12)


def test_a_replay_with_another_seed_is_reported():
    audit = _audit()
    moves = np.array([[0.5], [1.5]])
    t, m, v = _logged(moves, 3)
    data = ResidualData(X=np.zeros((2, 3)), y=t, x_names=("t_prev", "q_prev", "u"))
    out = audit.training_evidence(_Stage(4), moves, t, data, _Model(m, np.zeros(2), np.log(v), np.zeros(2)))
    assert out["replay_max_dev_um"] > 1e-3


def test_entry_level_is_the_bonferroni_chi2_quantile():
    audit = _audit()
    assert audit.entry_evidence(0.05, 1) == pytest.approx(0.5 * 3.841458820694124, rel=1e-9)
    # alpha / m = 0.05 / 80 = 6.25e-4: chi2(1) quantile 11.70 (two-sided normal z = 3.4205)
    assert audit.entry_evidence(0.05, 80) == pytest.approx(0.5 * 3.4205 ** 2, rel=1e-3)


# ---- f's error split into the part noise-free data leave and the noise draw's part ------------

def _fitted(se: str, seed: int = 5, n: int = 60):
    """A VHGPR fit (bias, linear trend, f's SE part ``se``) to affine data with heteroscedastic noise."""
    from microctl.gp.vhgpr import VHGPR

    rng = np.random.default_rng(seed)
    X = rng.uniform(-1, 1, (n, 2))
    y_true = 0.4 + 1.5 * X[:, 0] - 0.7 * X[:, 1]
    v = (0.05 + 0.2 * (X[:, 0] > 0)) ** 2
    y = y_true + np.sqrt(v) * rng.standard_normal(n)
    return VHGPR(bias=True, linear=True, linear_prior_var=10.0, se=se, n_restarts=1).fit(X, y), X, y, y_true, v


@pytest.mark.parametrize("se", ["off", "on"])
def test_f_weights_are_the_linear_map_from_the_training_outputs_to_f(se):
    """w . y' is f at x* for any outputs y' with the hyperparameters held: checked against the
    package's own prediction of a model whose f weights are re-solved for y' (scipy's Cholesky
    solve with the model's factor, not the inverse the weights use)."""
    from dataclasses import replace

    from scipy.linalg import cho_solve

    audit = _audit()
    model, X, y, _, _ = _fitted(se)
    rng = np.random.default_rng(11)
    y2 = y + rng.normal(0.0, 0.5, y.size)
    L = np.asarray(model.f_chol)
    other = replace(model, y_mean=float(np.mean(y2)),
                    f_alpha=cho_solve((L, True), (y2 - np.mean(y2)) / model.y_scale))
    for x_star in (np.array([0.3, -0.2]), np.array([1.4, 1.2]), X[7]):
        w = audit.f_weights(model, y, x_star)
        assert w is not None
        assert float(w @ y) == pytest.approx(float(model.predict(x_star[None, :]).f_mean[0]), abs=1e-9)
        assert float(w @ y2) == pytest.approx(float(other.predict(x_star[None, :]).f_mean[0]), abs=1e-8)
        assert float(np.sum(w)) == pytest.approx(1.0, abs=1e-12)  # a constant added to y moves f by it


def test_on_affine_truth_the_bias_part_vanishes_and_the_noise_part_is_the_error():
    """The truth is affine and f has a vague affine trend: with the noise-free residuals f
    reproduces it to the trend prior's shrinkage (|bias| <= 1e-3 of the truth's spread); the
    parts sum to f's error exactly, and the noise part's std is the hand sum sqrt(sum w_i^2 v_i)."""
    audit = _audit()
    model, X, y, y_true, v = _fitted("off")
    x_star = np.array([0.9, -0.8])
    truth_star = 0.4 + 1.5 * 0.9 + 0.7 * 0.8
    w = audit.f_weights(model, y, x_star)
    parts = audit.mean_error_parts(w, y, y_true, v, truth_star)
    f_err = float(model.predict(x_star[None, :]).f_mean[0]) - truth_star
    assert parts["bias_um"] + parts["noise_um"] == pytest.approx(f_err, abs=1e-9)
    assert abs(parts["bias_um"]) <= 1e-3 * np.ptp(y_true)
    assert abs(parts["noise_um"]) > 1e-3  # the split is not trivially zero
    assert parts["noise_std_um"] == pytest.approx(math.sqrt(sum(wi * wi * vi for wi, vi in zip(w, v))), rel=1e-12)


def test_f_weights_refuse_outputs_the_model_was_not_fitted_to():
    """A y of another length (a reading set aside) or another y (the weights would not reproduce
    f) gives None, not a wrong split."""
    audit = _audit()
    model, X, y, _, _ = _fitted("off")
    assert audit.f_weights(model, y[:-1], X[0]) is None
    assert audit.f_weights(model, y + 1.0 + y ** 2, X[0]) is None


def test_weights_told_the_models_own_variances_are_its_weights_and_the_true_ones_do_no_worse():
    """``noise_var`` replaces the model's R in K_f + R: told the model's own R (read off its factor,
    whose off-diagonal is K_f's: checked) the weights are the model's; told the truth's variances
    on an affine truth (f's trend with a vague prior: generalised least squares) the noise part's
    std is at most the model's (the true weights are the best linear ones; 1 % for the prior's
    shrinkage)."""
    audit = _audit()
    model, X, y, _, v = _fitted("off")
    post = model.posterior
    L = np.asarray(model.f_chol)
    Kf = post.train_rows("f", post.X)
    R = L @ L.T - Kf
    np.testing.assert_allclose(R - np.diag(np.diag(R)), 0.0, atol=1e-8 * np.max(np.abs(Kf)))
    for x_star in (np.array([0.9, -0.8]), X[3]):
        w = audit.f_weights(model, y, x_star)
        w_own = audit.f_weights(model, y, x_star, noise_var=np.diag(R) * model.y_scale ** 2)
        np.testing.assert_allclose(w_own, w, atol=1e-8)
        w_best = audit.f_weights(model, y, x_star, noise_var=v)
        assert np.sum(w_best ** 2 * v) <= 1.01 * np.sum(w ** 2 * v)


def test_dictionary_fit_recovers_a_planted_combination_and_the_floor_alone_has_its_closed_form():
    """A truth whose variance is a floor plus two of six candidate columns is described exactly by
    every candidate and by those two; by the floor alone the relative error is the closed form of a
    least-squares constant c on c / v - 1 (c = sum 1/v / sum 1/v^2), worked out here."""
    rng = np.random.default_rng(5)
    Phi = rng.uniform(0.0, 1.0, (150, 6)) ** 2
    v = 0.004 + 0.03 * Phi[:, 1] + 0.01 * Phi[:, 4]
    fit = _audit().dictionary_fit(v, Phi, [1, 4])
    assert fit["all_rel_rms"] < 1e-8 and fit["selected_rel_rms"] < 1e-8
    c = np.sum(1 / v) / np.sum(1 / v**2)
    floor_only = _audit().dictionary_fit(v, Phi, [])["selected_rel_rms"]
    assert floor_only == pytest.approx(math.sqrt(np.mean((c / v - 1) ** 2)), rel=1e-6)
    assert floor_only > 0.3  # the planted sources make the variance vary several-fold
    # a wrong pair leaves a clear error; the fit is never worse with more columns
    wrong = _audit().dictionary_fit(v, Phi, [0, 2])["selected_rel_rms"]
    assert wrong > 0.1 and wrong <= floor_only + 1e-12
