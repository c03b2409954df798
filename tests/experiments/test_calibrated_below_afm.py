"""microctl.experiments.report.calibrated_below_afm: the absolute bar's count expected for a mean
whose errors are exactly as wide as its bias std says, against independent answers: with one
trial P(|e| < a) = erf(a / (s sqrt 2)) in closed form; with two trials P((|e1| + |e2|) / 2 < a)
by numerical integration of two half-normals (scipy.integrate.quad); and its limits."""

from __future__ import annotations

import math

import numpy as np
from scipy import integrate
from scipy.stats import halfnorm

from microctl.experiments.report import CALIBRATED_DRAWS, calibrated_below_afm


def _tolerance(p: np.ndarray) -> float:
    """Four standard errors of the Monte Carlo sum (independent draws per point)."""
    return 4.0 * math.sqrt(float(np.sum(p * (1 - p))) / CALIBRATED_DRAWS) + 1e-12


def test_one_trial_matches_the_closed_form():
    rng = np.random.default_rng(0)
    points = 30
    tm = rng.normal(0, 5, (1, points))
    afm = tm[0] + rng.normal(0, 3, points)  # the AFM's error a = |tm - afm|
    s = rng.uniform(0.3, 4.0, (1, points))
    a = np.abs(tm[0] - afm)
    p = np.array([math.erf(ai / (si * math.sqrt(2))) for ai, si in zip(a, s[0])])
    assert abs(calibrated_below_afm(tm, afm, s) - p.sum()) <= _tolerance(p)


def test_two_trials_match_numerical_integration():
    rng = np.random.default_rng(1)
    points = 12
    tm = rng.normal(0, 5, (2, points))
    afm = tm.mean(axis=0) + rng.normal(0, 2, points)
    s = rng.uniform(0.5, 3.0, (2, points))
    a = np.abs(tm - afm[None, :]).mean(axis=0)  # the bar averages the AFM's error over the trials
    p = np.empty(points)
    for i in range(points):
        s1, s2, c = s[0, i], s[1, i], 2 * a[i]  # P(|e1| + |e2| < c)
        p[i] = integrate.quad(lambda x: halfnorm.pdf(x, scale=s1) * halfnorm.cdf(c - x, scale=s2), 0, c)[0]
    assert abs(calibrated_below_afm(tm, afm, s) - p.sum()) <= _tolerance(p)


def test_limits_and_determinism():
    """A vanishing std wins every point where the AFM errs at all; a huge one almost none; the
    same arguments give the same count (fixed draws)."""
    tm = np.array([[1.0, 2.0, 3.0, 4.0]])
    afm = np.array([1.5, 2.0, 2.0, 4.4])  # errors 0.5, 0, 1, 0.4: the AFM exact at one point
    assert calibrated_below_afm(tm, afm, np.full((1, 4), 1e-9)) == 3.0
    assert calibrated_below_afm(tm, afm, np.full((1, 4), 1e6)) < 0.01
    s = np.array([[0.3, 0.5, 0.8, 1.0]])
    assert calibrated_below_afm(tm, afm, s) == calibrated_below_afm(tm, afm, s)
