"""``microctl learn`` / ``api.learn``: a designed log, then refinement rounds, training between.

The learning run is checked against the same steps composed from the public pieces it stands
for (``api.collect``, training, ``api.refine``, training: the user's loop of
docs/experiments.md, Refinement), bit for bit; the command's refusals write nothing; a device
that fails mid-round leaves every completed move in the log and the last model on disk."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from microctl import api
from microctl.cli import main
from microctl.control.refine import ROUND_MOVES, learning_rounds
from microctl.errors import BackendError, ConfigError
from microctl.gp.vhgpr import FittedVHGPR
from microctl.models.training import ResidualModelSettings, residual_dataset, train_residual_model

ROOT = Path(__file__).resolve().parents[2]
CONFIG = ROOT / "configs/stage/sim_paper.yaml"
#: 60 designed moves and one refinement round of 40: the smallest run with a round.
N = 100


def test_rounds_are_forty_percent_of_the_moves_in_whole_rounds():
    assert [learning_rounds(n) for n in (5, 99, 100, 125, 199, 200, 400)] == [0, 0, 1, 1, 1, 2, 4]
    assert ROUND_MOVES == 40


def test_learn_is_collect_train_refine_train(tmp_path):
    stage = api.load_stage(CONFIG)
    settings = ResidualModelSettings(restarts=1)
    with stage.open_backend(seed=7) as b:
        model = api.learn(stage, N, tmp_path / "a.csv", seed=3, target_range_um=(0.0, 30.0), settings=settings,
                          backend=b)
    # the same steps from the public pieces, on a stage with the same seed
    log = tmp_path / "b.csv"

    def fit():
        return train_residual_model(residual_dataset(api.read_measurements(log, stage), stage.afm), stage.afm,
                                    settings)

    with stage.open_backend(seed=7) as b:
        api.collect(stage, N - ROUND_MOVES, log, seed=3, backend=b)
        first = fit()
        api.refine(stage, first, ROUND_MOVES, log, seed=[3, 0], target_range_um=(0.0, 30.0), backend=b)
        second = fit()
    assert (tmp_path / "a.csv").read_bytes() == log.read_bytes()
    x = np.random.default_rng(0).uniform(0.0, 20.0, (7, model.X.shape[1]))
    pa, pb = model.predict(x), second.predict(x)
    for name in ("f_mean", "f_var", "g_mean", "g_var"):
        np.testing.assert_array_equal(getattr(pa, name), getattr(pb, name))
    assert model.bound == second.bound
    # the refinement moved where the first model's controller would go: not the design's moves
    m = api.read_measurements(log, stage)
    assert np.allclose(m.u[N - ROUND_MOVES], 0.0)  # each episode starts at the zero state


def test_the_command_writes_the_log_and_the_model(tmp_path, capsys):
    log, model = tmp_path / "l.csv", tmp_path / "m.npz"
    rc = main(["learn", "--config", str(CONFIG), "-n", str(N), "--log", str(log), "-o", str(model),
               "--target-range", "0,30", "--seed", "2"])
    out = capsys.readouterr()
    assert rc == 0, out.err
    assert f"learn: {N} moves (60 designed + 1 refinement round(s) of 40)" in out.out
    assert "fit 1 of 2 on 60 moves" in out.err and "fit 2 of 2 on 100 moves" in out.err
    stage = api.load_stage(CONFIG)
    assert len(api.read_measurements(log, stage)) == N
    assert FittedVHGPR.load(model).X.shape[0] == N
    # a second run to the same log is refused and the log stays as it was
    before = log.read_bytes()
    assert main(["learn", "--config", str(CONFIG), "-n", str(N), "--log", str(log), "-o", str(model)]) == 2
    assert "--log" in capsys.readouterr().err and log.read_bytes() == before


@pytest.mark.parametrize("extra, message", [
    (["--target-range", "0,500"], "--target-range: 0,500 µm is not inside the stage's reachable range"),
    (["--target-range", "9,3"], "--target-range: expected LO,HI with LO < HI"),
    (["-n", "4"], "argument -n: must be at least 5"),
])
def test_refusals_name_the_option_and_write_nothing(tmp_path, capsys, extra, message):
    log, model = tmp_path / "l.csv", tmp_path / "m.npz"
    try:
        rc = main(["learn", "--config", str(CONFIG), "--log", str(log), "-o", str(model), "--quiet", *extra])
    except SystemExit as exc:  # a usage error (argparse): exit status 2 as well
        rc = exc.code
    assert rc == 2
    assert message in capsys.readouterr().err
    assert not log.exists() and not model.exists()


class _FailsAt:
    """A simulated stage whose move number ``k`` (1-based) fails as a device would."""

    def __init__(self, backend, k: int):
        self._b, self._k, self._moves = backend, k, 0

    def __getattr__(self, name):
        return getattr(self._b, name)

    def move(self, u):
        self._moves += 1
        if self._moves == self._k:
            raise BackendError("driver timeout (planted)")
        return self._b.move(u)


def test_a_failure_mid_round_keeps_the_moves_and_the_last_model(tmp_path):
    stage = api.load_stage(CONFIG)
    log, model = tmp_path / "l.csv", tmp_path / "m.npz"
    with stage.open_backend(seed=1) as b:
        with pytest.raises(BackendError, match=r"move 11 of 40 failed: .*planted.*keeps the 10 completed moves"):
            api.learn(stage, N, log, out=model, settings=ResidualModelSettings(restarts=1), backend=_FailsAt(b, 71))
    assert len(api.read_measurements(log, stage)) == 70  # 60 designed + the 10 before the failure
    assert FittedVHGPR.load(model).X.shape[0] == 60  # the first fit's model, written before the round


def test_an_existing_log_is_refused_unless_replaced(tmp_path):
    stage = api.load_stage(CONFIG)
    log = tmp_path / "l.csv"
    log.write_text("keep me\n")
    with pytest.raises(ConfigError, match="the file exists"):
        api.learn(stage, 10, log)
    assert log.read_text() == "keep me\n"
    api.learn(stage, 10, log, replace_log=True, settings=ResidualModelSettings(restarts=1))
    assert len(api.read_measurements(log, stage)) == 10


@pytest.mark.parametrize("kwargs, match", [
    ({"n": 4}, r"n: expected a number of moves >= 5 \(a model needs 5 to train on\), got 4"),
    ({"n": True}, r"n: expected a number of moves >= 5 .*got True"),
    ({"n": 100, "target_range_um": (0.0, 500.0)}, r"target_range_um: 0,500 µm is not inside the stage's reachable range"),
])
def test_api_refusals_name_the_value_and_move_nothing(tmp_path, kwargs, match):
    stage = api.load_stage(CONFIG)
    log = tmp_path / "l.csv"
    with pytest.raises(ConfigError, match=match):
        api.learn(stage, log=log, **kwargs)
    assert not log.exists()
