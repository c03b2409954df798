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
