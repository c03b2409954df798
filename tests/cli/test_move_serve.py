"""``microctl move`` and ``microctl serve`` against the simulator and the serial emulator."""

from __future__ import annotations

import io
import json
import os
import random
import re
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from serial_rig import serial_config

from microctl import api
from microctl.backends import make_backend
from microctl.backends.emulator import Emulator
from microctl.backends.simulated import SimulatedStage
from microctl.cli import main
from microctl.cli.commands.serve import OPS, Service, serve_lines
from microctl.errors import UnreachableTargetError
from microctl.measurement.log import read_log
from microctl.util import signals

ROOT = Path(__file__).resolve().parents[2]
CONFIG = ROOT / "configs/stage/sim_paper.yaml"
ENV = {**os.environ, "PYTHONPATH": str(ROOT)}


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """A 40-move log of the default design on sim_paper's simulator and the model trained on it (same
    geometry as emulated.yaml)."""
    d = tmp_path_factory.mktemp("move")
    stage = api.load_stage(CONFIG)
    log = d / "train.csv"
    assert api.collect(stage, 40, log, seed=1) == 40
    model = d / "model.npz"
    api.train(log, stage, out=model, restarts=1, seed=0)
    return stage, log, model


def _rows(path: Path) -> list[str]:
    text = path.read_text()
    assert text.endswith("\n")  # every line complete
    return text.splitlines()[1:]


def test_move_appends_every_move_and_the_log_trains(trained, tmp_path, capsys):
    stage, train_log, model = trained
    log = tmp_path / "moves.csv"
    log.write_bytes(train_log.read_bytes())  # append to the training log itself
    assert main(["move", "--config", str(CONFIG), "--model", str(model), "--targets", "5,12.5,20", "--log", str(log),
                 "--json", "--quiet"]) == 0
    recs = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    assert main(["move", "--config", str(CONFIG), "--model", str(model), "--target", "-3", "--log", str(log),
                 "--quiet"]) == 0
    out = capsys.readouterr().out
    got = read_log(log, stage.config.stage)
    assert len(got) == 44
    assert got.seq.tolist() == list(range(44))
    assert np.all(np.diff(got.time_s) > 0)  # a second run's clock continues the log's
    assert [r["seq"] for r in recs] == [40, 41, 42]
    assert got.t[40:43].tolist() == pytest.approx([r["measured_um"] for r in recs], abs=0)
    np.testing.assert_array_equal(got.u[40:43], [[r["u"][n] for n in stage.dof] for r in recs])
    for r in recs:  # the prediction is on target; the measured pose within a few predicted std
        assert r["predicted_um"] == pytest.approx(r["target_um"], abs=1e-6)
        assert abs(r["measured_um"] - r["target_um"]) < 1.0
    assert re.search(r"^\s+43\s+-3\.0000\s+-3\.0000\s+\d\.\d{4}\s+-?\d+\.\d{4}", out, re.M), out
    assert main(["train", str(log), "--config", str(CONFIG), "-o", str(tmp_path / "m2.npz"), "--restarts", "1",
                 "--quiet"]) == 0


def test_move_refuses_an_unreachable_target_before_moving(trained, tmp_path, capsys):
    stage, _, model = trained
    log = tmp_path / "moves.csv"
    rc = main(["move", "--config", str(CONFIG), "--model", str(model), "--targets", "5,900", "--log", str(log)])
    err = capsys.readouterr().err
    assert rc == 2 and "900" in err and "nothing was moved" in err
    assert _rows(log) == []
    for bad in (["--target", "nan"], ["--targets", "1,x"], ["--target", "inf"]):
        assert main(["move", "--config", str(CONFIG), "--model", str(model), *bad, "--log", str(log)]) == 2
    assert _rows(log) == []


class _Recording(SimulatedStage):
    """The simulator, recording every actuator command it is sent."""

    def __init__(self, *a, **kw):
        super().__init__(*a, **kw)
        self.sent: list[np.ndarray] = []

    def move(self, u):
        _, q = self.command_for(u)
        self.sent.append(q)
        return super().move(u)


def test_move_never_commands_outside_the_configured_ranges(trained, tmp_path):
    stage, _, model = trained
    ctl = api.Controller(stage, model)
    backend = _Recording(stage.config, seed=3)
    lo_r, hi_r = stage.range_um
    with api.Operator(ctl, backend, log=tmp_path / "edge.csv") as op:
        rng = np.random.default_rng(0)
        for k in range(8):
            lo, hi = ctl.reachable_interval(op.state)
            # the ends of what the stage reaches, where the optimum presses against the ranges
            t = lo + 0.01 * (hi - lo) if k % 2 else hi - 0.01 * (hi - lo)
            if k >= 4:
                t = rng.uniform(lo, hi)
            op.move(t)
        with pytest.raises(UnreachableTargetError):
            op.move(hi + 1.0)
    q = np.array(backend.sent)
    assert len(q) == 8
    assert np.all(q >= lo_r) and np.all(q <= hi_r)
    assert len(read_log(tmp_path / "edge.csv", stage.config.stage)) == 8


class _InterruptedDuringMove(SimulatedStage):
    """A simulator that receives Ctrl-C (SIGINT) while executing its second move."""

    calls = 0

    def move(self, u):
        self.calls += 1
        if self.calls == 2:
            # raised in this (the main) thread, so its handler runs here, inside the move; a
            # process-directed os.kill failed this test in the full suite only (twice, never in
            # any subset I ran); the real Ctrl-C of a terminal is the next test's, in a subprocess
            signal.raise_signal(signal.SIGINT)
        return super().move(u)


def test_ctrl_c_during_a_move_still_logs_it(trained, tmp_path):
    stage, _, model = trained
    log = tmp_path / "int.csv"
    # the interpreter's own handler, whatever an earlier test left (restored after the test)
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        with api.Operator(api.Controller(stage, model), _InterruptedDuringMove(stage.config), log=log) as op:
            op.move(5.0)
            with pytest.raises(KeyboardInterrupt):
                op.move(6.0)
            assert op.moves == 2
    finally:
        signal.signal(signal.SIGINT, previous)
    got = read_log(log, stage.config.stage)
    assert len(got) == 2 and got.seq.tolist() == [0, 1]


class _SwallowingController:
    """A controller whose solve received a Ctrl-C whose KeyboardInterrupt was lost: the command
    line's handler recorded it (microctl.util.signals.RECEIVED) but no KeyboardInterrupt came out."""

    def __init__(self, inner):
        self.inner = inner

    def __getattr__(self, name):
        return getattr(self.inner, name)

    def solve(self, *a, **kw):
        res = self.inner.solve(*a, **kw)
        signals.RECEIVED.append(signal.SIGINT)
        return res


def test_a_ctrl_c_swallowed_during_the_solve_stops_before_the_command_is_sent(trained, tmp_path):
    """A Ctrl-C recorded during the solve but lost on its way out (once seen end to end: `move`
    ran all 400 targets of the next test's sequence, then exited 130): the Operator stops before
    it sends that move's command, the log holding exactly the moves made."""
    stage, _, model = trained
    log = tmp_path / "sw.csv"
    backend = SimulatedStage(stage.config)
    ctl = api.Controller(stage, model)
    try:
        with api.Operator(ctl, backend, log=log) as op:
            op.move(5.0)
            op.controller = _SwallowingController(ctl)
            with pytest.raises(KeyboardInterrupt):
                op.move(6.0)
            assert op.moves == 1
            state = backend.state.copy()
        np.testing.assert_array_equal(backend.state, state)
    finally:
        signals.RECEIVED.clear()
    assert len(read_log(log, stage.config.stage)) == 1


def test_ctrl_c_on_the_command_line_leaves_the_log_complete(trained, tmp_path):
    stage, _, model = trained
    log = tmp_path / "cc.csv"
    targets = ",".join(f"{t:.2f}" for t in np.linspace(-20, 30, 400))
    p = subprocess.Popen([sys.executable, "-m", "microctl", "move", "--config", str(CONFIG), "--model", str(model),
                          f"--targets={targets}", "--log", str(log)], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                         text=True, env=ENV)
    printed = 0
    p.stdout.readline()  # header
    while printed < 3:
        assert p.stdout.readline().strip()
        printed += 1
    p.send_signal(signal.SIGINT)
    out, err = p.communicate(timeout=60)
    printed += len(out.splitlines())
    assert p.returncode == 130 and "interrupted" in err
    rows = _rows(log)
    assert printed <= len(rows) <= printed + 1 < 400  # the move under way when Ctrl-C came is logged too
    assert len(read_log(log, stage.config.stage)) == len(rows)


def test_move_through_the_serial_backend_on_the_emulator(trained, tmp_path):
    """The API over the serial backend (in-process emulator): the state read at connect is where moves start."""
    stage, _, model = trained
    cfg = serial_config()
    start_q = [3.0, 4.0, 5.0, 6.0]
    with Emulator(cfg, start_q_um=start_q, ont_polls=1) as emu:
        pointed = emu.pointed_at(cfg)
        st = api.Stage(pointed, stage.afm)
        with api.Operator(api.Controller(st, model), make_backend(pointed), log=tmp_path / "ser.csv") as op:
            s0 = op.state
            recs = [op.move(t) for t in (8.0, 15.0, 2.0)]
    assert s0[1:].tolist() == pytest.approx(start_q, abs=1e-6)
    assert recs[0].state_before.tolist() == pytest.approx(s0.tolist())
    got = read_log(tmp_path / "ser.csv", stage.config.stage)
    assert got.s_prev[0, 1:].tolist() == pytest.approx(start_q, abs=1e-6)
    assert got.t.tolist() == pytest.approx([r.measured_um for r in recs], abs=1e-9)
    assert got.s_prev[1:, 0].tolist() == pytest.approx(got.t[:-1].tolist(), abs=1e-9)


def test_move_command_against_microctl_emulate(trained, tmp_path):
    """`microctl move` on configs/stage/emulated.yaml served by a `microctl emulate` process."""
    stage, _, model = trained
    emu = subprocess.Popen([sys.executable, "-m", "microctl", "emulate", "--config",
                            str(ROOT / "configs/stage/emulated.yaml"), "--ports", "0,0,0", "--quiet"],
                           stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=ENV)
    try:
        ports = {}
        while len(ports) < 3:
            line = emu.stdout.readline()
            assert line, emu.stderr.read()
            m = re.match(r"emulate: (\S+) on socket://127\.0\.0\.1:(\d+)", line)
            if m:
                ports[m.group(1)] = m.group(2)
        text = (ROOT / "configs/stage/emulated.yaml").read_text()
        for dev, default in (("driver1", "50101"), ("driver2", "50102"), ("gauge", "50103")):
            text = text.replace(f"127.0.0.1:{default}", f"127.0.0.1:{ports[dev]}")
        cfg = tmp_path / "emu.yaml"
        cfg.write_text(text)
        log = tmp_path / "emu.csv"
        r = subprocess.run([sys.executable, "-m", "microctl", "move", "--config", str(cfg), "--model", str(model),
                            "--targets", "4,9,-2", "--log", str(log), "--json", "--quiet"], capture_output=True,
                           text=True, env=ENV, timeout=120)
        assert r.returncode == 0, r.stderr
    finally:
        emu.send_signal(signal.SIGINT)
        emu.communicate(timeout=30)
    recs = [json.loads(line) for line in r.stdout.splitlines()]
    got = read_log(log, stage.config.stage)
    assert len(recs) == len(got) == 3
    assert got.t.tolist() == pytest.approx([x["measured_um"] for x in recs], abs=1e-9)
    assert all(abs(x["measured_um"] - x["target_um"]) < 2.0 for x in recs)


# --------------------------------------------------------------------------- serve


def _serve(service: Service, lines: list[bytes], max_bytes: int = 4096) -> list[dict]:
    out = io.StringIO()
    serve_lines(service, io.BytesIO(b"".join(lines)), out, max_bytes)
    return [json.loads(line) for line in out.getvalue().splitlines()]


@pytest.fixture
def service(trained, tmp_path):
    stage, _, model = trained
    op = api.Operator(api.Controller(stage, model), stage.open_backend(), log=tmp_path / "serve.csv")
    yield Service(op.controller, op, can_move=True)
    op.close()


def test_serve_answers_each_operation(service, tmp_path, trained):
    _, _, model = trained
    reqs = [{"op": "state", "id": 1}, {"op": "solve", "target_um": 12.0, "id": "a"},
            {"op": "solve", "target_um": 12.0, "state": [1, 2, 3, 4, 5], "baseline": True},
            {"op": "move", "target_um": 7.5, "id": 2}, {"op": "state"}, {"op": "reload", "model": str(model)},
            {"op": "solve", "target_um": 900}]
    resp = _serve(service, [json.dumps(r).encode() + b"\n" for r in reqs])
    assert [r["ok"] for r in resp] == [True] * 6 + [False]
    assert resp[0]["id"] == 1 and resp[0]["result"]["state"]["t"] == 0.0 and resp[0]["result"]["moves"] == 0
    assert resp[1]["id"] == "a" and resp[1]["result"]["predicted_um"] == pytest.approx(12.0, abs=1e-6)
    assert resp[2]["result"]["state"]["q4"] == 5.0 and "vs_baseline" in resp[2]["result"]
    mv = resp[3]["result"]
    assert resp[4]["result"]["state"]["t"] == mv["measured_um"] and resp[4]["result"]["moves"] == 1
    assert resp[6]["error"]["code"] == "unreachable"
    assert len(read_log(tmp_path / "serve.csv", service.controller.stage.config.stage)) == 1


def test_serve_refuses_moves_without_a_log_and_oversized_lines(service):
    service.can_move = False
    resp = _serve(service, [b'{"op": "move", "target_um": 3}\n', b'{"op": "state", "pad": "' + b"x" * 9000 + b'"}\n',
                            b'{"op": "state"}\n'])
    assert [r["ok"] for r in resp] == [False, False, True]
    assert resp[0]["error"]["code"] == "no_log" and resp[1]["error"]["code"] == "too_large"
    assert service.operator.moves == 0


#: Values that make each field of a request invalid.
_BAD = {
    "target_um": [None, True, "12", [], {}, 1e308, -1e308, 10**400, "", "x" * 300, "nan", [1.0], {"v": 1}],
    "state": [True, "12", [], {}, [1, 2], [1, 2, 3, 4, 5, 6], [0, 0, 0, 0, 1e9], [0, -50, 0, 0, 0], {"t": 1},
              {"t": 0, "q1": 0, "q2": 0, "q3": 0, "q4": "a"}, [None] * 5, [[0]] * 5, "x"],
    "baseline": [None, "12", 1, [], {}, "true"],
    "model": [True, 12, [], "", "x" * 5000, "/dev/null", "../../etc/passwd", "no_such_model.npz", "a\u0000b"],
    "op": [None, 1, "", "SOLVE", "solve ", "quit", "exec", ["solve"], {"op": "solve"}],
}


def _malformed(rng: random.Random) -> bytes:
    """One malformed request line (seeded): bad bytes, bad JSON, wrong shapes, types and values."""
    good = [{"op": "solve", "target_um": 10.0}, {"op": "move", "target_um": 3.0}, {"op": "state"},
            {"op": "reload", "model": "x.npz"}, {"op": "solve", "target_um": 1.0, "state": [0, 0, 0, 0, 0]}]
    kind = rng.randrange(8)
    if kind == 0:  # random bytes (after a '#', so never a blank line)
        return b"#" + bytes(rng.randrange(256) for _ in range(rng.randrange(1, 200))).replace(b"\n", b" ") + b"\n"
    if kind == 1:  # a valid request cut short
        s = json.dumps(rng.choice(good))
        return s[: rng.randrange(1, len(s))].encode() + b"\n"
    if kind == 2:  # one field with an invalid value (or a field the operation does not take)
        req = dict(rng.choice(good))
        key = rng.choice(["target_um", "state", "baseline", "model", "op"])
        req[key] = rng.choice(_BAD[key])
        if key != "op" and key in OPS[req["op"]] and "target_um" in OPS[req["op"]]:
            req.setdefault("target_um", 5.0)
        return json.dumps(req).encode() + b"\n"
    if kind == 3:  # not an object
        return json.dumps(rng.choice([None, True, 5, "solve", [], [{"op": "state"}], 1e300])).encode() + b"\n"
    if kind == 4:  # deep nesting
        depth = rng.choice([100, 5000, 20000])
        return (b"[" * depth + b"]" * depth)[:60000] + b"\n"
    if kind == 5:  # non-standard numbers
        return rng.choice([b'{"op": "solve", "target_um": NaN}', b'{"op": "solve", "target_um": 1e999}',
                           b'{"op": "solve", "target_um": -Infinity}', b'{"op": "move", "target_um": Infinity}']) + b"\n"
    if kind == 6:  # targets far out of reach
        t = rng.choice([-1, 1]) * 10 ** rng.uniform(2.5, 6)
        return json.dumps({"op": rng.choice(["solve", "move"]), "target_um": t}).encode() + b"\n"
    return b'{"op": "state", "id": ' + json.dumps(rng.choice(_BAD["state"])).encode() + b', "x": 1}\n'


def test_serve_survives_a_fuzz_of_600_malformed_requests(service):
    rng = random.Random(20261124)
    lines = [_malformed(rng) for _ in range(600)]
    lines.insert(300, b"x" * 5000 + b"\n")  # over the bound
    resp = _serve(service, lines + [b'{"op": "state", "id": "after"}\n'])
    assert len(resp) == 602
    codes = {r["error"]["code"] for r in resp[:-1] if not r["ok"]}
    assert all(not r["ok"] for r in resp[:-1]), [r for r in resp[:-1] if r["ok"]][:3]
    assert "internal" not in codes and codes <= {"bad_json", "bad_encoding", "bad_request", "too_large", "input",
                                                 "unreachable"}, codes
    assert resp[-1] == {**resp[-1], "id": "after", "ok": True}
    assert service.operator.moves == 0


def test_serve_process_survives_malformed_input(trained, tmp_path):
    stage, _, model = trained
    rng = random.Random(7)
    lines = [_malformed(rng) for _ in range(60)] + [b'{"op": "move", "target_um": 6}\n', b'{"op": "state"}\n']
    r = subprocess.run([sys.executable, "-m", "microctl", "serve", "--config", str(CONFIG), "--model", str(model),
                        "--log", str(tmp_path / "s.csv"), "--max-request-bytes", "1024", "--quiet"],
                       input=b"".join(lines), capture_output=True, env=ENV, timeout=120)
    assert r.returncode == 0 and r.stderr == b""
    resp = [json.loads(line) for line in r.stdout.splitlines()]
    assert len(resp) == 62 and resp[-2]["ok"] and resp[-1]["result"]["moves"] == 1
    assert len(read_log(tmp_path / "s.csv", stage.config.stage)) == 1


def test_serve_tcp_answers_clients_in_turn_and_survives_a_dropped_one(trained, tmp_path):
    """serve --tcp 0: loopback only, the port on stderr; a client's requests answered in order, a
    client that drops mid-line costs only its connection, the next client is served; Ctrl-C ends
    it with 130 and the log holds every move made."""
    import socket

    stage, _, model = trained
    log = tmp_path / "tcp.csv"
    proc = subprocess.Popen([sys.executable, "-m", "microctl", "serve", "--config", str(CONFIG), "--model", str(model),
                             "--log", str(log), "--tcp", "0", "--max-request-bytes", "1024"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=ENV)
    try:
        port = None
        for _ in range(50):
            line = proc.stderr.readline()
            if m := re.match(r"serve: listening on 127\.0\.0\.1:(\d+)", line):
                port = int(m.group(1))
                break
        assert port, "no listening line"

        def ask(lines: list[bytes]) -> list[dict]:
            with socket.create_connection(("127.0.0.1", port), timeout=60) as c:
                c.sendall(b"".join(lines))
                c.shutdown(socket.SHUT_WR)
                data = b"".join(iter(lambda: c.recv(65536), b""))
            return [json.loads(x) for x in data.decode("ascii").splitlines()]

        first = ask([b'{"op": "solve", "target_um": 9, "id": 1}\n', b"not json\n", b"x" * 2000 + b"\n",
                     b'{"op": "move", "target_um": 6, "id": 2}\n'])
        assert [r["ok"] for r in first] == [True, False, False, True]
        assert [r["id"] for r in first] == [1, None, None, 2]
        assert first[1]["error"]["code"] == "bad_json" and first[2]["error"]["code"] == "too_large"
        with socket.create_connection(("127.0.0.1", port), timeout=60) as c:  # drops mid-request
            c.sendall(b'{"op": "move", "targ')
        second = ask([b'{"op": "state"}\n'])
        assert second[0]["ok"] and second[0]["result"]["moves"] == 1
    finally:
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=60)
    assert proc.returncode == 130 and "Traceback" not in err, err
    assert len(read_log(log, stage.config.stage)) == 1


def test_serve_tcp_port_in_use_is_refused(service):
    import socket

    from microctl.cli.commands.serve import serve_tcp
    from microctl.errors import ConfigError

    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen(1)
        port = taken.getsockname()[1]
        with pytest.raises(ConfigError, match=rf"--tcp {port}: cannot listen on 127\.0\.0\.1:{port} .*choose a free port"):
            serve_tcp(service, port, 4096, quiet=True)


def test_serve_tcp_port_out_of_range_is_refused(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["serve", "--config", str(CONFIG), "--model", "m.npz", "--tcp", "70000"])
    assert exc.value.code == 2 and "--tcp" in capsys.readouterr().err


def test_move_learn_refits_into_versioned_model_files(trained, tmp_path, capsys):
    """--learn --refit-every 3: after moves 3 and 6 a refit on the whole log, each a new version whose
    manifest line names the rows it was trained on; retraining those rows reproduces it."""
    stage, train_log, model0 = trained
    model = tmp_path / "model.npz"
    model.write_bytes(model0.read_bytes())
    log = tmp_path / "learn.csv"
    log.write_bytes(train_log.read_bytes())
    assert main(["move", "--config", str(CONFIG), "--model", str(model), "--targets", "3,6,9,12,15,18,21",
                 "--log", str(log), "--learn", "--refit-every", "3"]) == 0
    err = capsys.readouterr().err
    assert err.count("refit on the log's") == 2
    v1, v2 = tmp_path / "model.v1.npz", tmp_path / "model.v2.npz"
    assert v1.is_file() and v2.is_file() and not (tmp_path / "model.v3.npz").exists()
    assert model.read_bytes() == model0.read_bytes()  # the original is never overwritten
    entries = [json.loads(line) for line in (tmp_path / "model.versions.jsonl").read_text().splitlines()]
    assert [(e["version"], e["rows"]) for e in entries] == [(1, 43), (2, 46)]
    from microctl.gp.vhgpr import FittedVHGPR

    assert FittedVHGPR.load(v1).X.shape[0] == 43 and FittedVHGPR.load(v2).X.shape[0] == 46
    assert len(read_log(log, stage.config.stage)) == 47
    rows = tmp_path / "rows.csv"
    rows.write_text("".join(log.read_text().splitlines(keepends=True)[: 46 + 1]))
    import hashlib

    assert hashlib.sha256(rows.read_bytes()).hexdigest() == entries[1]["log_sha256"]
    again = api.train(rows, stage, restarts=entries[1]["restarts"], seed=entries[1]["seed"])
    np.testing.assert_allclose(again.predict(again.X[:5]).f_mean, FittedVHGPR.load(v2).predict(again.X[:5]).f_mean,
                               rtol=1e-9)


def test_learner_update_folds_each_move_into_the_model(trained, tmp_path):
    """Learner(update=True): between refits every move is added to the controller's model at once
    (microctl.gp.sparse.update), and the model's mean moves toward the residuals it was shown."""
    stage, train_log, model0 = trained
    log = tmp_path / "u.csv"
    log.write_bytes(train_log.read_bytes())
    ctl = api.Controller(stage, model0)
    before = ctl.eafm.model
    with api.Operator(ctl, stage.open_backend(), log=log) as op:
        learner = api.Learner(op, model0, every=1000, update=True)
        records = []
        for t in (4.0, 9.0, 14.0, 19.0, 24.0):
            records.append(op.move(t))
            assert learner.after_move(records[-1]) is None
    after = ctl.eafm.model
    assert after is not before and after.posterior_form == "sparse"
    assert after.info["sparse"]["updates"] == 5
    X = np.array([np.concatenate([r.state_before, r.u]) for r in records])
    y = np.array([r.measured_um for r in records]) - stage.afm.t_of(np.array([r.u for r in records]))
    # the updated mean is nearer the residuals it was given than the model that had not seen them, in
    # the norm weighted by the noise variances R the model gives them: conditioning a GP on readings y
    # leaves the residual R (K + R)^-1 (y - m) at them, whose R^-1/2-norm is below that of y - m (the
    # eigenvalues of R^1/2 (K + R)^-1 R^1/2 lie in (0, 1)); a plain mean of |residuals| need not fall
    # (on the same 40 moves drawn from the covering_still design the plain mean rose while this norm fell)
    prior = before.predict(X)
    R = np.exp(prior.g_mean)
    assert np.sum((y - after.predict(X).f_mean) ** 2 / R) < np.sum((y - prior.f_mean) ** 2 / R)
    assert len(read_log(log, stage.config.stage)) == 45


def test_update_needs_learn(trained, tmp_path, capsys):
    stage, train_log, model0 = trained
    rc = main(["move", "--config", str(CONFIG), "--model", str(model0), "--target", "5", "--update",
               "--log", str(tmp_path / "never.csv")])
    assert rc == 2 and "--update needs --learn" in capsys.readouterr().err
    assert not (tmp_path / "never.csv").exists()
