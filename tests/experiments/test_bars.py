"""The main job's bars (microctl.experiments.bars) on hand-made results: each bar passes and fails
where its definition says."""

from __future__ import annotations

import copy
import math

import pytest

from microctl.experiments.bars import BARS, evaluate_bars, vsse_worse_p

GOOD = {
    "incremental": {
        "targets_um": [7.0, 14.0, 21.0, 28.0],
        "paper_table_ii": {"targets_um": [7.0, 14.0, 21.0, 28.0],
                           "msse_um": {"eafm": [0.3, 0.7, 0.6, 0.9]}},
        "controllers": {
            "afm": {"msse_um": [1.2, 2.4, 3.6, 4.8], "vsse_um2": [0.03, 0.04, 0.02, 0.06]},
            "eafm": {"msse_um": [0.01, -0.02, 0.0, 0.03], "vsse_um2": [0.003, 0.003, 0.004, 0.002],
                     "true_mean_um": [[7.01, 14.0, 20.99, 28.02]] * 3},
            "oracle": {"msse_um": [0.0, 0.0, 0.0, 0.0], "vsse_um2": [0.003, 0.003, 0.004, 0.002]},
        },
    },
    "absolute": {"points": 30, "eafm_below_afm_points": 30, "p_value": 1e-9,
                 "fraction_within_2sigma": 0.9, "expected_fraction_within_2sigma": 0.95},
}


def test_all_bars_pass_on_good_results():
    bars = evaluate_bars(GOOD)
    assert list(bars) == list(BARS)
    assert all(b["passed"] for b in bars.values()), bars


@pytest.mark.parametrize("path,value,bar", [
    (("incremental", "controllers", "afm", "msse_um"), [0.03, 2.4, 3.6, 4.8], "msse_ratio"),
    (("incremental", "controllers", "afm", "vsse_um2"), [0.03, 0.04, 0.02, 0.0001], "vsse_not_worse"),
    (("incremental", "controllers", "eafm", "msse_um"), [0.01, -0.02, 0.0, 1.0], "eafm_msse_vs_paper"),
    (("incremental", "controllers", "eafm", "true_mean_um"), [[7.06, 14.0, 21.0, 28.0]] * 3, "eafm_bias"),
    (("incremental", "controllers", "oracle", "vsse_um2"), [0.001, 0.003, 0.004, 0.002], "vsse_vs_oracle"),
    (("absolute", "eafm_below_afm_points"), 26, "absolute_pe"),
    (("absolute", "p_value"), 0.02, "absolute_pe"),
    (("absolute", "fraction_within_2sigma"), 0.7, "coverage"),
])
def test_each_bar_fails_where_it_should(path, value, bar):
    res = copy.deepcopy(GOOD)
    node = res
    for key in path[:-1]:
        node = node[key]
    node[path[-1]] = value
    bars = evaluate_bars(res)
    assert not bars[bar]["passed"]
    assert all(b["passed"] for k, b in bars.items() if k != bar)


def _binom_cdf(k: int, n: int, p: float) -> float:
    """P(X <= k), X ~ Binomial(n, p), summed by hand (independent of scipy)."""
    return sum(math.comb(n, j) * p**j * (1 - p) ** (n - j) for j in range(k + 1))


def test_coverage_is_judged_by_the_measured_fraction_with_its_binomial_tolerance():
    res = copy.deepcopy(GOOD)
    res["absolute"].update(points=30, trials=2)  # 60 measurements, as in the main job
    # 51/60 = 85 %: below the band, but P(X <= 51 | 60, 0.90) is about 0.1 -> consistent with 90 %
    res["absolute"]["fraction_within_2sigma"] = 51 / 60
    assert _binom_cdf(51, 60, 0.90) > 0.005
    assert evaluate_bars(res)["coverage"]["passed"]
    # 46/60 = 77 %: P(X <= 46 | 60, 0.90) < 0.005 -> fails, whatever the expected coverage says
    res["absolute"]["fraction_within_2sigma"] = 46 / 60
    assert _binom_cdf(46, 60, 0.90) < 0.005
    res["absolute"]["expected_fraction_within_2sigma"] = 0.95
    bar = evaluate_bars(res)["coverage"]
    assert not bar["passed"] and "expected under the truth 95.0%" in bar["detail"]
    # too wide a band: 600 of 600 inside, P(X >= 600 | 600, 0.98) = 0.98^600 -> fails
    res["absolute"].update(points=300, trials=2, fraction_within_2sigma=1.0)
    assert 0.98**600 < 0.005 and not evaluate_bars(res)["coverage"]["passed"]
    # 60 of 60 inside: 0.98^60 = 0.30 -> consistent with 98 %
    res["absolute"].update(points=30, trials=2, fraction_within_2sigma=1.0)
    assert evaluate_bars(res)["coverage"]["passed"]


def test_vsse_bar_passes_a_controller_equal_to_the_oracle_where_the_afm_is_quiet():
    """The old vsse_ratio (AFM/EAFM >= 2) failed a controller that equals the oracle on a rig whose AFM
    pose happens to be quiet: a bar on the rig, not on the controller. The new bar passes it."""
    res = copy.deepcopy(GOOD)
    c = res["incremental"]["controllers"]
    c["afm"]["vsse_um2"] = [0.0031, 0.0029, 0.0041, 0.0021]  # AFM as quiet as the oracle
    assert evaluate_bars(res)["vsse_not_worse"]["passed"]
    assert evaluate_bars(res)["vsse_vs_oracle"]["passed"]


def test_vsse_not_worse_is_a_one_sided_f_test():
    """F = 0.006/0.002 = 3 with (9, 9) degrees of freedom: p = P(F(9,9) >= 3) = 0.0567 by the regularised
    incomplete beta, computed here by numerical integration of the F density (independent of scipy.stats)."""
    from scipy.integrate import quad
    from scipy.special import beta

    d = 9
    dens = lambda x: (d / d) ** (d / 2) * x ** (d / 2 - 1) * (1 + x) ** (-d) / beta(d / 2, d / 2)
    p_hand = quad(dens, 3.0, math.inf)[0]
    assert 0.05 < p_hand < 0.06
    a = {"vsse_um2": [0.002]}
    e = {"vsse_um2": [0.006]}
    assert vsse_worse_p(a, e, 10)[0] == pytest.approx(p_hand, rel=1e-6)
    res = copy.deepcopy(GOOD)
    res["incremental"]["controllers"]["eafm"]["vsse_um2"] = [0.003, 0.003, 0.004, 0.024]
    res["incremental"]["controllers"]["afm"]["vsse_um2"] = [0.03, 0.04, 0.02, 0.002]  # F = 12 at 28 µm: p < 0.001
    assert not evaluate_bars(res)["vsse_not_worse"]["passed"]


def test_msse_ratio_is_judged_on_its_lower_bound():
    """AFM |MSSE| 1.2 over EAFM |MSSE| 0.01: ratio 120, but with SE 0.2 the lower bound is
    1.2 / (0.01 + 0.4) = 2.9 < 4 -> fails; with SE 0.05, 1.2 / 0.11 = 10.9 -> passes."""
    res = copy.deepcopy(GOOD)
    e = res["incremental"]["controllers"]["eafm"]
    e["msse_stderr_um"] = [0.2, 0.01, 0.01, 0.01]
    bar = evaluate_bars(res)["msse_ratio"]
    assert not bar["passed"] and ">= 2.9" in bar["detail"]
    e["msse_stderr_um"] = [0.05, 0.01, 0.01, 0.01]
    assert evaluate_bars(res)["msse_ratio"]["passed"]


def test_coverage_without_the_truth_uses_the_measured_fraction():
    res = copy.deepcopy(GOOD)
    del res["absolute"]["expected_fraction_within_2sigma"]
    assert evaluate_bars(res)["coverage"]["passed"]  # 0.90 measured
    res["absolute"]["fraction_within_2sigma"] = 0.7  # 21/30: P(X <= 21 | 30, 0.9) < 0.005
    assert not evaluate_bars(res)["coverage"]["passed"]


def test_absolute_bar_on_a_simulated_stage_is_judged_against_the_truth():
    """With the simulator's truth the absolute bar reads the models' mean errors from the true
    mean (paired t-test), not the measured PE: where the moves scatter more than the AFM's bias,
    even a perfect model's PE is below the AFM's at only about half of the points, so the
    measured-PE share (here 15/30, p = 0.75) must not decide it."""
    res = copy.deepcopy(GOOD)
    res["absolute"].update(eafm_below_afm_points=15, p_value=0.75,
                           mean_error_vs_truth_um={"eafm_below_afm_points": 28},
                           tests={"paired_t_mean_error_vs_truth": {"p_value": 1e-6}})
    bar = evaluate_bars(res)["absolute_pe"]
    assert bar["passed"] and "nearer the true mean than the AFM's at 28/30" in bar["detail"]
    assert "measured: EAFM PE below AFM at 15/30 points, t-test p = 0.75" in bar["detail"]
    res["absolute"]["mean_error_vs_truth_um"]["eafm_below_afm_points"] = 26  # 87 % < 90 %
    assert not evaluate_bars(res)["absolute_pe"]["passed"]
    res["absolute"]["mean_error_vs_truth_um"]["eafm_below_afm_points"] = 30
    res["absolute"]["tests"]["paired_t_mean_error_vs_truth"]["p_value"] = 0.02
    assert not evaluate_bars(res)["absolute_pe"]["passed"]
    res["absolute"]["tests"]["paired_t_mean_error_vs_truth"] = None  # undefined test
    assert not evaluate_bars(res)["absolute_pe"]["passed"]


def test_oracle_bar_on_a_simulated_stage_reads_the_expected_vsse():
    """With the truth's expected VSSE in both runs the oracle bar is judged on it, not on the
    10-trial sample: a sample ratio of 1.6 over equal truth passes, a sample ratio of 0.6 over a
    pose 40x noisier in truth fails. Independent check: the F(9, 9) distribution puts a sample
    ratio of equal-variance normals above 1.5 with probability ~0.28 (computed here by Monte
    Carlo with a fixed seed), so a sample bar fails a controller equal to the oracle often."""
    import numpy as np

    rng = np.random.default_rng(7)
    a, b = rng.standard_normal((2, 20000, 10))
    share = float(np.mean(a.var(axis=1, ddof=1) / b.var(axis=1, ddof=1) > 1.5))
    assert 0.25 < share < 0.31
    res = copy.deepcopy(GOOD)
    c = res["incremental"]["controllers"]
    c["eafm"]["vsse_um2"] = [0.0048, 0.003, 0.004, 0.002]  # 1.6x the oracle's sample at 7 µm
    c["eafm"]["expected_vsse_um2"] = [0.003, 0.003, 0.004, 0.002]
    c["oracle"]["expected_vsse_um2"] = [0.003, 0.003, 0.004, 0.002]
    bar = evaluate_bars(res)["vsse_vs_oracle"]
    assert bar["passed"] and "expected under the truth [1.0, 1.0, 1.0, 1.0]" in bar["detail"]
    assert "measured EAFM/oracle VSSE [1.6, 1.0, 1.0, 1.0]" in bar["detail"]
    c["eafm"]["vsse_um2"] = [0.003, 0.003, 0.004, 0.0012]  # a quiet sample ...
    c["eafm"]["expected_vsse_um2"] = [0.003, 0.003, 0.004, 0.08]  # ... of a pose 40x noisier
    assert not evaluate_bars(res)["vsse_vs_oracle"]["passed"]
