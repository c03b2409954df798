"""Measurement log writer and reader: round trip and every error path."""

from pathlib import Path

import numpy as np
import pytest

from microctl.errors import DataError
from microctl.measurement.log import (
    Measurement,
    MeasurementLogWriter,
    log_columns,
    read_log,
)
from microctl.stage.config import load_stage_config
from microctl.stage.kinematics import inverse_kinematics_matrix

ROOT = Path(__file__).resolve().parents[2]
STAGE = load_stage_config(ROOT / "configs/stage/table1.yaml").stage
K = inverse_kinematics_matrix(STAGE)
HEADER = "seq,time_s,u_z,u_rx,u_ry,q1,q2,q3,q4,t_prev,q1_prev,q2_prev,q3_prev,q4_prev,t"


def _write(tmp_path, text, name="log.csv"):
    p = tmp_path / name
    p.write_text(text)
    return p


def test_header_and_round_trip_with_extra(tmp_path):
    assert ",".join(log_columns(STAGE)) == HEADER
    p = tmp_path / "log.csv"
    s = np.zeros(5)
    with MeasurementLogWriter(p, STAGE, extra_columns=("trial", "controller")) as w:
        for k in range(3):
            u = np.array([5.0 + k, 0.1, -0.1])
            m = Measurement(t_um=0.1 * k + 1 / 3, q_um=K @ u, u=u, time_s=k + 1.0)
            w.write(m, s, extra={"trial": 1, "controller": "afm"})
            # flushed row by row: readable while still open
            assert len(read_log(p, STAGE)) == k + 1
            s = np.concatenate([[m.t_um], m.q_um])
    log = read_log(p, STAGE, min_rows=3)
    assert log.t[0] == 1 / 3  # exact float round trip
    assert log.u.shape == (3, 3) and log.q.shape == (3, 4) and log.s_prev.shape == (3, 5)
    assert np.allclose(log.s_prev[1:], np.column_stack([log.t, log.q])[:-1])
    assert log.extra["controller"] == ("afm",) * 3 and log.extra_numeric("trial").tolist() == [1, 1, 1]
    assert log.time_s.tolist() == [1.0, 2.0, 3.0]


def test_prev_from_previous_row_when_absent(tmp_path):
    p = _write(tmp_path, "seq,u_z,u_rx,u_ry,q1,q2,q3,q4,t\n0,1,0,0,1,1,1,1,1.1\n1,2,0,0,2,2,2,2,2.2\n")
    log = read_log(p, STAGE)
    assert log.s_prev.tolist() == [[0, 0, 0, 0, 0], [1.1, 1, 1, 1, 1]]
    assert log.time_s is None and not log.prev_from_columns


ROW = "0,1,0,0,0,1,1,1,1,0,0,0,0,0,1.5"


@pytest.mark.parametrize(
    "text, match",
    [
        ("seq,time_s,u_z,u_rx,q1,q2,q3,q4,t\n0,0,0,0,0,0,0,0,0\n", r"log\.csv: missing required column 'u_ry'"),
        (f"{HEADER}\n{ROW}\n1,1,0,0,0,1,1,1,abc,0,0,0,0,0,1.5\n", r"log\.csv: row 3, column 'q4': 'abc' is not a number"),
        (f"{HEADER}\n{ROW}\n1,1,0,0,0,1,1,1,1,0,0,0,0,0,nan\n", r"log\.csv: row 3, column 't': value 'nan' is not finite"),
        (f"{HEADER}\n{ROW}\n0,1,0,0,0,1,1,1,1,0,0,0,0,0,1\n", r"log\.csv: row 3, column 'seq': duplicate seq 0"),
        (f"{HEADER}\n5,1,0,0,0,1,1,1,1,0,0,0,0,0,1\n{ROW}\n", r"log\.csv: row 3, column 'seq': seq 0 is not increasing"),
        (f"{HEADER}\n1.5,1,0,0,0,1,1,1,1,0,0,0,0,0,1\n", r"log\.csv: row 2, column 'seq'.*not a non-negative integer"),
        (f"{HEADER}\n{ROW}\n1,1,0,0,0,1,1,1,1,0,0,0,0\n", r"log\.csv: row 3 has 13 fields"),
        ("seq,u_z,u_rx,u_ry,q1,q2,q3,q4,t,t_prev\n0,0,0,0,0,0,0,0,0,0\n", r"log\.csv: .*previous-state columns.*'q1_prev'"),
        (f"{HEADER}\n{ROW}\n", r"log\.csv: 1 data rows, at least 5 needed"),
        ("", r"log\.csv: the file is empty"),
    ],
)
def test_reader_errors(tmp_path, text, match):
    p = _write(tmp_path, text)
    with pytest.raises(DataError, match=match):
        read_log(p, STAGE, min_rows=5 if "at least 5" in match else 1)


def test_missing_file(tmp_path):
    with pytest.raises(DataError, match="nope.csv: cannot read"):
        read_log(tmp_path / "nope.csv", STAGE)
