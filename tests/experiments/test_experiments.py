"""``microctl experiment`` end to end: simulated and emulated-serial runs, validation, interruption."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import yaml

from microctl.util import stats
from microctl.backends.simulated import SimulatedStage
from microctl.cli import main
from microctl.errors import BackendError, ConfigError
from microctl.experiments.config import load_experiment_config
from microctl.experiments.runner import run_experiment
from microctl.experiments.report import calibrated_below_afm
from microctl.measurement.log import read_log
from microctl.stage.config import load_stage_config

ROOT = Path(__file__).resolve().parents[2]
STAGE = ROOT / "configs/stage/sim_paper.yaml"
EMULATED = ROOT / "configs/stage/emulated.yaml"

TINY = {
    "stage": str(STAGE),
    "training": {"moves": 20, "restarts": 1, "max_iter": 60},
    "absolute": {"points": 3, "trials": 2},
    "incremental": {"targets_um": [7, 14], "trials": 3},
    "oracle": {"grid": 9, "line_points": 15, "zooms": 1},
    "figures": False,
}


def _write(tmp_path: Path, doc: dict, name: str = "exp.yaml") -> Path:
    p = tmp_path / name
    p.write_text(yaml.safe_dump(doc))
    return p


@pytest.fixture(scope="module")
def quick_run(tmp_path_factory):
    d = tmp_path_factory.mktemp("quick")
    doc = dict(TINY, figures=True)
    exp = _write(d, doc)
    out = d / "out"
    rc = main(["experiment", str(exp), "--out", str(out), "--quiet"])
    assert rc == 0
    return out, json.loads((out / "results.json").read_text())


def test_outputs_listed_for_the_input_guard(quick_run):
    """``experiment`` refuses an input in --out under a name it writes: the list must be complete."""
    from microctl.cli.commands.experiment import OUTPUTS

    out, _ = quick_run
    written = {p.name for p in out.iterdir()}
    assert written <= set(OUTPUTS), written - set(OUTPUTS)


def test_results_fields(quick_run):
    out, res = quick_run
    inc = res["incremental"]
    assert inc["targets_um"] == [7.0, 14.0] and inc["trials"] == 3
    for name in ("afm", "eafm", "oracle"):
        c = inc["controllers"][name]
        assert len(c["msse_um"]) == 2 and len(c["vsse_um2"]) == 2
    assert set(inc["p_value"]) == {"msse", "vsse"}
    ab = res["absolute"]
    assert len(ab["pe_um"]["afm"]) == 3 and len(ab["pe_um"]["eafm"]) == 3
    # the coverage the report states is the one of the logged measurements and predictions
    meas, mean, std = (np.asarray(ab[k]) for k in ("measured_um", "eafm_mean_um", "eafm_std_um"))
    assert ab["fraction_within_2sigma"] == pytest.approx(np.mean(np.abs(meas - mean) <= 2 * std))
    assert ab["p_value"] == ab["tests"]["two_sample_t"]["p_value"]
    for f in ("report.md", "config.yaml", "model.npz", "training_log.csv", "absolute_log.csv",
              "incremental_log.csv"):
        assert (out / f).is_file(), f
    text = (out / "report.md").read_text()
    assert "Table II" in text and "Brown–Forsythe" in text
    cfg = yaml.safe_load((out / "config.yaml").read_text())
    assert cfg["experiment"]["training"]["moves"] == 20 and "stage" in cfg["stage_config"]
    pytest.importorskip("matplotlib")
    assert (out / "fig5_absolute.png").is_file() and (out / "fig6_incremental.png").is_file()


def test_least_motion_counts_match_the_choices(quick_run):
    """results.json keeps each EAFM result's choice; the per-target least-motion counts are those of
    the choices (recounted here from the strings), the report states them, and controllers without
    the rule have neither."""
    from microctl.experiments.report import least_motion_trials

    out, res = quick_run
    ctrls = res["incremental"]["controllers"]
    for name in ("afm", "oracle"):
        assert "least_motion_trials" not in ctrls[name] and "choice" not in ctrls[name]
    choice = ctrls["eafm"]["choice"]
    assert len(choice) == 3 and all(len(row) == 2 and all(c for c in row) for row in choice)
    assert ctrls["eafm"]["least_motion_trials"] == [sum(row[j].startswith("least motion:") for row in choice)
                                                    for j in range(2)]
    assert "returned the least motion instead of eq. 4's optimum" in (out / "report.md").read_text()
    # the counting itself, on hand-made choices (2 trials x 3 targets)
    made = [["least motion: eq. 4's optimum better with P = 0.9 < 0.95", "optimum: it is the least motion", ""],
            ["least motion: eq. 4's optimum not better once ...", "optimum: lower expected squared error than the least motion", ""]]
    assert least_motion_trials(made) == [2, 0, 0]
    assert least_motion_trials([["", ""], ["", ""]]) is None and least_motion_trials(None) is None


def test_msse_recomputed_from_logs(quick_run):
    out, res = quick_run
    stage = load_stage_config(STAGE).stage
    log = read_log(out / "incremental_log.csv", stage)
    ctrl = np.array(log.extra["controller"])
    target = log.extra_numeric("target_um")
    trial = log.extra_numeric("trial")
    inc = res["incremental"]
    for name in ("afm", "eafm", "oracle"):
        rows = (ctrl == name) & (target > 0)
        # (trials, targets) in execution order
        sse = (target[rows] - log.t[rows]).reshape(inc["trials"], len(inc["targets_um"]))
        assert np.array_equal(trial[rows].reshape(sse.shape)[:, 0], np.arange(inc["trials"]))
        np.testing.assert_allclose(stats.msse(sse), inc["controllers"][name]["msse_um"], rtol=1e-12)
        np.testing.assert_allclose(stats.vsse(sse), inc["controllers"][name]["vsse_um2"], rtol=1e-12)
        # each trial starts by returning to the zero state
        zero = (ctrl == name) & (target == 0)
        assert zero.sum() == inc["trials"] and np.allclose(log.u[zero], 0.0)
    # training log: every designed move, readable
    assert len(read_log(out / "training_log.csv", stage)) == res["training"]["rows"] == 20
    # absolute log: 2 moves (u0, u_i) per point per trial
    assert len(read_log(out / "absolute_log.csv", stage)) == 2 * 3 * 2


def test_bias_uncertainty_against_the_truth(quick_run):
    """The absolute experiment's bias uncertainty is f's std at the logged move (not the total std),
    and its coverage of the true mean is the fraction the report states."""
    from microctl.models.afm import AnalyticForwardModel
    from microctl.models.eafm import EAFM

    out, res = quick_run
    ab = res["absolute"]
    stage = load_stage_config(STAGE).stage
    log = read_log(out / "absolute_log.csv", stage)
    point = log.extra_numeric("point")
    rows = point >= 0  # the moves to the points, after each return to zero; trial-major order
    eafm = EAFM(AnalyticForwardModel(stage), out / "model.npz")
    f_var = np.array([eafm.predict(s, u).f_var[0] for s, u in zip(log.s_prev[rows], log.u[rows])])
    bias = np.asarray(ab["eafm_bias_std_um"])
    np.testing.assert_allclose(bias.ravel(), np.sqrt(f_var), rtol=1e-9)
    assert np.all(bias > 0) and np.all(bias < np.asarray(ab["eafm_std_um"]))  # f's part of t's variance
    tm, mean = np.asarray(ab["true_mean_um"]), np.asarray(ab["eafm_mean_um"])
    np.testing.assert_allclose(np.abs(tm - mean).mean(axis=0), ab["mean_error_vs_truth_um"]["eafm"], rtol=1e-12)
    dev = np.abs(mean - tm)
    assert ab["bias_vs_truth"]["within_2sigma"] == pytest.approx(np.count_nonzero(dev <= 2 * bias) / dev.size)
    assert ab["bias_vs_truth"]["median_error_over_std"] == pytest.approx(np.median(dev / bias))
    expected = ab["bias_vs_truth"]["calibrated_below_afm_points"]
    assert expected == calibrated_below_afm(tm, ab["afm_um"], bias) and 0 <= expected <= ab["points"]
    assert "predicted bias uncertainty (f's std)" in (out / "report.md").read_text()


def test_common_random_numbers(quick_run):
    """Same seed per trial for every controller: the return-to-zero moves read the same gauge value."""
    out, res = quick_run
    stage = load_stage_config(STAGE).stage
    log = read_log(out / "incremental_log.csv", stage)
    ctrl = np.array(log.extra["controller"])
    zero = log.extra_numeric("target_um") == 0
    reads = {n: log.t[zero & (ctrl == n)] for n in ("afm", "eafm", "oracle")}
    np.testing.assert_array_equal(reads["afm"], reads["eafm"])
    np.testing.assert_array_equal(reads["afm"], reads["oracle"])


@pytest.mark.parametrize("patch,needle", [
    ({"training": {"moves": 20, "colour": "red"}}, "training.colour"),
    ({"incremental": {"targets_um": [7, "x"]}}, "incremental.targets_um[1]"),
    ({"incremental": {"targets_um": [7, 500]}}, "incremental.targets_um[1]"),
    ({"controllers": ["afm", "eafm", "magic"]}, "controllers[2]"),
    ({"controller": {"r_e": "huge"}}, "controller.r_e"),
    ({"controller": {"constraint_tol": 1e9}}, "controller.constraint_tol"),
    ({"controller": {"kappa": -1}}, "controller.kappa"),
    ({"training": {"moves": 20, "noise_model": "magic"}}, "training.noise_model"),
    ({"training": {"moves": 20, "linear_trend": False, "se": "off"}}, "training"),
    ({"training": {"moves": 20, "refine_target_range_um": [0, 500]}}, "training.refine_target_range_um"),
    ({"training": {"moves": 20, "gp_mean": "linear"}}, "training.gp_mean"),
    ({"training": {"moves": 20, "g_gp": "maybe"}}, "training.g_gp"),
    ({"training": {"moves": 20, "se": "sometimes"}}, "training.se"),
    ({"absolute": {"trials": 0}}, "absolute.trials"),
    ({"stage": "nope.yaml"}, "stage"),
])
def test_bad_field_fails_before_any_move(tmp_path, capsys, monkeypatch, patch, needle):
    moves = []
    orig = SimulatedStage.move
    monkeypatch.setattr(SimulatedStage, "move", lambda self, u: moves.append(u) or orig(self, u))
    exp = _write(tmp_path, {**TINY, **patch})
    out = tmp_path / "out"
    rc = main(["experiment", str(exp), "--out", str(out)])
    err = capsys.readouterr().err
    assert rc == 2
    lines = err.strip().splitlines()
    assert len(lines) == 1 and needle in lines[0] and str(exp) in lines[0]
    assert moves == [] and not out.exists()


def test_training_se_and_g_gp_reach_the_residual_model(tmp_path):
    """The experiment file's ``se`` and ``g_gp`` are the residual model's settings of the same name;
    unset, they are ResidualModelSettings' defaults (one source of the defaults)."""
    from microctl.models.training import ResidualModelSettings

    cfg = load_experiment_config(_write(tmp_path, {**TINY, "training": {"moves": 20, "se": "on", "g_gp": "off"}}))
    st = cfg.training.model_settings(5)
    assert (st.se, st.g_gp, st.seed) == ("on", "off", 5)
    plain = load_experiment_config(_write(tmp_path, {**TINY, "training": {"moves": 20}}, "plain.yaml"))
    d = ResidualModelSettings()
    assert (plain.training.model_settings(0).se, plain.training.model_settings(0).g_gp) == (d.se, d.g_gp)


def test_oracle_needs_a_simulated_stage(tmp_path, capsys):
    exp = _write(tmp_path, {**TINY, "stage": str(EMULATED)})
    rc = main(["experiment", str(exp), "--out", str(tmp_path / "out")])
    assert rc == 2 and "controllers" in capsys.readouterr().err


def test_interrupted_run_keeps_logs(tmp_path, capsys):
    """A backend failure after k moves: every completed move is in the logs, readable."""
    k_fail = 31  # 20 training moves, then 11 absolute moves
    count = {"n": 0}

    class Failing(SimulatedStage):
        def move(self, u):
            if count["n"] >= k_fail:
                raise BackendError("cable pulled")
            count["n"] += 1
            return super().move(u)

    cfg = load_experiment_config(_write(tmp_path, TINY))
    out = tmp_path / "out"
    with pytest.raises(BackendError, match="cable pulled") as exc:
        run_experiment(cfg, out, quiet=True, backend_factory=lambda c, seed: Failing(c, seed=seed))
    assert "absolute_log.csv: 11 rows" in str(exc.value)
    stage = cfg.stage_config.stage
    assert len(read_log(out / "training_log.csv", stage)) == 20
    ab = read_log(out / "absolute_log.csv", stage)
    assert len(ab) == 11 and list(ab.seq) == list(range(11))
    assert not (out / "results.json").exists()
    # through the CLI: exit 1, one clear line
    count["n"] = 0
    import microctl.experiments.runner as runner

    orig = runner.default_backend_factory
    runner.default_backend_factory = lambda c, seed: Failing(c, seed=seed)
    try:
        rc = main(["experiment", str(tmp_path / "exp.yaml"), "--out", str(tmp_path / "out2"), "--quiet"])
    finally:
        runner.default_backend_factory = orig
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 1 and len(err) == 1 and "keep every completed move" in err[0]


def test_keyboard_interrupt_keeps_logs(tmp_path, capsys):
    count = {"n": 0}

    class Interrupted(SimulatedStage):
        def move(self, u):
            if count["n"] >= 7:
                raise KeyboardInterrupt
            count["n"] += 1
            return super().move(u)

    cfg = load_experiment_config(_write(tmp_path, TINY))
    with pytest.raises(KeyboardInterrupt):
        run_experiment(cfg, tmp_path / "out", quiet=True, backend_factory=lambda c, s: Interrupted(c, seed=s))
    assert "training_log.csv: 7 rows" in capsys.readouterr().err
    assert len(read_log(tmp_path / "out" / "training_log.csv", cfg.stage_config.stage)) == 7


@pytest.mark.slow
def test_emulated_serial_run(tmp_path):
    """Once through the serial backend against the in-process emulator (emulate: true)."""
    doc = {**TINY, "stage": str(EMULATED), "emulate": True, "controllers": ["afm", "eafm"],
           "training": {"moves": 12, "design": "face_episodes", "restarts": 1, "max_iter": 40},
           "absolute": {"points": 2, "trials": 1}, "incremental": {"targets_um": [7], "trials": 2}}
    exp = _write(tmp_path, doc)
    out = tmp_path / "out"
    assert main(["experiment", str(exp), "--out", str(out), "--quiet"]) == 0
    res = json.loads((out / "results.json").read_text())
    assert res["backend"] == "emulated serial" and res["common_random_numbers"] is False
    stage = load_stage_config(EMULATED).stage
    log = read_log(out / "incremental_log.csv", stage)
    assert len(log) == 2 * 2 * 2  # 2 controllers x 2 trials x (zero + 1 target)
    assert set(log.extra["controller"]) == {"afm", "eafm"}


def test_seed_offset_shifts_every_seed(tmp_path):
    exp = _write(tmp_path, TINY)
    cfg = load_experiment_config(exp)
    shifted = cfg.with_seed_offset(10_000)
    for k, v in vars(cfg.seeds).items():
        assert getattr(shifted.seeds, k) == v + 10_000
    assert shifted.seed_offset == 10_000 and shifted.to_dict()["seed_offset"] == 10_000
    with pytest.raises(ConfigError, match="seed offset must be a non-negative integer, got -1"):
        cfg.with_seed_offset(-1)


@pytest.mark.slow
def test_short_run_quality(tmp_path):
    """A short seeded run (80 designed moves, no refinement) on sim_paper: the EAFM beats the
    AFM where the stage's defects make the AFM wrong and noisy. Thresholds sit well inside
    what the main job measures over 10 seed sets (|MSSE| ratio > 100, VSSE ratio > 4): a
    broken noise model or mean correction drops below them."""
    doc = {**TINY, "training": {"moves": 80, "restarts": 1}, "incremental": {"targets_um": [7, 21], "trials": 4},
           "absolute": {"points": 10, "trials": 2}}
    res = run_experiment(load_experiment_config(_write(tmp_path, doc)), tmp_path / "out", quiet=True)
    inc = res["incremental"]["controllers"]
    assert np.all(np.abs(inc["afm"]["msse_um"]) > 10 * np.abs(inc["eafm"]["msse_um"]))
    assert np.all(np.asarray(inc["eafm"]["true_std_um"]) <= 1.25 * np.asarray(inc["oracle"]["true_std_um"]))
    assert np.all(np.asarray(inc["afm"]["expected_vsse_um2"]) > 2 * np.asarray(inc["eafm"]["expected_vsse_um2"]))
    assert res["absolute"]["eafm_below_afm_points"] >= 9
    assert set(res["bars"]) >= {"msse_ratio", "vsse_not_worse", "eafm_bias", "vsse_vs_oracle", "coverage"}


@pytest.mark.slow
def test_out_on_an_old_run_folder_clears_the_previous_run(tmp_path, capsys):
    """The files a previous run wrote are removed first (figures: false writes none, so old
    figures would otherwise survive beside new results); other files are kept; a folder
    under an output name is refused before any work."""
    from microctl.cli.commands.experiment import OUTPUTS

    exp = _write(tmp_path, TINY)  # figures: false
    out = tmp_path / "old_run"
    out.mkdir()
    for name in ("fig5_absolute.png", "fig6_incremental.png", "results.json", "report.md"):
        (out / name).write_text("from the previous run")
    (out / "my_notes.txt").write_text("keep me")
    assert main(["experiment", str(exp), "--out", str(out)]) == 0
    cap = capsys.readouterr()
    err = cap.err
    assert "removed the previous run's" in err and "fig5_absolute.png" in err
    # results on stdout, notes on stderr (issue 22 item 8): `experiment ... > out.txt` captures the table
    assert "experiment: results in" in cap.out and "MSSE (µm)" in cap.out and "results in" not in err
    assert not (out / "fig5_absolute.png").exists() and not (out / "fig6_incremental.png").exists()
    assert (out / "my_notes.txt").read_text() == "keep me"
    assert json.loads((out / "results.json").read_text())["incremental"]["trials"] == 3
    assert {p.name for p in out.iterdir()} <= set(OUTPUTS) | {"my_notes.txt"}
    # an output name taken by a folder: one line, exit 2, nothing removed or run
    (out / "model.npz").unlink()
    (out / "model.npz").mkdir()
    rc = main(["experiment", str(exp), "--out", str(out), "--quiet"])
    lines = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(lines) == 1 and "'model.npz' is a folder" in lines[0]
    assert (out / "results.json").is_file()


def test_figures_show_every_controller_with_units(quick_run):
    """Fig. 6: one y scale per row, every controller drawn (markers side by side, so a
    controller coinciding with another stays visible); Fig. 5: no line joins the unrelated
    absolute points, the band is ±2σ; every axis names its unit."""
    pytest.importorskip("matplotlib")
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from microctl.experiments.figures import figure_fig5, figure_fig6

    _, res = quick_run
    fig = figure_fig6(res["incremental"])
    axes = np.array(fig.axes).reshape(2, -1)
    assert len({ax.get_ylim() for ax in axes[0]}) == 1 and len({ax.get_ylim() for ax in axes[1]}) == 1
    for ax in axes[0]:
        marks = {ln.get_label(): ln for ln in ax.get_lines() if ln.get_marker() not in ("None", "", None)}
        assert set(marks) == {"AFM", "EAFM", "oracle"}
        x0 = {name: float(ln.get_xdata()[0]) for name, ln in marks.items()}
        assert len(set(x0.values())) == 3  # side by side, never on top of each other
    for ax in fig.axes:
        assert "µm" in ax.get_ylabel() or not ax.get_ylabel()
        assert "trial" in ax.get_xlabel() and "unit" in ax.get_xlabel()
    plt.close(fig)
    fig = figure_fig5(res["absolute"])
    a, b, c = fig.axes[:3]
    for ln in a.get_lines():
        if len(ln.get_xdata()) > 2:
            assert ln.get_linestyle() == "None", ln.get_label()  # markers only
    ab = res["absolute"]
    band = [cont for cont in a.containers if "2σ" in str(cont.get_label())]
    assert band, "the EAFM band is labelled ±2σ"
    seg = band[0].lines[2][0].get_segments()[0]  # one error bar: mean ± 2 std of the first point in x order
    order = np.argsort(ab["afm_um"])
    half = abs(seg[1][1] - seg[0][1]) / 2
    assert half == pytest.approx(2 * np.nanmean(np.asarray(ab["eafm_std_um"]), axis=0)[order][0])
    for ax in (a, b, c):
        assert "(µm)" in ax.get_ylabel() or "(σ)" in ax.get_ylabel()
    assert "no unit" in c.get_xlabel()
    plt.close(fig)


def test_a_degenerate_floor_is_warned_recorded_and_reported(tmp_path, capsys, monkeypatch):
    """The experiment checks the trained floor as `microctl train` does (microctl.models.floor_check):
    a degenerate check, planted here (the check itself is tested on a rig where the degeneracy
    occurs, tests/models/test_floor_check.py), is said on stderr, kept in results.json's training
    rounds and in the saved model's info, and named in report.md; a sound floor adds nothing."""
    import microctl.models.floor_check as fc
    from microctl.gp.vhgpr import FittedVHGPR

    planted = fc.FloorCheck(rows=(3, 7), hat=(0.97, 0.91), floor_std_um=2e-5, floor_rows=4)
    monkeypatch.setattr(fc, "interpolated_floor", lambda model, X: planted)
    out = tmp_path / "out"
    doc = {**TINY, "controllers": ["afm", "eafm"], "incremental": {"targets_um": [7], "trials": 2}}
    assert main(["experiment", str(_write(tmp_path, doc)), "--out", str(out)]) == 0
    err = capsys.readouterr().err
    assert "round 0: warning: the mean correction passes through 2 of the 4 training reading(s)" in err
    res = json.loads((out / "results.json").read_text())
    assert res["training"]["rounds"][-1]["floor_check"] == {
        "rows": [3, 7], "hat": [0.97, 0.91], "floor_std_um": 2e-5, "floor_rows": 4, "at_bound": False,
        "finding": "the mean correction passes through 2 of the 4 training reading(s) that the noise model gives only "
                   "its floor (hat values up to 0.97)"}
    assert FittedVHGPR.load(out / "model.npz").info["floor_check"]["rows"] == [3, 7]
    assert "noise floor is not an estimate" in (out / "report.md").read_text()

    monkeypatch.setattr(fc, "interpolated_floor", lambda model, X: fc.FloorCheck((), (), 0.02, 40))
    out2 = tmp_path / "out2"
    assert main(["experiment", str(_write(tmp_path, doc)), "--out", str(out2), "--quiet"]) == 0
    res2 = json.loads((out2 / "results.json").read_text())
    assert res2["training"]["rounds"][-1]["floor_check"] is None
    assert "noise floor is not an estimate" not in (out2 / "report.md").read_text()
