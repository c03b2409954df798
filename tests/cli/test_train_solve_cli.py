"""``microctl train`` and ``microctl solve`` end to end through ``microctl.cli.main``."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import yaml
from scipy.stats import norm

from microctl.cli import main
from microctl.gp.vhgpr import FittedVHGPR
from microctl.models.afm import AnalyticForwardModel
from microctl.stage.config import load_stage_config

ROOT = Path(__file__).resolve().parents[2]
CONFIG = ROOT / "configs/stage/table1.yaml"


@pytest.fixture(scope="module")
def trained(tmp_path_factory, planted_log):
    """The hand-written 40-row log (conftest ``planted_log``) and the model trained on it."""
    d = tmp_path_factory.mktemp("train")
    afm = AnalyticForwardModel(load_stage_config(CONFIG).stage)
    log = planted_log
    model = d / "model.npz"
    rc = main(["train", str(log), "--config", str(CONFIG), "-o", str(model), "--restarts", "1", "--seed", "3",
               "--quiet"])
    assert rc == 0
    return d, log, model, afm


def test_train_writes_a_bound_model(trained):
    d, log, model, afm = trained
    m = FittedVHGPR.load(model)
    assert m.geometry_hash == afm.stage.geometry_hash()
    assert m.x_names == ("t_prev", "q1_prev", "q2_prev", "q3_prev", "q4_prev", "u_z", "u_rx", "u_ry")
    assert m.X.shape == (40, 8)


def test_solve_json(trained, capsys):
    d, log, model, afm = trained
    capsys.readouterr()
    rc = main(["solve", "--config", str(CONFIG), "--model", str(model), "--target", "12.5",
               "--state", "1,2,3,4,5", "--json"])
    out = json.loads(capsys.readouterr().out)
    assert rc == 0
    for key in ("target_um", "u", "q_um", "predicted_um", "predicted_std_um", "status", "solve_time_s", "baseline"):
        assert key in out
    assert set(out["u"]) == {"z", "rx", "ry"}
    assert set(out["baseline"]) >= {"u", "predicted_um", "predicted_std_um"}
    assert out["target_um"] == 12.5 and abs(out["predicted_um"] - 12.5) <= 1e-8
    q = np.array(out["q_um"])
    assert np.all(q >= 0) and np.all(q <= 32)
    u = np.array([out["u"][k] for k in ("z", "rx", "ry")])
    np.testing.assert_allclose(afm.K @ u, q, atol=1e-9)
    assert out["predicted_std_um"] > 0 and out["status"] == "Solve_Succeeded"
    # the least-motion rule is on by default and says which command it returned
    assert out["choice"].startswith(("optimum: lower expected squared error", "optimum: it is the least motion",
                                     "least motion: "))
    # the comparison with the AFM baseline, and the defaults shared with the API and experiments
    # the verdict follows from the probability it reports (P(log noise ratio < 0) = Phi(-mean/std))
    cmp = out["vs_baseline"]
    assert out["credibly_quieter_than_baseline"] is (cmp["prob_quieter"] >= cmp["level"]) and cmp["level"] == 0.95
    assert cmp["prob_quieter"] == pytest.approx(norm.cdf(-cmp["log_ratio_mean"] / cmp["log_ratio_std"]), abs=1e-9)
    assert out["r_e"] == "noise_quantile" and out["kappa"] == 1.645 and out["model"]["noise_model"] == "dictionary"
    assert out["baseline"]["predicted_by"] == "eafm"


def test_solve_human_table(trained, capsys):
    d, log, model, afm = trained
    rc = main(["solve", "--config", str(CONFIG), "--model", str(model), "--target", "20"])
    text = capsys.readouterr().out
    assert rc == 0 and "AFM baseline" in text and "EAFM pred. std" in text and "IPOPT" in text
    assert "quieter than the AFM baseline's" in text and "from the state t = 0" in text


def test_train_options_and_noise_report(trained, capsys, tmp_path):
    d, log, model, afm = trained
    out = tmp_path / "hgp.npz"
    rc = main(["train", str(log), "--config", str(CONFIG), "-o", str(out), "--noise-model", "hgp",
               "--no-linear-trend", "--restarts", "1"])
    err = capsys.readouterr().out  # the result is on stdout (issue 22 item 8)
    assert rc == 0 and "noise model hgp" in err
    m = FittedVHGPR.load(out)
    assert m.noise_model == "hgp" and m.f_log_linear_vars is None
    rc = main(["train", str(log), "--config", str(CONFIG), "-o", str(tmp_path / "p.npz"), "--restarts", "1",
               "--noise-model", "physical"])
    err = capsys.readouterr().out
    assert rc == 0 and "stick-slip std per µm moved" in err and "q4" in err and "SE part" in err
    # the dictionary: the planted log's scatter is uniform (0.05 µm), so no source is selected once f's
    # SE part follows the planted sin(z/8) (--se on; with se: auto the BIC drops it on these 40 rows and
    # the sin enters as a tilt source: the known defect of tests/models/test_first_fit_mean.py)
    rc = main(["train", str(log), "--config", str(CONFIG), "-o", str(tmp_path / "d.npz"), "--restarts", "1",
               "--se", "on"])
    err = capsys.readouterr().out
    from microctl.models.noise_dictionary import candidate_features
    n_cand = len(candidate_features(trained[3], context=True).names) + 1  # + the tilt group
    assert rc == 0 and f"noise model dictionary: no noise source selected among {n_cand} candidates" in err
    assert FittedVHGPR.load(tmp_path / "d.npz").noise_model == "dictionary"
    rc = main(["train", str(log), "--config", str(CONFIG), "-o", str(tmp_path / "x.npz"), "--no-linear-trend",
               "--se", "off"])
    assert rc == 2 and "--se off needs the linear trend" in capsys.readouterr().err
    rc = main(["train", str(log), "--config", str(CONFIG), "-o", str(tmp_path / "x.npz"), "--restarts", "0"])
    assert rc == 2 and "--restarts: must be an integer in [1, 100], got 0" in capsys.readouterr().err


@pytest.mark.parametrize("state,needle", [("1,2,3", "3 value(s)"), ("1,2,x,4,5", "'x'"), ("1,2,3,4,nan", "not finite")])
def test_bad_state_exit_2(trained, capsys, state, needle):
    d, log, model, afm = trained
    rc = main(["solve", "--config", str(CONFIG), "--model", str(model), "--target", "5", "--state", state])
    err = capsys.readouterr().err
    assert rc == 2 and needle in err and len(err.strip().splitlines()) == 1


def test_unreachable_target_exit_2(trained, capsys):
    d, log, model, afm = trained
    rc = main(["solve", "--config", str(CONFIG), "--model", str(model), "--target", "400"])
    err = capsys.readouterr().err
    # the target value is the input at fault: exit 2, one line with the reachable interval
    assert rc == 2 and "unreachable" in err and "reaches [" in err and len(err.strip().splitlines()) == 1


def test_model_for_another_geometry_refused(trained, capsys, tmp_path):
    d, log, model, afm = trained
    raw = yaml.safe_load(CONFIG.read_text())
    raw["stage"]["tool"]["point_mm"] = [-40.0, 30.0, 10.0]
    other = tmp_path / "other.yaml"
    other.write_text(yaml.safe_dump(raw))
    rc = main(["solve", "--config", str(other), "--model", str(model), "--target", "5"])
    err = capsys.readouterr().err
    assert rc == 2 and "model.npz" in err and "geometry" in err


def test_train_bad_log_exit_2(tmp_path, capsys):
    log = tmp_path / "bad.csv"
    log.write_text("seq,u_z,u_rx,u_ry,q1,q2,q3,q4,t\n0,1,0,0,1,1,1,1,abc\n")
    rc = main(["train", str(log), "--config", str(CONFIG), "-o", str(tmp_path / "m.npz"), "--quiet"])
    err = capsys.readouterr().err
    assert rc == 2 and "bad.csv" in err


def test_one_shot_solve_never_imports_scipy(trained):
    """Start-up (issue: the lab's loop): a one-shot ``solve`` loads a model, builds the controller,
    solves and prints without ``scipy`` (its linear algebra alone costs more CPU than NumPy and
    CasADi together); a regression would bring the import back silently."""
    import subprocess
    import sys

    _, _, model, _ = trained
    code = ("import sys\nfrom microctl.cli import main\n"
            f"rc = main(['solve', '--config', {str(CONFIG)!r}, '--model', {str(model)!r}, '--target', '14'])\n"
            "print('RC', rc, sorted(m for m in sys.modules if m == 'scipy' or m.startswith('scipy.')))\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=True).stdout
    assert "RC 0 []" in out, out[-2000:]


def test_train_line_names_exchanged_shapes():
    """The one-line noise summary ``train`` prints names a shape the selection re-chose."""
    from microctl.cli.commands.train import describe_noise

    summary = {"noise_model": "dictionary", "floor_std_um": 0.05, "sources": {"dq3:sq": {}, "dq1:sq": {}},
               "selection": {"candidates": 65, "shape_swaps": [["dq3:abs", "dq3:sq"]]}}
    line = describe_noise(summary)
    assert "dq3:sq, dq1:sq" in line and "dq3:abs -> dq3:sq" in line
    del summary["selection"]["shape_swaps"]
    assert "re-chosen" not in describe_noise(summary)


def test_train_line_names_the_mean_shift_trend():
    """The one-line summary says which sources the mean correction's trend reads (docs/vhgpr.md,
    "The mean shift that scatter causes"), and says nothing of it without one."""
    from microctl.cli.commands.train import describe_noise

    summary = {"noise_model": "dictionary", "floor_std_um": 0.05, "sources": {"dq4:sq": {}},
               "selection": {"candidates": 65, "mean_shift": {"features": ["dq4:sq"], "gain_nats": 1.5}}}
    assert "the mean correction has a trend in dq4:sq" in describe_noise(summary)
    del summary["selection"]["mean_shift"]
    assert "trend" not in describe_noise(summary)


def test_train_no_mean_shift_is_passed_to_the_settings(monkeypatch, tmp_path):
    """``--no-mean-shift`` reaches the residual model's settings (the default: on)."""
    from microctl.cli.commands import train as train_cmd

    seen = []

    def fake(data, afm, settings):
        seen.append(settings.mean_shift)
        raise train_cmd.DataError("stop here")

    monkeypatch.setattr(train_cmd, "train_residual_model", fake)
    log = tmp_path / "log.csv"
    from microctl import api

    api.collect(api.load_stage(CONFIG), 12, log, seed=1)
    for extra, want in (([], True), (["--no-mean-shift"], False)):
        rc = main(["train", str(log), "--config", str(CONFIG), "-o", str(tmp_path / "m.npz"), *extra])
        assert rc == 2 and seen[-1] is want
