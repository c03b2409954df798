"""``microctl stage show`` and the top-level CLI."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from microctl import __version__
from microctl.cli import main


def test_version(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["--version"])
    assert exc.value.code == 0
    assert __version__ in capsys.readouterr().out


def test_help_lists_commands(capsys):
    with pytest.raises(SystemExit):
        main(["--help"])
    assert "stage" in capsys.readouterr().out


def test_stage_show_json(table1_path, capsys):
    assert main(["stage", "show", "--config", str(table1_path), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["dof"] == ["z", "rx", "ry"]
    assert info["actuators"] == ["q1", "q2", "q3", "q4"]
    K = np.array(info["inverse_kinematics"])
    assert K.shape == (4, 3)
    np.testing.assert_allclose(K[0], [1, 0, -15])
    lo, hi = info["t_range_um"]
    assert lo < 0 < 7 < 28 < hi


def test_stage_show_table(table1_path, capsys):
    assert main(["stage", "show", "--config", str(table1_path)]) == 0
    out = capsys.readouterr().out
    assert "inverse kinematics q = K u" in out and "reachable t" in out


def test_usage_error_exit_2():
    proc = subprocess.run([sys.executable, "-m", "microctl", "stage", "show"], capture_output=True, text=True)
    assert proc.returncode == 2
    assert "--config" in proc.stderr
