"""The BIC's parameter price, against Schwarz's criterion computed independently."""

import math

import numpy as np
import pytest
from scipy import stats

from microctl.util.bic import bic_penalty


@pytest.mark.parametrize("k, n", [(1, 125), (3, 200), (9, 2000)])
def test_penalty_is_half_k_log_n(k, n):
    # BIC = -2 log L + k log n, so k extra parameters need a log-likelihood gain of k log(n) / 2
    bic_cost = k * math.log(n)
    assert bic_penalty(k, n) == pytest.approx(bic_cost / 2, rel=1e-15)


def test_one_parameter_decides_between_nested_gaussians():
    # a known-truth check of what the penalty is for: a Gaussian with a free mean against one with
    # mean 0 on n draws. log L gains n ybar^2 / (2 sigma^2); BIC keeps the mean when that exceeds
    # bic_penalty(1, n). A true mean of 0 keeps it rarely; a mean of 1 sigma nearly always.
    rng = np.random.default_rng(3)
    n = 200

    def kept(mu):
        y = rng.normal(mu, 1.0, size=(2000, n))
        return float(np.mean(n * y.mean(axis=1) ** 2 / 2 > bic_penalty(1, n)))

    # P(chi2_1 > log 200 = 5.30) = 0.0213; over 2000 draws its SE is 0.0032, so 3 SE either side
    # is [0.012, 0.031]. Half the price (P = 0.104) or twice it (P = 0.0011) falls far outside.
    p = stats.chi2.sf(math.log(n), 1)
    se = math.sqrt(p * (1 - p) / 2000)
    assert p - 3 * se < kept(0.0) < p + 3 * se
    assert kept(1.0) == 1.0
