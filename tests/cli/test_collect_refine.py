"""``microctl collect --refine MODEL.npz`` end to end through ``microctl.cli.main``: the user's
refinement loop (collect, train, collect --refine --append, train) on the simulated sim_paper
stage, and the refusals."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from microctl.cli import main
from microctl.gp.vhgpr import FittedVHGPR
from microctl.measurement.log import read_log
from microctl.models.afm import AnalyticForwardModel
from microctl.stage.config import load_stage_config

ROOT = Path(__file__).resolve().parents[2]
CONFIG = ROOT / "configs/stage/sim_paper.yaml"


@pytest.fixture(scope="module")
def loop(tmp_path_factory):
    d = tmp_path_factory.mktemp("refine")
    log, model, model2 = d / "log.csv", d / "m.npz", d / "m2.npz"
    assert main(["collect", "--config", str(CONFIG), "-n", "40", "-o", str(log), "--quiet"]) == 0
    assert main(["train", str(log), "--config", str(CONFIG), "-o", str(model), "--restarts", "1", "--quiet"]) == 0
    before = log.read_bytes()
    assert main(["collect", "--config", str(CONFIG), "--refine", str(model), "-n", "9", "--target-range", "0,30",
                 "--append", "-o", str(log), "--seed", "4", "--quiet"]) == 0
    assert main(["train", str(log), "--config", str(CONFIG), "-o", str(model2), "--restarts", "1", "--quiet"]) == 0
    return d, log, model2, before


def test_refinement_moves_are_appended_and_trained_on(loop, capsys):
    d, log, model2, before = loop
    stage = load_stage_config(CONFIG).stage
    afm = AnalyticForwardModel(stage)
    assert log.read_bytes().startswith(before)  # the designed moves are kept as they were
    m = read_log(log, stage)
    assert len(m.t) == 49
    refined = m.u[40:]
    # episodes from the zero state: moves 1 and 6 of the nine return to it, the others do not
    zero = [i for i, u in enumerate(refined) if np.allclose(u, 0.0)]
    assert zero == [0, 5]
    q = refined @ afm.K.T
    assert np.all(q >= afm.lo - 1e-9) and np.all(q <= afm.hi + 1e-9)
    assert FittedVHGPR.load(model2).X.shape[0] == 49


def test_the_same_seed_gives_the_same_moves(loop, tmp_path):
    d, log, _, _ = loop
    outs = []
    for k in range(2):
        out = tmp_path / f"r{k}.csv"
        assert main(["collect", "--config", str(CONFIG), "--refine", str(d / "m.npz"), "-n", "5", "-o", str(out),
                     "--seed", "4", "--target-range", "0,30", "--quiet"]) == 0
        outs.append(read_log(out, load_stage_config(CONFIG).stage).u)
    np.testing.assert_array_equal(outs[0], outs[1])


@pytest.mark.parametrize("extra, message", [
    (["--design", "covering"], "--design covering and --refine"),
    (["--target-range", "0,500"], "--target-range: 0,500 µm is not inside the stage's reachable range"),
    (["--target-range", "9,3"], "--target-range: expected LO,HI with LO < HI"),
])
def test_refusals_name_the_option_and_write_nothing(loop, tmp_path, capsys, extra, message):
    d = loop[0]
    out = tmp_path / "x.csv"
    rc = main(["collect", "--config", str(CONFIG), "--refine", str(d / "m.npz"), "-n", "3", "-o", str(out), "--quiet",
               *extra])
    assert rc == 2
    assert message in capsys.readouterr().err
    assert not out.exists()


def test_target_range_without_refine_is_refused(tmp_path, capsys):
    out = tmp_path / "x.csv"
    assert main(["collect", "--config", str(CONFIG), "-n", "3", "-o", str(out), "--target-range", "0,30"]) == 2
    assert "--target-range: only with --refine" in capsys.readouterr().err
    assert not out.exists()


def test_a_model_of_another_stage_is_refused(loop, tmp_path, capsys):
    other = tmp_path / "other.yaml"
    text = CONFIG.read_text().replace("[15, 0, 5]", "[16, 0, 5]")
    assert text != CONFIG.read_text()
    other.write_text(text)
    out = tmp_path / "x.csv"
    assert main(["collect", "--config", str(other), "--refine", str(loop[0] / "m.npz"), "-n", "3", "-o", str(out)]) == 2
    assert "m.npz" in capsys.readouterr().err
    assert not out.exists()


@pytest.mark.parametrize("value", ["0", "0,1,2", "a,b"])
def test_a_malformed_target_range_is_a_usage_error(tmp_path, capsys, value):
    out = tmp_path / "x.csv"
    with pytest.raises(SystemExit, match="2"):
        main(["collect", "--config", str(CONFIG), "-n", "3", "-o", str(out), "--target-range", value])
    err = capsys.readouterr().err
    assert f"argument --target-range: expected LO,HI (two numbers in µm, e.g. 0,30), got '{value}'" in err
    assert "Traceback" not in err and not out.exists()
