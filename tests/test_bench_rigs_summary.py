"""scripts/bench_rigs.py's summary counts, on rig-targets whose ratios are worked out by hand.

The calibration compares the prediction the result states, N(target, pred_std^2) with
pred_std = sqrt(f_var + noise), with the readings' true RMS deviation from it,
sqrt(std^2 + err^2); the scatter calibration compares the true std with the predicted noise std.
"""

from __future__ import annotations

import math

from script_loader import load_script


def _bench():
    return load_script("bench_rigs", "bench_rigs_summary")


def _target(std, err, pred, noise, oracle=0.1):
    return {"std_um": std, "err_um": err, "pred_std_um": pred, "pred_noise_std_um": noise,
            "oracle_std_um": oracle, "afm_std_um": oracle, "solve_ms": 1.0}


def test_calibration_counts_the_mean_error_with_the_scatter():
    bench = _bench()
    targets = [
        # sqrt(0.06^2 + 0.08^2) = 0.10: RMS / pred = 1.0 (in); std / noise = 0.06 / 0.1 = 0.6 (out)
        _target(0.06, 0.08, 0.10, 0.10),
        # RMS 0.05 / 0.10 = 0.5 (out: the predicted std, with f's variance, is too wide);
        # std / noise = 0.05 / 0.05 = 1.0 (in)
        _target(0.05, 0.0, 0.10, 0.05),
        # RMS sqrt(0.09^2 + 0.12^2) = 0.15 / 0.12 = 1.25 (in); std / noise 0.09 / 0.1 = 0.9 (in)
        _target(0.09, -0.12, 0.12, 0.10),
        # RMS 0.2 / 0.1 = 2.0 (out); std / noise 2.0 (out)
        _target(0.2, 0.0, 0.1, 0.1),
    ]
    results = [{"runs": [{"n": 200, "method": "default", "fit_s": 1.0, "targets": targets}]}]
    (row,) = bench.summarise(results, [200], ["default"])
    assert (row["cal_pass"], row["cal_scatter_pass"], row["cal_n"]) == (2, 2, 4)
    assert abs(row["cal_min"] - 0.5) < 1e-12 and abs(row["cal_max"] - 2.0) < 1e-12
    # the rig fails on both counts: the third target's |err| 0.12 > 0.1 and the fourth's std is 2x the oracle's
    assert (row["rigs_pass"], row["rigs_err_pass"], row["rigs_std_pass"]) == (0, 0, 0)


def test_a_failing_target_names_a_floor_the_mean_passes_through():
    """A rig-run whose floor check is degenerate (kept in the JSON) says so on each failing target's
    line; a run without one does not."""
    bench = _bench()
    t = {**_target(0.05, 0.15, 0.03, 0.004), "target_um": 6.0, "f_std_um": 0.03, "pred_noise_std_oracle_um": 0.01, "f_std_oracle_um": 0.02,
         "q_prev_um": [0, 0, 0, 0], "q_um": [1, 1, 1, 1], "oracle_q_um": [1, 1, 1, 1]}
    floor = {"rows": [16, 67], "hat": [1.0, 1.0], "floor_std_um": 5.7e-5}
    results = [{"family": "hinge_slip", "seed": 8, "runs": [
        {"n": 125, "method": "default", "targets": [t], "floor_check": floor},
        {"n": 200, "method": "default", "targets": [t], "floor_check": None}]}]
    lines = [bench._fmt_fail(f) for f in bench.failing_targets(results)]
    assert len(lines) == 2 and all(": mean;" in ln for ln in lines)
    assert ("floor not an estimate: the mean correction passes through 2 training reading(s) that the noise model gives "
            "only its floor (floor std 5.7e-05 µm") in lines[0]
    assert "floor not an estimate" not in lines[1]


def test_a_failing_target_is_the_controllers_loss_only_where_the_model_ranks_the_oracle_better():
    """Expected squared errors worked by hand (f_var + noise var, µm²): a target counts as the
    controller's loss when the oracle pose's is more than 5 % below the chosen pose's."""
    bench = _bench()

    def tgt(std, noise, f, noise_o, f_o):
        return {**_target(std, 0.0, 0.1, noise), "target_um": 6.0, "f_std_um": f, "pred_noise_std_oracle_um": noise_o,
                "f_std_oracle_um": f_o, "q_prev_um": [0] * 4, "q_um": [0] * 4, "oracle_q_um": [0] * 4}

    chosen = tgt(0.2, 0.3, 0.4, 0.0, 0.0)      # chosen 0.09 + 0.16 = 0.25; oracle 0: better (controller)
    flat = tgt(0.2, 0.3, 0.4, 0.4, 0.3)        # oracle 0.16 + 0.09 = 0.25: a tie (the model's)
    near = tgt(0.2, 0.3, 0.4, 0.0, 0.4869)     # oracle 0.2371 = 0.9484 x 0.25: just past 5 % (controller)
    edge = tgt(0.2, 0.3, 0.4, 0.0, 0.4875)     # oracle 0.2377 = 0.9506 x 0.25: within 5 % (the model's)
    passing = tgt(0.1, 0.3, 0.4, 0.0, 0.0)     # std 0.1 = the oracle's: not a failing target, not counted
    assert [bench.controller_loss(t) for t in (chosen, flat, near, edge)] == [True, False, True, False]
    runs = [{"n": 200, "method": "default", "targets": [chosen, flat, near, edge, passing]}]
    assert bench._controller_losses(runs) == "2 of 4"
    results = [{"family": "clean", "seed": 0, "runs": runs}]
    lines = [bench._fmt_fail(f) for f in bench.failing_targets(results)]
    assert len(lines) == 4
    assert "the controller's loss" in lines[0] and "the model's loss" in lines[1]


def test_the_default_rigs_give_every_field_the_summary_reads():
    """``--rigs`` without ``--family`` (the default stick-slip rigs, run_rig) scores each target with
    the fields the family rigs give (at 7594c53 the summary raised KeyError on them), and the
    ``told`` reference names the rig's stick-slip actuators."""
    bench = _bench()
    res = bench.run_rig(0, (30,), ("told",))
    run = res["runs"][0]
    assert run["selected"] and {nm.split(":")[0] for nm in run["selected"]} == {f"d{q}" for q in res["friction"]}
    for t in run["targets"]:
        assert t["pred_noise_std_um"] > 0 and t["pred_noise_std_oracle_um"] > 0 and t["f_std_um"] >= 0
        assert math.isfinite(t["pred_alt_var_um2"]) and t["pred_alt_var_um2"] >= 0  # v_alt, as EAFM.alt_var
    (row,) = bench.summarise([res], (30,), ("told",))
    assert row["rigs"] == 1 and row["cal_n"] == 4


def test_the_data_limited_mean_bar_widens_only_by_sigma_star_at_the_oracles_pose():
    """max(0.1 µm, 3 sigma*) worked by hand: sigma* 0.06 gives 0.18 µm, sigma* 0.02 leaves 0.1 µm,
    a missing sigma* (nan: a sparse model) leaves 0.1 µm; the std half is not touched."""
    bench = _bench()

    def tgt(err, sigma, std=0.1):
        return {**_target(std, err, 0.1, 0.1), "f_noise_std_best_oracle_um": sigma}

    assert abs(bench.data_err_bar_um(tgt(0.0, 0.06)) - 0.18) < 1e-12
    assert bench.data_err_bar_um(tgt(0.0, 0.02)) == 0.1
    assert bench.data_err_bar_um(tgt(0.0, float("nan"))) == 0.1
    assert bench.data_err_bar_um({"err_um": 0.0}) == 0.1  # a JSON from before the field: the bar
    runs = [
        {"targets": [tgt(0.15, 0.06), tgt(-0.17, 0.06)]},   # within 0.18 at both: passes the data bar only
        {"targets": [tgt(0.15, 0.06), tgt(0.19, 0.06)]},    # 0.19 > 0.18: fails both
        {"targets": [tgt(0.12, 0.02)]},                     # 0.12 > max(0.1, 0.06): fails both
        {"targets": [tgt(0.12, float("nan"))]},             # no sigma*: 0.1 µm, fails both
        {"targets": [tgt(0.05, 0.06, std=0.2)]},            # std 2x the oracle's: fails both
        {"targets": [tgt(0.05, 0.01)]},                     # passes both
    ]
    got = bench.data_bar_summary(runs)
    assert (got["rigs_data_pass"], got["data_widened"], got["data_n"]) == (2, 5, 8)  # five targets carry sigma* 0.06 of eight
    assert sum(bench._rig_passes(r) for r in runs) == 1
    assert abs(got["sigma_best_median_um"] - 0.06) < 1e-12
