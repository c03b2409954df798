"""YAML reading and field bounds of the stage config (issue 12): every bad input one clear line."""

from __future__ import annotations

import copy
import re
from pathlib import Path

import pytest
import yaml

from microctl.cli import main
from microctl.errors import ConfigError
from microctl.stage.config import load_stage_config, load_yaml, parse_stage_config

SERIAL = {
    "controllers": [{"name": "driver1", "url": "socket://127.0.0.1:1"}],
    "axes": {f"q{i}": {"controller": "driver1", "axis": str(i)} for i in range(1, 5)},
    "gauge": {"url": "socket://127.0.0.1:2"},
}


@pytest.fixture
def doc(table1_path):
    return yaml.safe_load(table1_path.read_text())


def _serial_doc(doc, **gauge):
    d = copy.deepcopy(doc)
    ser = copy.deepcopy(SERIAL)
    ser["gauge"].update(gauge)
    d["backend"] = {"kind": "serial", "serial": ser}
    return d


def _bad(d, match):
    with pytest.raises(ConfigError, match=match):
        parse_stage_config(d, source="bad.yaml")


# ---- reading the file ------------------------------------------------------------------


def test_non_utf8_yaml_names_file_line_column(tmp_path, table1_path):
    p = tmp_path / "latin1.yaml"
    p.write_bytes(table1_path.read_bytes().replace(b"name: table1", b"name: caf\xe9"))
    with pytest.raises(ConfigError, match=r"latin1\.yaml: not UTF-8 text: byte 0xe9 at line 5, column 12"):
        load_stage_config(p)


def test_utf8_bom_is_read(tmp_path, table1_path, table1):
    p = tmp_path / "bom.yaml"
    p.write_bytes(b"\xef\xbb\xbf" + table1_path.read_bytes())
    assert load_stage_config(p).stage == table1.stage


def test_duplicate_key_refused_with_both_lines(tmp_path):
    p = tmp_path / "dup.yaml"
    p.write_text("stage:\n  tool: {point_mm: [0, 0, 0]}\n  name: a\n  tool: {point_mm: [1, 0, 0]}\n")
    with pytest.raises(ConfigError, match=r"dup\.yaml: invalid YAML at line 4, column 3: duplicate key 'tool' "
                                          r"\(first at line 2\)"):
        load_yaml(p)


def test_duplicate_key_in_flow_mapping(tmp_path):
    p = tmp_path / "dup.yaml"
    p.write_text("a: {x: 1, x: 2}\n")
    with pytest.raises(ConfigError, match=r"duplicate key 'x'"):
        load_yaml(p)


def test_merge_keys_still_allowed(tmp_path):
    p = tmp_path / "merge.yaml"
    p.write_text("base: &b {x: 1, y: 2}\nother:\n  <<: *b\n  x: 3\n")
    assert load_yaml(p)["other"] == {"x": 3, "y": 2}


def test_float_without_dot_is_a_number(tmp_path):
    p = tmp_path / "f.yaml"
    p.write_text("a: [1e-3, 1E5, -2.5e+2, 1e, e5, '1e3']\n")
    assert load_yaml(p)["a"] == [1e-3, 1e5, -250.0, "1e", "e5", "1e3"]


@pytest.mark.slow
def test_deep_nesting_is_one_line(tmp_path):
    p = tmp_path / "deep.yaml"
    p.write_text("[" * 20000 + "]" * 20000 + "\n")
    with pytest.raises(ConfigError, match=r"deep\.yaml: invalid YAML"):
        load_yaml(p)


def test_directory_as_config(tmp_path):
    with pytest.raises(ConfigError, match="cannot read: Is a directory"):
        load_yaml(tmp_path)


def test_cli_non_utf8_stage_exit_2(tmp_path, capsys):
    p = tmp_path / "s.yaml"
    p.write_bytes(b"stage:\n  name: \xff\xfe\n")
    assert main(["stage", "show", "--config", str(p)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "not UTF-8" in err and "Traceback" not in err


# ---- numeric bounds --------------------------------------------------------------------


@pytest.mark.parametrize("value, match", [
    ([0, 1e301], r"stage\.actuators\[1\]\.limit_um\[1\]: 1e\+301 is too large; the magnitude must be at most 10000"),
    ([0, 2e4], r"limit_um\[1\]: 20000.0 is too large"),
    ([0, 10**400], r"limit_um\[1\]: 1000+ is too large"),
])
def test_limit_um_bounded(doc, value, match):
    d = copy.deepcopy(doc)
    d["stage"]["actuators"][1]["limit_um"] = value
    _bad(d, match)


def test_generic_magnitude_bound(doc):
    d = copy.deepcopy(doc)
    d["stage"]["tool"]["point_mm"] = [1e12, 0, 0]
    _bad(d, r"stage\.tool\.point_mm\[0\]: 1000000000000.0 is too large; the magnitude must be at most 1e\+09")


@pytest.mark.parametrize("field, value, match", [
    ("timeout_s", 1e5, r"gauge\.timeout_s: must be <= 3600, got 100000.0"),
    ("baudrate", 10**12, r"gauge\.baudrate: must be an integer in \[1, 100000000\]"),
    ("query", "MEAS\u00b5?", r"gauge\.query: 'MEAS\u00b5\?': character 5 \('\u00b5'\) is a non-ASCII character; "
                             r"the gauge query is sent to the device as ASCII"),
    ("query", "ME\nAS?", r"gauge\.query: .*character 3 \('\\n'\) is a control character"),
    ("eol", "\u2028", r"gauge\.eol: .*non-ASCII"),
    ("eol", ";", r"gauge\.eol: ';' must end with a line feed or carriage return"),
    ("tare_samples", 0, r"gauge\.tare_samples: must be an integer in \[1, 10000\]"),
])
def test_serial_gauge_fields(doc, field, value, match):
    _bad(_serial_doc(doc, **{field: value}), match)


def test_serial_axis_must_be_ascii(doc):
    d = _serial_doc(doc)
    d["backend"]["serial"]["axes"]["q2"]["axis"] = "\u00c4"
    _bad(d, r"backend\.serial\.axes\.q2\.axis: 'Ä': character 1 .* non-ASCII")


def test_serial_timeouts_bounded(doc):
    d = _serial_doc(doc)
    d["backend"]["serial"]["on_target_timeout_s"] = 1e5
    _bad(d, r"backend\.serial\.on_target_timeout_s: must be <= 3600")
    d = _serial_doc(doc)
    d["backend"]["serial"]["poll_interval_s"] = 10.0
    _bad(d, r"backend\.serial\.poll_interval_s: must be <= 5")


def test_zero_at_start_needs_zero_in_range(doc):
    d = _serial_doc(doc, zero_at_start=True)
    d["stage"]["actuators"][2]["range_um"] = [1, 32]
    _bad(d, r"gauge\.zero_at_start: tares the gauge at the zero state q = 0, but actuator q3 .*\[1.0, 32.0\]")


def test_good_serial_config_round_trips(doc):
    cfg = parse_stage_config(_serial_doc(doc, query="POS", eol="\r", tare_samples=5), source="ok.yaml")
    g = cfg.backend.serial.gauge
    assert (g.query, g.eol, g.tare_samples) == ("POS", "\r", 5)
    again = parse_stage_config(yaml.safe_load(cfg.dump_yaml()), source="x")
    assert again.backend == cfg.backend


@pytest.mark.parametrize("axis, match", [
    ([1], r"axes\.q2\.axis: expected an axis id such as '1' or 'A', got \[1\]"),
    ("A=1", r"axes\.q2\.axis: 'A=1' is not a valid axis id \('=' separates axis and value in replies\)"),
    ("\r\n", r"axes\.q2\.axis: '\\r\\n' is not a valid axis id \(no spaces\)"),
])
def test_serial_axis_ids(doc, axis, match):
    d = _serial_doc(doc)
    d["backend"]["serial"]["axes"]["q2"]["axis"] = axis
    _bad(d, match)


def test_cli_error_with_a_line_break_in_a_value_is_one_line(doc, tmp_path, capsys):
    d = _serial_doc(doc)
    d["backend"]["serial"]["controllers"][0]["name"] = "drv\n1"
    p = tmp_path / "s.yaml"
    p.write_text(yaml.safe_dump(d))
    assert main(["stage", "show", "--config", str(p)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "drv\\n1" in err, err


def test_libyaml_loader_reads_what_the_python_loader_reads(tmp_path):
    """The strict loader on libyaml's parser (start-up speed) against the pure-Python strict
    loader: the same documents for every shipped YAML file, the same refusals with line and
    column for broken ones."""
    import yaml

    from microctl.stage import config as cfg

    if cfg._LOADER is cfg._StrictLoader:
        pytest.skip("PyYAML without libyaml: only the Python loader is used")
    root = Path(__file__).resolve().parents[2]
    files = sorted(root.glob("configs/**/*.yaml")) + sorted(root.glob("microctl/configs/**/*.yaml"))
    assert len(files) >= 5
    for f in files:
        text = f.read_text(encoding="utf-8")
        assert yaml.load(text, Loader=cfg._LOADER) == yaml.load(text, Loader=cfg._StrictLoader), f
    for text, where in (("a: {x: 1, x: 2}\n", "line 1, column 11"), ("stage:\n  a: 1\n  a: 2\n", "line 3, column 3"),
                        ("a: [1, 2\n", "line 2, column 1")):
        p = tmp_path / "bad.yaml"
        p.write_text(text)
        with pytest.raises(ConfigError, match=re.escape(where)):
            load_yaml(p)
        with pytest.raises(yaml.YAMLError) as py_err:
            yaml.load(text, Loader=cfg._StrictLoader)
        mark = py_err.value.problem_mark
        assert f"line {mark.line + 1}, column {mark.column + 1}" == where
