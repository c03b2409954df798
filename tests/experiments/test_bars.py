"""The main job's bars (microctl.experiments.bars) on hand-made results: each bar passes and fails
where its definition says."""

from __future__ import annotations

import copy

import pytest

from microctl.experiments.bars import BARS, evaluate_bars

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
    (("incremental", "controllers", "afm", "vsse_um2"), [0.03, 0.004, 0.02, 0.06], "vsse_ratio"),
    (("incremental", "controllers", "eafm", "msse_um"), [0.01, -0.02, 0.0, 1.0], "eafm_msse_vs_paper"),
    (("incremental", "controllers", "eafm", "true_mean_um"), [[7.06, 14.0, 21.0, 28.0]] * 3, "eafm_bias"),
    (("incremental", "controllers", "oracle", "vsse_um2"), [0.001, 0.003, 0.004, 0.002], "vsse_vs_oracle"),
    (("absolute", "eafm_below_afm_points"), 26, "absolute_pe"),
    (("absolute", "p_value"), 0.02, "absolute_pe"),
    (("absolute", "expected_fraction_within_2sigma"), 0.985, "coverage"),
    (("absolute", "expected_fraction_within_2sigma"), 0.85, "coverage"),
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


def test_coverage_without_the_truth_uses_the_measured_fraction():
    res = copy.deepcopy(GOOD)
    del res["absolute"]["expected_fraction_within_2sigma"]
    assert evaluate_bars(res)["coverage"]["passed"]  # 0.90 measured
    res["absolute"]["fraction_within_2sigma"] = 0.88
    assert not evaluate_bars(res)["coverage"]["passed"]
