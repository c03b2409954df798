"""Experiment statistics against hand-computed values and textbook formulas."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import stats as st

from microctl.util import stats


def test_msse_vsse_by_hand():
    sse = np.array([[1.0, 2.0], [3.0, 2.0], [2.0, 5.0]])
    np.testing.assert_allclose(stats.msse(sse), [2.0, 3.0])
    # var of (1,3,2) with ddof=1: ((1)+(1)+0)/2 = 1; of (2,2,5): (1+1+4)/2 = 3
    np.testing.assert_allclose(stats.vsse(sse), [1.0, 3.0])
    np.testing.assert_allclose(stats.msse_stderr(sse), np.sqrt([1 / 3, 1.0]))
    np.testing.assert_allclose(stats.steady_state_errors([7, 14], [6.5, 15.0]), [0.5, -1.0])


def test_student_t_by_hand():
    a = np.array([1.2, 3.1, 3.0, 5.2])  # paper Table II, AFM MSSE
    b = np.array([0.3, 0.7, 0.6, 0.9])  # EAFM MSSE
    na, nb = a.size, b.size
    sp2 = ((na - 1) * a.var(ddof=1) + (nb - 1) * b.var(ddof=1)) / (na + nb - 2)
    t = (a.mean() - b.mean()) / math.sqrt(sp2 * (1 / na + 1 / nb))
    p_two = 2 * st.t.sf(abs(t), na + nb - 2)
    res = stats.two_sample_t(a, b)
    assert res.statistic == pytest.approx(t, rel=1e-12)
    assert res.p_value == pytest.approx(p_two, rel=1e-10)
    assert res.p_one_sided == pytest.approx(p_two / 2, rel=1e-10)


def test_paired_t_by_hand():
    a = np.array([2.0, 3.0, 4.0, 6.0])
    b = np.array([1.0, 2.5, 2.0, 3.0])
    d = a - b
    t = d.mean() / (d.std(ddof=1) / math.sqrt(d.size))
    res = stats.paired_t(a, b)
    assert res.statistic == pytest.approx(t, rel=1e-12)
    assert res.p_value == pytest.approx(2 * st.t.sf(abs(t), d.size - 1), rel=1e-10)


def test_brown_forsythe_by_hand():
    """W = (N−k) Σ n_i (z̄_i − z̄)² / ((k−1) Σ Σ (z_ij − z̄_i)²), z_ij = |x_ij − median_i|."""
    a = np.array([0.0, 2.0, 5.0, 9.0, 1.0])
    b = np.array([1.0, 1.2, 0.9, 1.1, 1.0])
    za, zb = np.abs(a - np.median(a)), np.abs(b - np.median(b))
    z = np.concatenate([za, zb])
    N, k = z.size, 2
    num = (N - k) * (za.size * (za.mean() - z.mean()) ** 2 + zb.size * (zb.mean() - z.mean()) ** 2)
    den = (k - 1) * (((za - za.mean()) ** 2).sum() + ((zb - zb.mean()) ** 2).sum())
    W = num / den
    res = stats.brown_forsythe(a, b)
    assert res.statistic == pytest.approx(W, rel=1e-12)
    assert res.p_value == pytest.approx(st.f.sf(W, k - 1, N - k), rel=1e-10)
    assert res.p_one_sided == pytest.approx(res.p_value / 2)  # b has the smaller variance


def test_f_test_by_hand():
    a = np.array([0.0, 2.0, 4.0])  # var 4
    b = np.array([0.0, 1.0, 2.0])  # var 1
    res = stats.f_test_variances(a, b)
    assert res.statistic == pytest.approx(4.0)
    assert res.p_one_sided == pytest.approx(st.f.sf(4.0, 2, 2))
    assert res.p_one_sided == pytest.approx(1 / 5)  # F(2,2) survival: 1/(1+F)


def test_fraction_within():
    assert stats.fraction_within([0, 1, 3], [0, 0, 0], [1, 1, 1], k=2) == pytest.approx(2 / 3)
