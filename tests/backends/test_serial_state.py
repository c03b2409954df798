"""The serial backend from any starting state (issue 12), against the in-process emulator.

The emulator can start where another session left the rig: actuators at non-zero positions,
axes still moving, an error stored on a controller. Loopback only (127.0.0.1).
"""

from __future__ import annotations

import time
from dataclasses import replace

import numpy as np
import pytest
from serial_rig import START_Q, serial_config

from microctl.backends.collect import run_collect
from microctl.backends.emulator import Emulator, Fault
from microctl.backends.serial import SerialStage
from microctl.errors import BackendError, ConfigError
from microctl.experiments.runner import MoveRecorder
from microctl.measurement.log import read_log
from microctl.models.afm import AnalyticForwardModel
from microctl.stage.physics import sensor_reading


def _true_reading(emu) -> float:
    """The emulated gauge's noise-free reading of the pose the rig stands in now."""
    st = emu.stage
    return float(sensor_reading(st.model, st._p[None, :], st.time_s)[0])


def _moves(cfg, n, seed=5):
    return AnalyticForwardModel(cfg.stage).workspace.sample(n, np.random.default_rng(seed))


def test_first_row_carries_the_true_previous_state(tmp_path):
    """A second collect on a rig left at q = (19.0, 4.4, 16.3, 31.0): the first row's q_prev is that."""
    cfg = serial_config()
    out = tmp_path / "log.csv"
    with Emulator(cfg, start_q_um=START_Q) as emu:
        truth = _true_reading(emu)
        with SerialStage(emu.pointed_at(cfg)) as stage:
            assert stage.state[1:].tolist() == list(START_Q)
            run_collect(stage, _moves(cfg, 4), out, quiet=True)
        assert any("start state read from the devices: q1 = 19.0000 µm" in n for n in stage.notes)
    log = read_log(out, cfg.stage)
    assert log.s_prev[0, 1:].tolist() == list(START_Q)
    noise = cfg.backend.simulated.gauge_noise_std_um
    assert abs(log.s_prev[0, 0] - truth) < 5 * noise  # t_prev: the gauge at the start pose
    assert abs(truth) > 1.0  # ... which is not the zero state's reading
    # later rows chain: s_prev[k] = [t, q] of row k - 1
    assert np.allclose(log.s_prev[1:], np.column_stack([log.t, log.q])[:-1])


def test_zero_start_still_reads_zero_positions():
    cfg = serial_config()
    with Emulator(cfg) as emu:
        with SerialStage(emu.pointed_at(cfg)) as stage:
            assert stage.state[1:].tolist() == [0.0, 0.0, 0.0, 0.0]
        commands = [line.split()[0] for dev, line in emu.log if dev == "driver1"]
    assert commands == ["*IDN?", "ERR?", "SVO", "ERR?", "ONT?", "POS?"]


def test_axes_still_moving_at_connect_are_waited_for():
    cfg = serial_config()
    with Emulator(cfg, start_q_um=START_Q, start_ont_polls=3) as emu:
        with SerialStage(emu.pointed_at(cfg)) as stage:
            assert stage.state[1:].tolist() == list(START_Q)
        polls = [line for dev, line in emu.log if dev == "driver2" and line.startswith("ONT?")]
    assert len(polls) == 4  # three "0" answers, then on target


def test_stale_error_is_cleared_and_reported():
    cfg = serial_config()
    with Emulator(cfg, stale_errors={"driver2": 7}) as emu:
        with SerialStage(emu.pointed_at(cfg)) as stage:
            assert np.isfinite(stage.move(_moves(cfg, 1)[0]).t_um)
    assert any("controller 'driver2' reported error 7 (position out of limits) left from before this session" in n
               for n in stage.notes), stage.notes


def test_start_position_beyond_the_limit_moves_nothing():
    """POS? beyond limit_um (a wrong axis mapping or unit): refuse before any MOV."""
    cfg = serial_config()
    acts = list(cfg.stage.actuators)
    acts[3] = replace(acts[3], range_um=(0.0, 30.0), limit_um=(0.0, 30.0))
    narrow = replace(cfg, stage=replace(cfg.stage, actuators=tuple(acts)))
    with Emulator(cfg, start_q_um=START_Q) as emu:
        with pytest.raises(BackendError, match=r"controller 'driver2' \(socket://127\.0\.0\.1:\d+\): POS\? reports axis A "
                                               r"\(actuator q4\) at 31\.0000 µm, beyond its hardware limit \[0, 30\] µm; "
                                               r"check the axis mapping .*nothing was moved"):
            SerialStage(emu.pointed_at(narrow))
        assert not [line for _, line in emu.log if line.startswith("MOV")]


def test_emulator_start_checks():
    cfg = serial_config()
    with pytest.raises(ConfigError, match=r"start_q_um: q4 = 40 µm is beyond its limit_um \[0, 38\]"):
        Emulator(cfg, start_q_um=(0, 0, 0, 40))
    with pytest.raises(ConfigError, match=r"start_q_um: give 4 finite positions"):
        Emulator(cfg, start_q_um=(0, 0))
    with pytest.raises(ConfigError, match=r"stale_errors: 'driver9' is not a controller"):
        Emulator(cfg, stale_errors={"driver9": 7})


def test_zero_at_start_tares_on_the_mean_of_tare_samples():
    """From a non-zero start: the first MOV goes to the zero state, then tare_samples readings."""
    cfg = serial_config(zero_at_start=True, tare_samples=40)
    offset = 5.0
    with Emulator(cfg, start_q_um=START_Q, gauge_offset_um=offset) as emu:
        with SerialStage(emu.pointed_at(cfg)) as stage:
            truth = _true_reading(emu) + offset  # the zero state's reading, un-tared
            n_queries = sum(1 for dev, _ in emu.log if dev == "gauge")
            movs = [line for _, line in emu.log if line.startswith("MOV")]
            assert stage.state.tolist() == [0.0, 0.0, 0.0, 0.0, 0.0]
            m = stage.move(_moves(cfg, 1)[0])
    assert n_queries == 40
    assert sorted(movs) == ["MOV 1 0.000000 2 0.000000 3 0.000000", "MOV A 0.000000"]  # devices log concurrently
    noise = cfg.backend.simulated.gauge_noise_std_um
    assert abs(stage.tare_um - truth) < 4 * noise / np.sqrt(40)
    assert any("the mean of 40 readings (tare_samples; standard error" in n for n in stage.notes), stage.notes
    assert abs(m.t_um) < 100


@pytest.mark.parametrize("faulty", [["driver2"], ["driver1", "driver2"]])
def test_err_checked_on_every_controller_that_moved(faulty):
    cfg = serial_config()
    faults = [Fault("err7", name, after_moves=1) for name in faulty]
    with Emulator(cfg, faults=faults) as emu:
        with SerialStage(emu.pointed_at(cfg)) as stage:
            u = _moves(cfg, 2)
            stage.move(u[0])
            n = len(emu.log)
            with pytest.raises(BackendError) as info:
                stage.move(u[1])
        after = emu.log[n:]
    msg = str(info.value)
    for name in ("driver1", "driver2"):
        assert ("ERR?" in [line for dev, line in after if dev == name]) is True  # each controller asked
        assert (f"controller '{name}'" in msg) == (name in faulty), msg
    assert "error 7 (position out of limits) after MOV" in msg
    if len(faulty) == 2:
        assert "; also controller 'driver2'" in msg


@pytest.mark.slow
def test_time_s_over_a_shared_serial_backend_is_wall_time(tmp_path):
    """experiment: trials share one serial stage; time_s must not add its clock again per trial."""
    cfg = serial_config()
    rec = MoveRecorder(tmp_path / "log.csv", cfg, ("trial",))
    moves = _moves(cfg, 3)
    with Emulator(cfg) as emu:
        before_connect = time.monotonic()
        with SerialStage(emu.pointed_at(cfg)) as stage:
            connected = time.monotonic()  # the stage's clock started in between
            for trial in range(4):
                for u in moves:
                    last_move_from = time.monotonic()
                    rec.move(stage, u, trial=trial)
                    last_move_to = time.monotonic()
                time.sleep(0.25)
    rec.close()
    log = read_log(tmp_path / "log.csv", cfg.stage)
    assert np.all(np.diff(log.time_s) >= 0)
    # The last move settled while it ran (bounds that hold on a machine of any speed); a clock restarted
    # or added again per trial would miss them by the sleeps between trials.
    assert last_move_from - connected <= log.time_s[-1] <= last_move_to - before_connect


@pytest.mark.slow
def test_collect_cli_prints_the_start_state_and_tare(tmp_path, capsys):
    """``collect`` through the serial backend says where the rig stood, and how the gauge was tared."""
    from microctl.cli import main

    for gauge, expect in (({}, "collect: start state read from the devices: q1 = 19.0000 µm, q2 = 4.4000 µm"),
                          ({"zero_at_start": True, "tare_samples": 8},
                           "collect: gauge tared at the zero state: offset ")):
        cfg = serial_config(**gauge)
        with Emulator(cfg, start_q_um=START_Q) as emu:
            path = tmp_path / "stage.yaml"
            path.write_text(emu.pointed_at(cfg).dump_yaml())
            out = tmp_path / "log.csv"
            assert main(["collect", "--config", str(path), "-n", "2", "-o", str(out), "--force"]) == 0
        err = capsys.readouterr().err
        assert expect in err, err
        if gauge:
            assert "the mean of 8 readings (tare_samples; standard error" in err
            assert read_log(out, cfg.stage).s_prev[0].tolist() == [0.0] * 5
        else:
            assert read_log(out, cfg.stage).s_prev[0, 1:].tolist() == list(START_Q)


def test_garbled_controller_at_connect_names_it():
    cfg = serial_config()
    with Emulator(cfg, faults=[Fault("garbled", "driver2", after_moves=0)]) as emu:
        with pytest.raises(BackendError, match=r"controller 'driver2' \(socket://127\.0\.0\.1:\d+\): unparsable reply to "
                                               r"'ERR\?' \(axes A\) after 2 attempts; expected an integer, received"):
            SerialStage(emu.pointed_at(cfg))


def test_axes_never_on_target_time_out_with_the_controller_named():
    cfg = serial_config()
    cfg = replace(cfg, backend=replace(cfg.backend, serial=replace(cfg.backend.serial, on_target_timeout_s=0.2)))
    with Emulator(cfg, ont_polls=10**9) as emu:
        with SerialStage(emu.pointed_at(cfg)) as stage:
            with pytest.raises(BackendError, match=r"controller 'driver1' .*: axes 1, 2, 3 not on target within 0.2 s "
                                                   r"after MOV"):
                stage.move(_moves(cfg, 1)[0])


def test_gauge_number_must_be_finite_and_strict():
    """A permissive reply_pattern must not let 'inf' through as a reading."""
    cfg = serial_config(reply_pattern=r"^\s*(\S+)\s*$")
    with Emulator(cfg, gauge_offset_um=float("inf")) as emu:
        with pytest.raises(BackendError, match=r"gauge \(socket://.*\): unparsable reply to 'MEAS\?' after 2 attempts "
                                               r"\(pattern .*, a finite decimal number\); received b'\+inf\\r\\n'"):
            SerialStage(emu.pointed_at(cfg))
