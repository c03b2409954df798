"""Every ConfigError path of the stage YAML: the message names the file and the field."""

from __future__ import annotations

import copy

import pytest
import yaml

from microctl.cli import main
from microctl.errors import ConfigError
from microctl.stage.config import load_stage_config, parse_stage_config


@pytest.fixture
def doc(table1_path):
    return yaml.safe_load(table1_path.read_text())


def _bad(doc, mutate, match):
    d = copy.deepcopy(doc)
    mutate(d)
    with pytest.raises(ConfigError, match=match):
        parse_stage_config(d, source="bad.yaml")


def test_table1_loads(table1):
    assert table1.stage.dof == ("z", "rx", "ry")
    assert table1.stage.actuator_names == ("q1", "q2", "q3", "q4")
    assert table1.stage.tool.name == "t"
    assert table1.backend.kind == "simulated"


def test_roundtrip_yaml(table1):
    again = parse_stage_config(yaml.safe_load(table1.dump_yaml()), source="x")
    assert again.stage == table1.stage and again.backend == table1.backend


def test_unknown_key_top(doc):
    _bad(doc, lambda d: d.update(extra=1), r"bad\.yaml: <top>\.extra: unknown key 'extra'")


def test_unknown_key_actuator(doc):
    _bad(doc, lambda d: d["stage"]["actuators"][2].update(colour="red"), r"stage\.actuators\[2\]\.colour: unknown key")


def test_wrong_length(doc):
    _bad(doc, lambda d: d["stage"]["actuators"][1].update(contact_mm=[1, 2]), r"stage\.actuators\[1\]\.contact_mm: expected a list of 3 numbers, got 2 values")


def test_non_number(doc):
    _bad(doc, lambda d: d["stage"]["tool"].update(point_mm=[1, "a", 2]), r"stage\.tool\.point_mm\[1\]: expected a number")


def test_zero_normal(doc):
    _bad(doc, lambda d: d["stage"]["actuators"][2].update(normal=[0, 0, 0]), r"stage\.actuators\[2\]\.normal: is the zero vector")


def test_non_unit_normal(doc):
    _bad(doc, lambda d: d["stage"]["actuators"][2].update(normal=[0, 0, 2]), r"stage\.actuators\[2\]\.normal: has length 2, must be a unit vector")


def test_non_unit_tool_direction(doc):
    _bad(doc, lambda d: d["stage"]["tool"].update(direction=[0.5, 0, 0.5]), r"stage\.tool\.direction: has length")


def test_fewer_actuators_than_dof(doc):
    _bad(doc, lambda d: d["stage"].update(actuators=d["stage"]["actuators"][:2]), r"stage\.actuators: 2 actuators cannot determine 3 DoF")


def test_singular_contact_map(doc):
    """A ball pushed perpendicular to its contact normal transmits nothing: H R^T J singular."""
    _bad(doc, lambda d: d["stage"]["actuators"][3].update(direction=[1, 0, 0]), r"stage\.actuators\[3\]\.direction: is perpendicular to the contact normal")


def test_ill_conditioned_contact_map(doc):
    """n·d = 0.05: the ball needs 20× its stroke to move the platform."""
    import math

    e = 0.05
    _bad(doc, lambda d: d["stage"]["actuators"][0].update(direction=[math.sqrt(1 - e * e), 0, e]), r"stage\.actuators\[0\]\.direction: makes H R\^T J \(eq\. 10\) ill-conditioned: n·d = 0\.05")


def test_collinear_contacts_do_not_determine_pose(doc):
    """All contacts on the x axis: rotation about x moves no contact, so K is rank-deficient."""

    def mutate(d):
        for k, a in enumerate(d["stage"]["actuators"]):
            a["contact_mm"] = [-15 + 10 * k, 0, 5]

    _bad(doc, mutate, r"stage\.actuators: the contact points do not determine the DoF")


def test_range_lo_ge_hi(doc):
    _bad(doc, lambda d: d["stage"]["actuators"][1].update(range_um=[10, 10]), r"stage\.actuators\[1\]\.range_um: lower bound 10 must be below upper bound 10")


def test_range_outside_limit(doc):
    _bad(doc, lambda d: d["stage"]["actuators"][1].update(range_um=[0, 40]), r"stage\.actuators\[1\]\.range_um: \[0\.0, 40\.0\] must lie inside the hardware limit")


def test_bad_dof(doc):
    _bad(doc, lambda d: d["stage"].update(dof=["z", "tilt"]), r"stage\.dof\[1\]: 'tilt' is not a twist component")


def test_dof_order(doc):
    _bad(doc, lambda d: d["stage"].update(dof=["rx", "z", "ry"]), r"stage\.dof: list the DoF in twist order")


def test_duplicate_actuator_name(doc):
    _bad(doc, lambda d: d["stage"]["actuators"][1].update(name="q1"), r"stage\.actuators\[1\]\.name: actuator name 'q1' is used twice")


def test_unknown_backend(doc):
    _bad(doc, lambda d: d["backend"].update(kind="usb"), r"backend\.kind: 'usb' is not a backend; valid: simulated, serial")


def test_serial_required(doc):
    _bad(doc, lambda d: d["backend"].update(kind="serial"), r"backend\.serial: is required")


def test_unknown_effect(doc):
    _bad(doc, lambda d: d["backend"]["simulated"].update(effects={"warp": {}}), r"backend\.simulated\.effects\.warp: unknown key")


def test_effect_actuator_out_of_range(doc):
    _bad(
        doc,
        lambda d: d["backend"]["simulated"].update(effects={"actuator_gain": [{"actuator": 5, "gain": 0.9}]}),
        r"effects\.actuator_gain\[0\]\.actuator: must be an integer in \[1, 4\]",
    )


def test_effect_negative_gain(doc):
    _bad(
        doc,
        lambda d: d["backend"]["simulated"].update(effects={"actuator_gain": [{"actuator": 1, "gain": -1}]}),
        r"actuator_gain\[0\]\.gain: must be > 0",
    )


def test_serial_unknown_controller(doc):
    def mutate(d):
        d["backend"]["kind"] = "serial"
        d["backend"]["serial"] = {
            "controllers": [{"name": "a", "url": "socket://127.0.0.1:1"}],
            "axes": {f"q{i}": {"controller": "b" if i == 3 else "a", "axis": i} for i in range(1, 5)},
            "gauge": {"url": "socket://127.0.0.1:2"},
        }

    _bad(doc, mutate, r"backend\.serial\.axes\.q3\.controller: 'b' is not a configured controller; valid: a")


def test_invalid_yaml_file(tmp_path):
    f = tmp_path / "broken.yaml"
    f.write_text("stage: [1, 2\n")
    with pytest.raises(ConfigError, match=r"broken\.yaml: invalid YAML at line"):
        load_stage_config(f)


def test_missing_file(tmp_path):
    with pytest.raises(ConfigError, match=r"nope\.yaml: cannot read"):
        load_stage_config(tmp_path / "nope.yaml")


def test_cli_broken_yaml_one_line_exit_2(tmp_path, capsys, doc):
    d = copy.deepcopy(doc)
    d["stage"]["actuators"][2]["normal"] = [0, 0, 0]
    f = tmp_path / "bad.yaml"
    f.write_text(yaml.safe_dump(d))
    assert main(["stage", "show", "--config", str(f)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err
    assert "stage.actuators[2].normal" in err and "bad.yaml" in err
