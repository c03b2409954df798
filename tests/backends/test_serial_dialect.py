"""Documented versus actual serial dialect (docs/serial-protocol.md), issue 12.

The page is parsed, not copied: its command table, its ERR? codes and its two "Sequence"
lines are compared with what the backend sends to the in-process emulator (loopback) and
with what the emulator answers. A change on either side without the other fails here.
"""

from __future__ import annotations

import re
import socket
from pathlib import Path

import numpy as np
import pytest
from serial_rig import START_Q, serial_config

from microctl.backends.emulator import Emulator
from microctl.backends.serial import GCS_ERRORS, SerialStage
from microctl.models.afm import AnalyticForwardModel

ROOT = Path(__file__).resolve().parents[2]
DOC = (ROOT / "docs/serial-protocol.md").read_text()


def _documented_table() -> dict[str, str]:
    """Command word → its reply text, from the PZT-driver table."""
    section = DOC[DOC.index("## PZT drivers"):DOC.index("## Gauge")]
    out = {}
    for line in section.splitlines():
        m = re.match(r"\|\s*(.+?)\s*\|\s*(.+?)\s*\|\s*$", line)
        if not m or m.group(1) in ("command", "---"):
            continue
        for cmd in re.findall(r"`([^`]+)`", m.group(1)):
            out[cmd.split()[0]] = m.group(2)
    return out


def _documented_sequence(name: str) -> list[str]:
    m = re.search(rf"^Sequence {name}: (.+)$", DOC, re.M)
    assert m, f"docs/serial-protocol.md has no 'Sequence {name}:' line"
    return re.findall(r"`([^`]+)`", m.group(1))


def _collapse(words: list[str]) -> list[str]:
    """Repeated polls count once (the docs write ``ONT?`` …)."""
    out: list[str] = []
    for w in words:
        if not out or out[-1] != w or w != "ONT?":
            out.append(w)
    return out


@pytest.fixture(scope="module")
def session():
    """Connect from a non-zero start, make 3 moves, read once: the emulator's log of every line."""
    cfg = serial_config()
    moves = AnalyticForwardModel(cfg.stage).workspace.sample(3, np.random.default_rng(2))
    with Emulator(cfg, start_q_um=START_Q, start_ont_polls=2, ont_polls=2) as emu:
        with SerialStage(emu.pointed_at(cfg)) as stage:
            for u in moves:
                stage.move(u)
            stage.read()
        log = list(emu.log)
    return cfg, log


def test_table_lists_exactly_the_commands_the_backend_sends(session):
    cfg, log = session
    sent = {line.split()[0] for dev, line in log if dev != "gauge"}
    assert sent == set(_documented_table())
    assert {line for dev, line in log if dev == "gauge"} == {cfg.backend.serial.gauge.query}


def test_documented_error_codes_are_the_backends():
    reply = _documented_table()["ERR?"]
    codes = {int(c) for c in re.findall(r"(\d+) [a-z]", reply)}
    assert codes - {0} == set(GCS_ERRORS)


def test_start_sequence(session):
    cfg, log = session
    want = _documented_sequence("at start")
    for ctrl in ("driver1", "driver2"):
        words = _collapse([line.split()[0] for dev, line in log if dev == ctrl])
        assert words[0] == "*IDN?"
        assert words[1:1 + len(want)] == want, (ctrl, words)


def test_move_sequence_one_mov_per_controller_with_every_mapped_axis(session):
    cfg, log = session
    want = _documented_sequence("per move")
    mapped = {"driver1": ["1", "2", "3"], "driver2": ["A"]}
    for ctrl, axes in mapped.items():
        words = _collapse([line.split()[0] for dev, line in log if dev == ctrl])
        start_len = 1 + len(_documented_sequence("at start"))
        per_move = words[start_len:]
        assert per_move == want * 3, (ctrl, per_move)  # 3 moves, each exactly the documented sequence
        movs = [line for dev, line in log if dev == ctrl and line.startswith("MOV")]
        for mov in movs:
            parts = mov.split()[1:]
            assert parts[::2] == axes  # every mapped axis, also unchanged ones
            assert all(re.fullmatch(r"-?\d+\.\d{6}", v) for v in parts[1::2])  # %.6f µm


def _ask(port: int, command: str) -> bytes:
    with socket.create_connection(("127.0.0.1", port), timeout=2) as s:
        s.sendall(command.encode("ascii") + b"\n")
        data = b""
        while not data.endswith(b"\n") or data.endswith(b" \n"):
            chunk = s.recv(4096)
            if not chunk:
                break
            data += chunk
        return data


def test_emulator_answers_as_documented():
    """Reply formats of the table: multi-line rule, ERR? codes, unknown command → 2."""
    cfg = serial_config()
    with Emulator(cfg, start_q_um=START_Q) as emu:
        port = emu.ports["driver1"]
        assert _ask(port, "*IDN?").count(b"\n") == 1
        pos = _ask(port, "POS? 1 2 3").decode()
        lines = pos.split("\n")[:-1]
        assert [ln.rstrip() for ln in lines] == ["1=19.000000", "2=4.400000", "3=16.300000"]
        assert all(ln.endswith(" ") for ln in lines[:-1]) and not lines[-1].endswith(" ")
        assert re.fullmatch(r"(\d=[01] \n){2}\d=[01]\n", _ask(port, "ONT? 1 2 3").decode())
        with socket.create_connection(("127.0.0.1", port), timeout=2) as s:
            s.sendall(b"FOO 1\n")
            s.sendall(b"ERR?\n")
            assert s.recv(64) == b"2\n"
            s.sendall(b"MOV 1 5.0\nERR?\n")  # servo still off
            assert s.recv(64) == b"10\n"
