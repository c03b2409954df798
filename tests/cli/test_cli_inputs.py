"""Command-line arguments that cannot be right: one line, exit 2, and no input destroyed (issue 12)."""

from __future__ import annotations

import shutil
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from microctl.cli import main
from microctl.cli.commands import diagnose as diagnose_cmd

ROOT = Path(__file__).resolve().parents[2]
TABLE1 = ROOT / "configs/stage/table1.yaml"
SIM = ROOT / "configs/stage/sim_paper.yaml"
QUICK = ROOT / "configs/experiments/quick.yaml"


def _one_line_error(capsys, rc, want_rc=2, contains=()):
    err = capsys.readouterr().err
    assert rc == want_rc, err
    assert err.count("\n") == 1 and "Traceback" not in err, err
    for text in contains:
        assert text in err, err
    return err


@pytest.fixture(scope="module")
def log40(tmp_path_factory) -> Path:
    """A 40-move simulated log of the sim_paper stage (enough for a diagnosis)."""
    d = tmp_path_factory.mktemp("log40")
    out = d / "log.csv"
    assert main(["collect", "--config", str(SIM), "-n", "40", "-o", str(out), "--quiet"]) == 0
    return out


@pytest.mark.parametrize("argv", [
    ["collect", "--config", str(TABLE1), "-n", "3", "-o", "x.csv"],
    ["train", "x.csv", "--config", str(TABLE1), "-o", "m.npz"],
    ["gp", "fit", "x.csv", "--x", "a", "--y", "b", "-o", "g.npz"],
    ["diagnose", "x.csv", "--config", str(TABLE1), "--out", "d"],
    ["emulate", "--config", str(TABLE1)],
])
def test_negative_seed_is_a_usage_error(capsys, argv):
    with pytest.raises(SystemExit) as info:
        main(argv + ["--seed", "-1"])
    err = capsys.readouterr().err
    assert info.value.code == 2 and "argument --seed: must be a non-negative integer, got -1" in err
    assert "Traceback" not in err


@pytest.mark.parametrize("value,message", [("0", "must be at least 1, got 0"), ("two", "'two' is not an integer")])
def test_gp_restarts_must_be_a_positive_integer(capsys, value, message):
    with pytest.raises(SystemExit) as info:
        main(["gp", "fit", "x.csv", "--x", "a", "--y", "b", "-o", "g.npz", "--restarts", value])
    err = capsys.readouterr().err
    assert info.value.code == 2 and f"argument --restarts: {message}" in err
    assert "Traceback" not in err


def test_collect_refuses_to_overwrite_its_stage_file(tmp_path, capsys):
    cfg = tmp_path / "stage.yaml"
    shutil.copy(TABLE1, cfg)
    before = cfg.read_bytes()
    rc = main(["collect", "--config", str(cfg), "-n", "3", "-o", str(tmp_path / "." / "stage.yaml")])
    _one_line_error(capsys, rc, contains=["is the stage config --config; refusing to overwrite an input"])
    assert cfg.read_bytes() == before


def test_train_refuses_to_overwrite_its_log(log40, tmp_path, capsys):
    log = tmp_path / "log.csv"
    shutil.copy(log40, log)
    before = log.read_bytes()
    link = tmp_path / "link.csv"
    link.symlink_to(log)
    rc = main(["train", str(log), "--config", str(SIM), "-o", str(link)])
    _one_line_error(capsys, rc, contains=["is the measurement log LOG.csv; refusing to overwrite an input"])
    assert log.read_bytes() == before


def test_gp_commands_refuse_to_overwrite_inputs(tmp_path, capsys):
    data = tmp_path / "d.csv"
    rng = np.random.default_rng(0)
    x = rng.uniform(0, 5, 30)
    data.write_text("x,y\n" + "".join(f"{float(a)!r},{float(np.sin(a) + 0.1 * b)!r}\n" for a, b in zip(x, rng.standard_normal(30))))
    before = data.read_bytes()
    rc = main(["gp", "fit", str(data), "--x", "x", "--y", "y", "-o", str(data)])
    _one_line_error(capsys, rc, contains=["is the data file DATA.csv"])
    assert data.read_bytes() == before
    model = tmp_path / "g.npz"
    assert main(["gp", "fit", str(data), "--x", "x", "--y", "y", "-o", str(model), "--restarts", "1", "--quiet"]) == 0
    capsys.readouterr()
    m_before = model.read_bytes()
    rc = main(["gp", "predict", str(model), str(data), "-o", str(model)])
    _one_line_error(capsys, rc, contains=["is the model file GP.npz"])
    assert model.read_bytes() == m_before


@pytest.mark.parametrize("argv, message", [
    (["collect", "--config", str(TABLE1), "-n", "3", "-o", "{tmp}"], "is a directory, expected a file name"),
    (["collect", "--config", str(TABLE1), "-n", "3", "-o", "{tmp}/nope/x.csv"], "the folder '{tmp}/nope' does not exist"),
    (["stage", "show", "--config", "{tmp}"], "cannot read: Is a directory"),
    (["solve", "--config", str(TABLE1), "--model", "{tmp}", "--target", "5"], "it is a directory"),
])
def test_directory_given_as_a_file(tmp_path, capsys, argv, message):
    rc = main([a.replace("{tmp}", str(tmp_path)) for a in argv])
    _one_line_error(capsys, rc, contains=[message.replace("{tmp}", str(tmp_path))])


def test_experiment_out_is_an_existing_file(tmp_path, capsys):
    out = tmp_path / "results.txt"
    out.write_text("keep me\n")
    rc = main(["experiment", str(QUICK), "--out", str(out)])
    _one_line_error(capsys, rc, contains=[f"--out {out}: is a file; give a folder"])
    assert out.read_text() == "keep me\n"


def test_experiment_out_unwritable(tmp_path, capsys):
    blocker = tmp_path / "file"
    blocker.write_text("")
    rc = main(["experiment", str(QUICK), "--out", str(blocker / "sub")])
    _one_line_error(capsys, rc, contains=[f"--out {blocker / 'sub'}: cannot write there: Not a directory"])


def test_experiment_refuses_to_overwrite_its_own_file(tmp_path, capsys):
    """Re-running the config.yaml an experiment wrote, into the same folder, would overwrite it."""
    doc = yaml.safe_load(QUICK.read_text())
    doc["stage"] = str(SIM)
    exp = tmp_path / "config.yaml"
    exp.write_text(yaml.safe_dump(doc))
    before = exp.read_bytes()
    rc = main(["experiment", str(exp), "--out", str(tmp_path)])
    _one_line_error(capsys, rc, contains=["writes config.yaml there, which is the experiment file"])
    assert exp.read_bytes() == before


def test_diagnose_refuses_to_overwrite_its_config(log40, tmp_path, capsys):
    """diagnose writes extended.yaml; a second round with --config out/extended.yaml --out out would lose it."""
    out = tmp_path / "out"
    out.mkdir()
    cfg = out / "extended.yaml"
    shutil.copy(SIM, cfg)
    rc = main(["diagnose", str(log40), "--config", str(cfg), "--out", str(out), "--quiet"])
    _one_line_error(capsys, rc, contains=["writes extended.yaml there, which is the stage config --config"])
    assert cfg.read_bytes() == SIM.read_bytes()


@pytest.mark.slow
def test_diagnose_outputs_are_listed(log40, tmp_path):
    """The list the input guard uses covers every file diagnose writes."""
    out = tmp_path / "d"
    assert main(["diagnose", str(log40), "--config", str(SIM), "--out", str(out), "--no-gp", "--quiet"]) == 0
    written = {p.name for p in out.iterdir()}
    assert written and written <= set(diagnose_cmd.OUTPUTS), written - set(diagnose_cmd.OUTPUTS)


@pytest.mark.parametrize("state, message", [
    ("0,100,0,0,0", "q1 = 100 µm is beyond the actuator's hardware limit [0, 38] µm"),
    ("0,1,2,3,-0.5", "q4 = -0.5 µm is beyond the actuator's hardware limit [0, 38] µm"),
    ("1e300,0,0,0,0", "t = 1e+300 µm is implausible"),
])
def test_solve_state_beyond_hardware_limit(tmp_path, capsys, state, message):
    rc = main(["solve", "--config", str(TABLE1), "--model", str(tmp_path / "unused.npz"), "--target", "5",
               "--state", state])
    _one_line_error(capsys, rc, contains=[message])


def test_ctrl_c_while_modules_load_prints_no_traceback(tmp_path):
    """SIGINT at several moments of start-up: exit 130, one line, never a traceback.

    The moments are observed, not timed: the child runs with ``-X importtime``, which writes a
    line to stderr as each module finishes importing, and SIGINT is sent as soon as the line of
    a chosen module appears, so each run is interrupted while the modules that follow it load
    (argparse and the command modules, NumPy, CasADi, SciPy, PyYAML), on a fast or a slow
    machine alike. All of them load inside ``main()`` (microctl.cli itself imports only ``sys``
    and microctl.errors), which is where the interrupt must be caught.
    """
    import threading

    cmd = [sys.executable, "-X", "importtime", "-m", "microctl", "collect", "--config", str(TABLE1), "-n", "300",
           "-o", str(tmp_path / "c.csv")]
    for module in ("argparse", "microctl.cli.commands", "numpy", "casadi", "scipy", "yaml"):
        p = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                             preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
        watchdog = threading.Timer(120, p.kill)  # a hung child fails the test instead of hanging it
        watchdog.start()
        try:
            lines = []
            for line in p.stderr:  # until `module` has been imported
                lines.append(line)
                if line.startswith("import time:") and line.rsplit("|", 1)[-1].strip() == module:
                    p.send_signal(signal.SIGINT)
                    break
            else:
                pytest.fail(f"{module} was never imported: {''.join(lines)[-2000:]}")
            lines += p.stderr.readlines()
            p.wait()
        finally:
            watchdog.cancel()
        err = "".join(line for line in lines if not line.startswith("import time:"))
        assert "Traceback" not in err, (module, err)
        assert (p.returncode, err) == (130, "microctl: interrupted\n"), (module, p.returncode, err)


def test_experiment_file_not_utf8(tmp_path, capsys):
    exp = tmp_path / "exp.yaml"
    exp.write_bytes(QUICK.read_bytes().replace(b"# A tiny", b"# A t\xefny"))
    rc = main(["experiment", str(exp), "--out", str(tmp_path / "out")])
    _one_line_error(capsys, rc, contains=["exp.yaml: not UTF-8 text: byte 0xef at line 1"])


def test_environment_oserror_is_one_line_exit_1(tmp_path, capsys, monkeypatch):
    """E.g. results.json on a full disk: one line, exit 1, the old file untouched, no temp file left."""
    import errno
    import json as _json

    from microctl.util import io as mio

    target = tmp_path / "results.json"
    target.write_text("{}\n")

    def full(self, *a, **k):
        raise OSError(errno.ENOSPC, "No space left on device", str(self))

    from microctl.util import atomic

    monkeypatch.setattr(atomic.os, "fsync", full)  # the disk fills while the temp file is written
    with pytest.raises(OSError):
        mio.write_json(target, {"a": 1})
    monkeypatch.undo()
    assert _json.loads(target.read_text()) == {} and [p.name for p in tmp_path.iterdir()] == ["results.json"]

    import microctl.cli.commands.stage as stage_cmd

    def boom(args):
        raise OSError(errno.ENOSPC, "No space left on device", str(target))

    monkeypatch.setattr(stage_cmd, "_show", boom)
    rc = main(["stage", "show", "--config", str(TABLE1)])
    _one_line_error(capsys, rc, want_rc=1, contains=[f"{target}: No space left on device"])


@pytest.mark.parametrize("start_q, message", [
    ("1,2,x,4", "--start-q '1,2,x,4': expected comma-separated positions in µm"),
    ("0,0,0,50", "start_q_um: q4 = 50 µm is beyond its limit_um [0, 38]"),
    ("0,0", "start_q_um: give 4 finite positions"),
])
def test_emulate_start_q_checked(capsys, start_q, message):
    rc = main(["emulate", "--config", str(ROOT / "configs/stage/emulated.yaml"), "--ports", "0,0,0",
               "--start-q", start_q])
    _one_line_error(capsys, rc, contains=[message])


def test_memory_error_is_one_line_exit_1(capsys, monkeypatch):
    import microctl.cli.commands.stage as stage_cmd

    def boom(args):
        raise MemoryError

    monkeypatch.setattr(stage_cmd, "_show", boom)
    rc = main(["stage", "show", "--config", str(TABLE1)])
    _one_line_error(capsys, rc, want_rc=1, contains=["microctl: error: out of memory"])
