"""``microctl collect`` into tmp_path, and the training designs."""

from pathlib import Path

import numpy as np
import pytest

from microctl.backends.collect import space_filling_moves
from microctl.cli import main
from microctl.errors import ConfigError
from microctl.measurement.design import training_moves
from microctl.measurement.log import read_log
from microctl.models.afm import AnalyticForwardModel
from microctl.stage.config import load_stage_config

ROOT = Path(__file__).resolve().parents[2]
SIM = str(ROOT / "configs/stage/sim_paper.yaml")


def test_design_fills_polytope_and_spreads_consecutive_moves():
    afm = AnalyticForwardModel(load_stage_config(SIM).stage)
    u = space_filling_moves(afm, 125, seed=1)
    assert u.shape == (125, 3) and afm.workspace.contains(u).all()
    q = afm.q_of(u)
    steps = np.linalg.norm(np.diff(q, axis=0), axis=1)
    d = np.linalg.norm(q[:, None] - q[None], axis=-1)[np.triu_indices(125, 1)]
    assert np.min(steps) >= 0.25 * np.median(d) - 1e-9
    # covers the box: every DoF spans most of its range
    span = (u.max(0) - u.min(0)) / (afm.workspace.u_hi - afm.workspace.u_lo)
    assert (span > 0.7).all()  # the polytope's extremes are vertices
    assert np.array_equal(u, space_filling_moves(afm, 125, seed=1))


def test_collect_cli_writes_log(tmp_path, capsys):
    out = tmp_path / "log.csv"
    assert main(["collect", "--config", SIM, "-n", "20", "--seed", "3", "-o", str(out), "--quiet"]) == 0
    log = read_log(out, load_stage_config(SIM).stage, min_rows=20)
    assert len(log) == 20 and log.seq.tolist() == list(range(20))
    assert np.allclose(log.s_prev[1:, 1:], log.q[:-1]) and np.allclose(log.s_prev[1:, 0], log.t[:-1])
    # same config and seed -> same data
    out2 = tmp_path / "log2.csv"
    assert main(["collect", "--config", SIM, "-n", "20", "--seed", "3", "-o", str(out2), "--quiet"]) == 0
    assert out.read_text() == out2.read_text()


def test_collect_cli_input_errors(tmp_path, capsys):
    assert main(["collect", "--config", str(tmp_path / "none.yaml"), "-o", str(tmp_path / "x.csv")]) == 2
    assert "none.yaml" in capsys.readouterr().err
    assert main(["collect", "--config", SIM, "-n", "0", "-o", str(tmp_path / "x.csv")]) == 2


def test_covering_design_holds_actuators_still_and_visits_the_limits():
    """Every pose inside the polytope; a third or more of the moves keep at least one actuator
    exactly still (hold moves and faces with a held actuator); every actuator sits at each of
    its limits in some move; step sizes of each actuator spread from ~0 to most of its range."""
    afm = AnalyticForwardModel(load_stage_config(SIM).stage)
    u = training_moves(afm, "covering", 200, seed=4)
    assert u.shape == (200, 3) and afm.workspace.contains(u).all()
    q = np.vstack([np.zeros(4), afm.q_of(u)])
    dq = np.diff(q, axis=0)
    still = np.abs(dq) < 1e-9
    assert np.mean(still.any(axis=1)) >= 0.3
    for i in range(4):
        assert still[:, i].sum() >= 10, f"actuator {i + 1} rarely held still"
        assert np.any(np.abs(q[:, i] - afm.lo[i]) < 1e-9) and np.any(np.abs(q[:, i] - afm.hi[i]) < 1e-9)
        moving = np.abs(dq[:, i])[~still[:, i]]
        assert np.min(moving) < 1.0 and np.max(moving) > 20.0
    assert np.array_equal(u, training_moves(afm, "covering", 200, seed=4))


@pytest.mark.slow
def test_large_designs_run_in_linear_memory():
    """n = 20000 (the first release built a 20000 x 20000 distance matrix, 3 GiB): both
    designs finish and stay in the polytope."""
    afm = AnalyticForwardModel(load_stage_config(SIM).stage)
    for design in ("space_filling", "covering"):
        u = training_moves(afm, design, 20000, seed=0)
        assert u.shape == (20000, 3) and afm.workspace.contains(u).all()


def test_design_arguments_are_checked():
    afm = AnalyticForwardModel(load_stage_config(SIM).stage)
    with pytest.raises(ConfigError, match="training design 'grid' is not one of covering, space_filling"):
        training_moves(afm, "grid", 10, 0)
    with pytest.raises(ConfigError, match=r"number of moves must be an integer in \[1, 1000000\], got 0"):
        training_moves(afm, "covering", 0, 0)
    with pytest.raises(ConfigError, match="design seed must be a non-negative integer, got -1"):
        training_moves(afm, "covering", 5, -1)
