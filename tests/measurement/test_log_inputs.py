"""Measurement-log reading and writing against bad input and a full disk (issue 12)."""

from __future__ import annotations

import errno
import json
import os
from pathlib import Path

import numpy as np
import pytest

from microctl.measurement import log as ml
from microctl.backends.collect import run_collect
from microctl.backends.simulated import SimulatedStage
from microctl.cli import main
from microctl.errors import DataError
from microctl.measurement.log import LogWriteError, MeasurementLogWriter, read_log
from microctl.models.afm import AnalyticForwardModel
from microctl.stage.config import load_stage_config
from microctl.util.tabular import parse_number

ROOT = Path(__file__).resolve().parents[2]
STAGE_YAML = ROOT / "configs/stage/table1.yaml"
CFG = load_stage_config(STAGE_YAML)


@pytest.fixture(scope="module")
def good_log(tmp_path_factory) -> Path:
    """A 12-move log of the simulated Table I stage (valid by construction)."""
    path = tmp_path_factory.mktemp("log") / "good.csv"
    moves = AnalyticForwardModel(CFG.stage).workspace.sample(12, np.random.default_rng(3))
    with SimulatedStage(CFG, seed=4) as stage:
        run_collect(stage, moves, path, quiet=True)
    return path


def _edit(src: Path, dst: Path, row: int, column: str, value: str) -> Path:
    """Copy a log, setting ``column`` on file line ``row`` (header = 1) to ``value``."""
    lines = src.read_text().splitlines()
    header = lines[0].split(",")
    cells = lines[row - 1].split(",")
    cells[header.index(column)] = value
    lines[row - 1] = ",".join(cells)
    dst.write_text("\n".join(lines) + "\n")
    return dst


def test_good_log_reads(good_log):
    log = read_log(good_log, CFG.stage)
    assert len(log) == 12 and log.prev_from_columns


@pytest.mark.parametrize("text", ["1_0.5", "1_000", "\u0661\u0662", "0x10", "1,5", "1.5.2", "e3", "--1", "1e"])
def test_parse_number_is_strict(text):
    with pytest.raises(DataError, match=r"f\.csv: row 3, column 'q1': .* is not a number"):
        parse_number(text, "f.csv", 3, "q1")


@pytest.mark.parametrize("text, value", [("12", 12.0), (" -0.5 ", -0.5), (".5", 0.5), ("5.", 5.0),
                                         ("+1.5e-3", 1.5e-3), ("2E+2", 200.0)])
def test_parse_number_accepts_decimals(text, value):
    assert parse_number(text, "f.csv", 2, "x") == value


def test_parse_number_overflow_is_not_finite():
    with pytest.raises(DataError, match=r"value '1e400' is not finite \(beyond the float range\)"):
        parse_number("1e400", "f.csv", 2, "x")


@pytest.mark.parametrize("row, column, value, match", [
    (4, "q2", "1_0.5", r"row 4, column 'q2': '1_0.5' is not a number"),
    (5, "seq", "1e30", r"row 5, column 'seq': '1e30' is too large \(at most 9007199254740992\)"),
    (3, "t", "1e300", r"row 3, column 't': 1e\+300 µm is implausible: the stage reaches at most \|t\| = [\d.]+ µm"),
    (3, "t_prev", "-5000", r"row 3, column 't_prev': -5000 µm is implausible"),
    (6, "u_z", "100", r"row 6, columns u_z,u_rx,u_ry: u = \[100, .*\] is outside the workspace: K u puts actuator "
                      r"q\d at [\d.]+ µm, outside its range \[0, 32\] µm"),
    (7, "q3", "32.5", r"row 7, column 'q3': 32.5 µm is outside the actuator's range \[0, 32\] µm"),
    (7, "q3", "-1", r"row 7, column 'q3': -1 µm is outside the actuator's range"),
    (8, "q1", None, r"row 8, column 'q1': .* µm differs from K u = .* by 0.5 µm \(tolerance 0.01 µm\)"),
    (9, "q4_prev", "45", r"row 9, column 'q4_prev': 45 µm is outside the actuator's hardware limit \[0, 38\] µm"),
    (2, "time_s", "-1", r"row 2, column 'time_s': -1 s is outside \[0, 1e\+09\]"),
    (4, "time_s", "1e300", r"row 4, column 'time_s': 1e\+300 s is outside"),
    (6, "time_s", "0.5", r"row 6, column 'time_s': 0.5 s is earlier than 4 s on row 5; time_s must not decrease"),
])
def test_reader_refuses_impossible_rows(good_log, tmp_path, row, column, value, match):
    if value is None:  # half a µm off K u, still inside the range
        lines = good_log.read_text().splitlines()
        q = float(lines[row - 1].split(",")[lines[0].split(",").index(column)])
        value = repr(q + 0.5 if q < 31 else q - 0.5)
    bad = _edit(good_log, tmp_path / "bad.csv", row, column, value)
    with pytest.raises(DataError, match=r"bad\.csv: " + match):
        read_log(bad, CFG.stage)


def test_tolerance_admits_rounded_logs(good_log, tmp_path):
    """A log written with 4 decimals (a user's rig) still reads."""
    lines = good_log.read_text().splitlines()
    out = [lines[0]]
    for line in lines[1:]:
        cells = line.split(",")
        out.append(",".join([cells[0]] + [f"{float(c):.4f}" for c in cells[1:]]))
    p = tmp_path / "rounded.csv"
    p.write_text("\n".join(out) + "\n")
    assert len(read_log(p, CFG.stage)) == 12


def test_bom_in_header_is_skipped(good_log, tmp_path):
    p = tmp_path / "bom.csv"
    p.write_bytes(b"\xef\xbb\xbf" + good_log.read_bytes())
    a, b = read_log(p, CFG.stage), read_log(good_log, CFG.stage)
    assert np.array_equal(a.t, b.t) and np.array_equal(a.seq, b.seq)


def test_non_utf8_and_nul_bytes(good_log, tmp_path):
    p = tmp_path / "latin1.csv"
    p.write_bytes(good_log.read_bytes().replace(b"\n", b"\n\xe9", 1))
    with pytest.raises(DataError, match=r"latin1\.csv: not a text CSV file: byte 0xe9 on line 2 is not UTF-8"):
        read_log(p, CFG.stage)
    p = _edit(good_log, tmp_path / "nul.csv", 3, "q2", "1\x002")
    with pytest.raises(DataError, match=r"nul\.csv: row 3, column 'q2': '1\\x002' is not a number"):
        read_log(p, CFG.stage)
    p = _edit(good_log, tmp_path / "long.csv", 3, "q2", "1" * 200_000)
    with pytest.raises(DataError, match=r"long\.csv: line 3: not a valid CSV line: field larger than field limit"):
        read_log(p, CFG.stage)


def test_cli_huge_t_is_one_line_exit_2(good_log, tmp_path, capsys):
    bad = _edit(good_log, tmp_path / "huge.csv", 5, "t", "1e300")
    out = tmp_path / "m.npz"
    assert main(["train", str(bad), "--config", str(STAGE_YAML), "-o", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1, err
    assert "huge.csv: row 5, column 't': 1e+300 µm is implausible" in err
    assert not out.exists()


@pytest.mark.slow
def test_diagnose_sets_an_implausible_row_aside_as_an_outlier(tmp_path, capsys):
    """diagnose reads what train refuses: a corrupt cell is an outlier to name by row (issue 11),
    with a one-line note naming the file, row and column, and the run completes."""
    log = tmp_path / "log.csv"
    assert main(["collect", "--config", str(STAGE_YAML), "-n", "60", "--seed", "1", "-o", str(log), "--quiet"]) == 0
    bad = _edit(log, tmp_path / "huge.csv", 20, "t", "1e300")
    assert main(["diagnose", str(bad), "--config", str(STAGE_YAML), "--out", str(tmp_path / "diag"), "--no-gp"]) == 0
    err = capsys.readouterr().err
    assert "huge.csv: row 20, t: 1e+300 µm is implausible" in err and "set aside as an outlier" in err
    report = json.loads((tmp_path / "diag" / "report.json").read_text())
    assert [r["line"] for r in report["outliers"]["rows"]] == [20]


# ---- the writer on a full disk ---------------------------------------------------------------


def _measure(stage, u):
    s_prev = stage.state
    return stage.move(u), s_prev


def test_full_disk_cuts_partial_row_and_keeps_completed(tmp_path, monkeypatch):
    path = tmp_path / "log.csv"
    moves = AnalyticForwardModel(CFG.stage).workspace.sample(5, np.random.default_rng(1))
    real_write = os.write
    calls = {"rows": 0}

    def write(fd, data):
        if fd == writer._fh.fileno():
            calls["rows"] += 1
            if calls["rows"] > 2:
                real_write(fd, bytes(data[: len(data) // 2]))  # half a row reaches the disk
                raise OSError(errno.ENOSPC, "No space left on device")
        return real_write(fd, data)

    with SimulatedStage(CFG) as stage:
        writer = MeasurementLogWriter(path, CFG.stage)
        monkeypatch.setattr(ml.os, "write", write)
        with pytest.raises(LogWriteError, match=r"log\.csv: cannot write the row of move 3 \(the move was executed\): "
                                                 r"No space left on device; the log keeps the 2 completed moves"):
            for u in moves:
                m, s_prev = _measure(stage, u)
                writer.write(m, s_prev)
        writer.close()
    monkeypatch.undo()
    text = path.read_text()
    assert text.endswith("\n") and text.count("\n") == 3  # header + 2 complete rows, no half row
    assert len(read_log(path, CFG.stage)) == 2


def test_cli_collect_to_full_device_exit_1(capsys):
    if not Path("/dev/full").exists():
        pytest.skip("no /dev/full on this system")
    assert main(["collect", "--config", str(STAGE_YAML), "-n", "3", "-o", "/dev/full", "--force", "--quiet"]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "/dev/full: cannot write the header: No space left on device" in err
