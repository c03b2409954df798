"""``microctl collect`` into tmp_path, and the space-filling design."""

from pathlib import Path

import numpy as np

from microctl.afm import AnalyticForwardModel
from microctl.cli import main
from microctl.collect import space_filling_moves
from microctl.config import load_stage_config
from microctl.measurement_log import read_log

ROOT = Path(__file__).resolve().parents[1]
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
