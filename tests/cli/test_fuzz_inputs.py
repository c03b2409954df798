"""Property-based fuzzing of every input file through the command line (issue 12).

Stage YAML, experiment YAML, measurement logs and model files are mutated (structure-aware
edits: a value replaced by an awkward one, a key removed, added or repeated, a row or column
dropped or doubled; and plain byte edits). Each mutant goes through ``microctl.cli.main``
in-process. The only outcomes allowed:

- exit 0 with valid output (the JSON parses, the log reads back, the model loads), or
- exit 2 with exactly one line on stderr, ``microctl...: error: ...``;

never an exception escaping ``main`` (a traceback), never exit 1 (these are input
problems, not environment failures), never several lines of noise.

Bounded: a fixed number of examples per target, derandomized (the same cases every run),
no deadline, no example database. ``experiment`` runs with ``run_experiment`` replaced by a
stub once the file has validated: what is fuzzed is the validation of the file, not hours
of experiment that a valid mutant (``moves: 100000``) could ask for.
"""

from __future__ import annotations

import contextlib
import io
import json
import os
import tempfile
import warnings
from pathlib import Path

import numpy as np
import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from microctl.cli import main
from microctl.gp.vhgpr import FittedVHGPR
from microctl.measurement.log import read_log
from microctl.stage.config import load_stage_config

ROOT = Path(__file__).resolve().parents[2]
TABLE1 = ROOT / "configs/stage/table1.yaml"
EMULATED = ROOT / "configs/stage/emulated.yaml"
SIM = ROOT / "configs/stage/sim_paper.yaml"

#: Examples per target (stage YAML gets twice as many: it is fast). A deeper local campaign:
#: ``MICROCTL_FUZZ_EXAMPLES=500 MICROCTL_FUZZ_RANDOM=1 pytest tests/cli/test_fuzz_inputs.py``.
EXAMPLES = int(os.environ.get("MICROCTL_FUZZ_EXAMPLES", "30"))
FUZZ = settings(max_examples=EXAMPLES, deadline=None, derandomize=not os.environ.get("MICROCTL_FUZZ_RANDOM"),
                database=None, print_blob=True,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large,
                                       HealthCheck.function_scoped_fixture])

#: Values a careless or hostile file may hold where a number, a string, a list is expected.
AWKWARD = [0, -1, 1, 0.5, -0.0, 1e-300, 1e301, -1e301, 10**30, 2**64, float("nan"), float("inf"),
           "", " ", "1_0.5", "1e3", "nan", "ü", "\x00", "a" * 300, None, True, [], {}, [1, 2], [0, 1e301],
           {"x": 1}, [[1, 2, 3]], "socket://127.0.0.1:1", "q1", "\r\n", "MEAS\u00b5?"]
#: Tokens a byte-level edit inserts.
TOKENS = [b":", b"-", b"[", b"]", b"{", b"}", b"&a ", b"*a", b"\t", b"\xe9", b"\xef\xbb\xbf", b"\n", b"  ",
          b"!!python/object:os.system", b"<<: ", b"'", b'"', b"#", b",", b"\x00", b"1e400", b"_"]

# ---- running the CLI ------------------------------------------------------------------------


def _run(argv: list[str]) -> tuple[int, str, str]:
    """``main(argv)`` with stdout/stderr captured; an escaping exception fails the test.

    Python warnings are shown on stderr the way the command line shows them (pytest would
    otherwise collect them silently), so that a warning counts as a line of noise.
    """
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err), \
            warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("default")
        warnings.simplefilter("ignore", ResourceWarning)  # as Python shows them by default: not at all
        try:
            rc = main(argv)
        except SystemExit as exc:  # argparse usage errors
            rc = int(exc.code or 0)
    text = err.getvalue() + "".join(warnings.formatwarning(w.message, w.category, w.filename, w.lineno)
                                    for w in caught)
    return rc, out.getvalue(), text


def _assert_clear_error(rc: int, err: str, argv: list[str]) -> None:
    assert rc == 2, f"exit {rc} (want 0 or 2) for {argv}: {err!r}"
    lines = err.splitlines()
    assert len(lines) == 1 and err.endswith("\n"), f"not one line: {err!r}"
    assert lines[0].startswith("microctl") and ": error: " in lines[0], lines[0]
    assert "Traceback" not in err


OUTCOMES: dict[str, dict[str, int]] = {}


def _count(target: str, rc: int) -> None:
    c = OUTCOMES.setdefault(target, {"ok": 0, "error": 0})
    c["ok" if rc == 0 else "error"] += 1


def _both_outcomes(*targets: str) -> None:
    """The mutants reached both sides: some accepted (and checked), some refused."""
    for target in targets:
        c = OUTCOMES.get(target, {})
        print(f"fuzz {target}: {c}")
        assert c.get("ok", 0) > 0 and c.get("error", 0) > 0, (target, c)


# ---- mutation strategies ----------------------------------------------------------------------


def _paths(doc, prefix=()):
    """Every (path, value) in a parsed YAML document, containers included."""
    yield prefix, doc
    if isinstance(doc, dict):
        for k, v in doc.items():
            yield from _paths(v, prefix + (k,))
    elif isinstance(doc, list):
        for i, v in enumerate(doc):
            yield from _paths(v, prefix + (i,))


def _set(doc, path, value):
    node = doc
    for key in path[:-1]:
        node = node[key]
    node[path[-1]] = value


def _delete(doc, path):
    node = doc
    for key in path[:-1]:
        node = node[key]
    del node[path[-1]]


@st.composite
def yaml_mutant(draw, base_text: str) -> bytes:
    """A mutated YAML file: 1-3 structural edits, or a byte edit of the text."""
    if draw(st.integers(0, 3)) == 0:  # byte-level
        data = bytearray(base_text.encode())
        for _ in range(draw(st.integers(1, 3))):
            pos = draw(st.integers(0, len(data)))
            cut = draw(st.integers(0, 12))
            data[pos:pos + cut] = draw(st.sampled_from(TOKENS))
        return bytes(data)
    doc = yaml.safe_load(base_text)
    for _ in range(draw(st.integers(1, 2))):
        paths = [p for p, _ in _paths(doc) if p]
        if not paths:
            break
        path = draw(st.sampled_from(paths))
        op = draw(st.sampled_from(["replace", "replace", "replace", "delete", "add", "scale"]))
        try:
            if op == "replace":
                _set(doc, path, draw(st.sampled_from(AWKWARD)))
            elif op == "delete":
                _delete(doc, path)
            elif op == "add":
                parent = [p for p, v in _paths(doc) if isinstance(v, dict)]
                _set(doc, draw(st.sampled_from(parent)) + ("extra_key",), draw(st.sampled_from(AWKWARD)))
            else:
                node = dict(_paths(doc))[path]
                if isinstance(node, (int, float)) and not isinstance(node, bool):
                    _set(doc, path, node * draw(st.sampled_from([-1, 0, 1e-9, 10, 1e6, 1e12])))
        except (KeyError, IndexError, TypeError):
            pass
    text = yaml.safe_dump(doc, sort_keys=False, allow_unicode=True)
    if draw(st.integers(0, 3)) == 0 and "\n" in text:  # a key given twice: repeat one line of the dump
        lines = text.splitlines(keepends=True)
        i = draw(st.integers(0, len(lines) - 1))
        lines.insert(i, lines[i])
        text = "".join(lines)
    return text.encode()


# ---- stage YAML ---------------------------------------------------------------------------------


@pytest.mark.slow
def test_fuzz_stage_yaml():
    OUTCOMES.clear()
    _fuzz_stage_yaml()
    _both_outcomes("stage show")
    assert OUTCOMES.get("collect", {}).get("ok", 0) > 0, OUTCOMES  # some mutants ran on the simulator


@settings(FUZZ, max_examples=2 * EXAMPLES)
@given(st.data())
def _fuzz_stage_yaml(data):
    base = data.draw(st.sampled_from([TABLE1, EMULATED, SIM]), label="base")
    mutant = data.draw(yaml_mutant(base.read_text()), label="mutant")
    with tempfile.TemporaryDirectory() as tmp:
        cfg = Path(tmp) / "stage.yaml"
        cfg.write_bytes(mutant)
        argv = ["stage", "show", "--config", str(cfg), "--json"]
        rc, out, err = _run(argv)
        _count("stage show", rc)
        if rc != 0:
            _assert_clear_error(rc, err, argv)
            return
        info = json.loads(out)
        assert np.all(np.isfinite(info["t_range_um"])), info["t_range_um"]
        config = load_stage_config(cfg)
        if config.backend.kind != "simulated":
            return  # nothing listens on its ports; serial runs are tested against the emulator
        log = Path(tmp) / "log.csv"
        argv = ["collect", "--config", str(cfg), "-n", "3", "-o", str(log), "--quiet"]
        rc, out, err = _run(argv)
        _count("collect", rc)
        if rc != 0:
            _assert_clear_error(rc, err, argv)
            return
        assert len(read_log(log, config.stage)) == 3


# ---- experiment YAML ------------------------------------------------------------------------------

EXPERIMENT = {
    "stage": str(SIM),
    "controllers": ["afm", "eafm", "oracle"],
    "seeds": {"design": 0, "gp": 0},
    "training": {"moves": 20, "design": "face_episodes", "restarts": 1, "max_iter": 60},
    "controller": {"r_e": "noise_median"},
    "absolute": {"points": 3, "trials": 2},
    "incremental": {"targets_um": [7, 14], "trials": 3},
    "oracle": {"grid": 9, "line_points": 15, "zooms": 1},
    "figures": False,
}


def test_fuzz_experiment_yaml(monkeypatch):
    OUTCOMES.clear()
    _fuzz_experiment_yaml(monkeypatch)
    _both_outcomes("experiment (validation)")


@FUZZ
@given(data=st.data())
def _fuzz_experiment_yaml(monkeypatch, data):
    import microctl.experiments.runner as runner

    seen = []

    def stub(cfg, out, **kw):  # the file validated: record it instead of running for minutes
        seen.append(cfg)
        return {"timings_s": {"total": 0.0}}

    monkeypatch.setattr(runner, "run_experiment", stub)
    mutant = data.draw(yaml_mutant(yaml.safe_dump(EXPERIMENT, sort_keys=False)), label="mutant")
    with tempfile.TemporaryDirectory() as tmp:
        exp = Path(tmp) / "exp.yaml"
        exp.write_bytes(mutant)
        argv = ["experiment", str(exp), "--out", str(Path(tmp) / "out"), "--quiet"]
        rc, out, err = _run(argv)
        _count("experiment (validation)", rc)
        if rc != 0:
            _assert_clear_error(rc, err, argv)
            assert not seen
            return
        assert len(seen) == 1 and (Path(tmp) / "out").is_dir()


# ---- measurement logs --------------------------------------------------------------------------


@pytest.fixture(scope="module")
def good_log(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("fuzzlog") / "log.csv"
    rc, _, err = _run(["collect", "--config", str(TABLE1), "-n", "12", "-o", str(path), "--quiet"])
    assert rc == 0, err
    return path


CELLS = ["", " ", "nan", "inf", "-inf", "1e300", "-1e300", "1e30", "1_0.5", "١٢", "0x1f", "1,5", "abc",
         "-0", "3.", ".5", "1e-320", "9" * 400, "40", "-3", "\x00", "\"1\"", "1e", "+", "9007199254740993"]


@st.composite
def log_mutant(draw, text: str) -> bytes:
    lines = text.splitlines()
    header, rows = lines[0].split(","), [r.split(",") for r in lines[1:]]
    for _ in range(draw(st.integers(1, 3))):
        op = draw(st.sampled_from(["cell", "cell", "cell", "drop_row", "dup_row", "swap_rows", "drop_col",
                                   "rename_col", "dup_col", "blank", "bom", "bytes"]))
        if op == "cell" and rows:
            r = draw(st.integers(0, len(rows) - 1))
            c = draw(st.integers(0, len(header) - 1))
            if c < len(rows[r]):
                rows[r][c] = draw(st.sampled_from(CELLS))
        elif op == "drop_row" and rows:
            del rows[draw(st.integers(0, len(rows) - 1))]
        elif op == "dup_row" and rows:
            i = draw(st.integers(0, len(rows) - 1))
            rows.insert(i, list(rows[i]))
        elif op == "swap_rows" and len(rows) > 1:
            i = draw(st.integers(0, len(rows) - 2))
            rows[i], rows[i + 1] = rows[i + 1], rows[i]
        elif op in ("drop_col", "rename_col", "dup_col") and header:
            c = draw(st.integers(0, len(header) - 1))
            if op == "drop_col":
                del header[c]
                for row in rows:
                    if c < len(row):
                        del row[c]
            elif op == "rename_col":
                header[c] = draw(st.sampled_from(["", "t", "seq", "x", "Q1", " q1", "u_z"]))
            else:
                header.insert(c, header[c])
                for row in rows:
                    if c < len(row):
                        row.insert(c, row[c])
        elif op == "blank":
            rows.insert(draw(st.integers(0, len(rows))), [""])
    out = "\n".join([",".join(header)] + [",".join(r) for r in rows]) + "\n"
    data = out.encode("utf-8")
    if "bom" in out or draw(st.integers(0, 9)) == 0:
        data = b"\xef\xbb\xbf" + data
    if draw(st.integers(0, 5)) == 0:
        pos = draw(st.integers(0, len(data)))
        data = data[:pos] + draw(st.sampled_from(TOKENS)) + data[pos + draw(st.integers(0, 6)):]
    return data


@pytest.mark.slow
def test_fuzz_measurement_log(good_log):
    OUTCOMES.clear()
    _fuzz_measurement_log(good_log)
    _both_outcomes("train")


@FUZZ
@given(data=st.data())
def _fuzz_measurement_log(good_log, data):
    mutant = data.draw(log_mutant(good_log.read_text()), label="mutant")
    config = load_stage_config(TABLE1)
    with tempfile.TemporaryDirectory() as tmp:
        log = Path(tmp) / "log.csv"
        log.write_bytes(mutant)
        model = Path(tmp) / "m.npz"
        argv = ["train", str(log), "--config", str(TABLE1), "-o", str(model), "--restarts", "1", "--quiet"]
        rc, out, err = _run(argv)
        _count("train", rc)
        if rc != 0:
            _assert_clear_error(rc, err, argv)
            assert not model.exists()
            return
        read_log(log, config.stage)  # what train accepted reads back
        m = FittedVHGPR.load(model)
        assert np.isfinite(m.y_scale) and m.y_scale > 0


# ---- model files -----------------------------------------------------------------------------


@pytest.fixture(scope="module")
def good_model(good_log, tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("fuzzmodel") / "model.npz"
    rc, _, err = _run(["train", str(good_log), "--config", str(TABLE1), "-o", str(path), "--restarts", "1",
                       "--quiet"])
    assert rc == 0, err
    return path


FLOATS = [np.nan, np.inf, -np.inf, 0.0, -1.0, 1e300, -1e300, 1e-300, 800.0, -800.0, 1e20, 2.0]


@st.composite
def model_mutant(draw, path: Path) -> bytes:
    with np.load(path) as npz:
        arrays = {k: npz[k] for k in npz.files}
    if draw(st.integers(0, 5)) == 0:  # byte-level: truncate or flip
        data = bytearray(path.read_bytes())
        pos = draw(st.integers(0, len(data) - 1))
        if draw(st.booleans()):
            return bytes(data[:pos])
        data[pos] ^= draw(st.integers(1, 255))
        return bytes(data)
    for _ in range(draw(st.integers(1, 2))):
        name = draw(st.sampled_from(sorted(arrays)))
        op = draw(st.sampled_from(["element", "element", "scale", "shape", "drop", "dtype", "meta"]))
        a = arrays[name]
        if op == "element" and a.dtype.kind == "f" and a.size:
            a = a.copy()
            a.flat[draw(st.integers(0, a.size - 1))] = draw(st.sampled_from(FLOATS))
        elif op == "scale" and a.dtype.kind == "f":
            a = a * draw(st.sampled_from([-1.0, 0.0, 1.5, 1e10]))
        elif op == "shape":
            a = a.reshape(-1)[: max(0, a.size - 1)]
        elif op == "drop":
            del arrays[name]
            continue
        elif op == "dtype":
            try:
                a = a.astype(draw(st.sampled_from([np.int64, np.float32, np.complex128, "U4", object])))
            except (ValueError, TypeError, OverflowError):
                continue
        elif op == "meta" and "meta_json" in arrays:
            try:
                meta = json.loads(str(arrays["meta_json"]))
            except ValueError:
                continue
            if not isinstance(meta, dict):
                continue
            key = draw(st.sampled_from(["training_hash", "geometry_hash", "x_names", "y_name", "info"]))
            meta[key] = draw(st.sampled_from([None, 1, "", "abc", ["x"], {"a": 1}, "0" * 64]))
            arrays["meta_json"] = np.array(draw(st.sampled_from([json.dumps(meta), "{not json", "[]"])))
            continue
        arrays[name] = a
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    return buf.getvalue()


@pytest.mark.slow
def test_fuzz_model_file(good_model):
    OUTCOMES.clear()
    _fuzz_model_file(good_model)
    _both_outcomes("solve")


@FUZZ
@given(data=st.data())
def _fuzz_model_file(good_model, data):
    mutant = data.draw(model_mutant(good_model), label="mutant")
    with tempfile.TemporaryDirectory() as tmp:
        model = Path(tmp) / "model.npz"
        model.write_bytes(mutant)
        argv = ["solve", "--config", str(TABLE1), "--model", str(model), "--target", "5", "--json"]
        rc, out, err = _run(argv)
        _count("solve", rc)
        if rc != 0:
            _assert_clear_error(rc, err, argv)
            return
        res = json.loads(out)
        assert np.isfinite(res["predicted_um"]) and np.isfinite(res["predicted_std_um"]), res
        assert all(np.isfinite(res["q_um"]))
