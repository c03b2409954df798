"""The cause registry, the sensor object and the one direction-of-approach rule."""

from __future__ import annotations

from dataclasses import fields, replace

import numpy as np
import pytest
import yaml
from conftest import CONFIGS

from microctl.backends.simulated import SimulatedStage
from microctl.errors import ConfigError
from microctl.models.afm import AnalyticForwardModel
from microctl.models.extended import ExtendedForwardModel
from microctl.stage.causes import KINDS, REGISTRY, Backlash, Cause, Effects, stage_parts
from microctl.stage.config import parse_stage_config
from microctl.stage.physics import (
    STILL_TOL_UM,
    approach_direction,
    directions_from_steps,
)
from microctl.stage.sensor import Sensor


def _doc():
    return yaml.safe_load((CONFIGS / "stage" / "table1.yaml").read_text())


def _one_of_each(rng=np.random.default_rng(0)):
    return [cls.draw(rng, 2 if cls.per_actuator else None, compression_um=5.0) for cls in REGISTRY.values()]


# ---- registry ------------------------------------------------------------------------------


def test_registry_is_the_spec_vocabulary():
    """The registry holds exactly the causes of shared/spec/diagnosis.md, with its parameter names,
    plus the documented extension ``hysteresis`` (docs/diagnosis.md)."""
    spec = {
        "actuator_gain": ("actuator", "gain"), "contact_offset": ("actuator", "dx_mm", "dy_mm"),
        "tool_offset": ("dx_mm", "dy_mm"), "sensor_scale": ("scale",), "sensor_nonlinearity": ("quad_per_um",),
        "contact_loss": ("actuator", "gap_um"), "backlash": ("actuator", "lag_um"), "drift": ("rate_um_per_s",),
        "actuator_friction": ("actuator", "std_per_um"),
    }
    spec["hysteresis"] = ("actuator", "half_width_um", "range_um")  # the extension
    assert {n: tuple(f.name for f in fields(c)) for n, c in REGISTRY.items()} == spec
    assert all(c.kind in KINDS for c in REGISTRY.values())
    assert [n for n, c in REGISTRY.items() if c.kind == "noise"] == ["actuator_friction"]
    assert [n for n, c in REGISTRY.items() if c.kind == "dynamic"] == ["contact_loss", "backlash", "hysteresis", "drift"]
    # Effects has one field per registered cause
    assert [f.name for f in fields(Effects)] == list(REGISTRY)


def test_every_cause_round_trips_through_the_config():
    """Effects -> YAML -> parser -> Effects, for one entry of every cause (parser iterates the registry)."""
    eff = Effects.of(_one_of_each())
    doc = _doc()
    doc["backend"]["simulated"]["effects"] = eff.to_dict()
    cfg = parse_stage_config(doc)
    assert cfg.backend.simulated.effects == eff
    assert parse_stage_config(yaml.safe_load(cfg.dump_yaml())).backend.simulated.effects == eff
    assert [c.name for c in eff.items()] == list(REGISTRY)


def test_corrections_accept_noise_causes_and_refuse_bad_values():
    """A diagnosed stick-slip is a correction (extended.yaml): it tells the residual model which
    actuators scatter; its values are checked like any cause's."""
    doc = _doc()
    doc["stage"]["corrections"] = {"actuator_friction": [{"actuator": 1, "std_per_um": 0.1}]}
    cfg = parse_stage_config(doc, "s.yaml")
    assert [(c.actuator, c.std_per_um) for c in cfg.stage.corrections.actuator_friction] == [(1, 0.1)]
    doc["stage"]["corrections"] = {"actuator_friction": [{"actuator": 1, "std_per_um": -0.1}]}
    with pytest.raises(ConfigError, match=r"stage\.corrections\.actuator_friction\[0\]\.std_per_um"):
        parse_stage_config(doc, "s.yaml")
    for cause, entry, msg in [
        ("actuator_gain", [{"actuator": 1, "gain": 0.0}], r"actuator_gain\[0\]\.gain"),
        ("contact_loss", [{"actuator": 5, "gap_um": 1.0}], r"contact_loss\[0\]\.actuator"),
        ("backlash", [{"actuator": 1, "lag_um": -0.1}], r"backlash\[0\]\.lag_um"),
        ("hysteresis", [{"actuator": 2, "half_width_um": 0.2, "range_um": 0.0}], r"hysteresis\[0\]\.range_um"),
        ("drift", {"rate_um_per_s": 0.1, "extra": 1}, r"drift"),
        ("nonsense", {}, r"nonsense"),
    ]:
        doc = _doc()
        doc["backend"]["simulated"]["effects"] = {cause: entry}
        with pytest.raises(ConfigError, match=msg):
            parse_stage_config(doc, "s.yaml")


def test_each_cause_changes_the_stage_parts_it_names(table1):
    """apply() against hand answers: the CAD numbers with exactly one thing changed."""
    stage = table1.stage
    healthy = stage_parts(stage)
    for cause in _one_of_each(np.random.default_rng(3)):
        p = stage_parts(stage, Effects.of([cause]))
        changed = {k for k in ("contacts_mm", "tool_mm", "gain", "gap_um", "lag_um", "friction_std_per_um",
                               "hysteresis_half_um", "hysteresis_range_um")
                   if not np.array_equal(getattr(p, k), getattr(healthy, k))}
        if p.sensor != healthy.sensor:
            changed.add("sensor")
        want = {"actuator_gain": "gain", "contact_offset": "contacts_mm", "tool_offset": "tool_mm",
                "sensor_scale": "sensor", "sensor_nonlinearity": "sensor", "contact_loss": "gap_um",
                "backlash": "lag_um", "drift": "sensor", "actuator_friction": "friction_std_per_um",
                "hysteresis": ("hysteresis_half_um", "hysteresis_range_um")}[cause.name]
        assert changed == ({want} if isinstance(want, str) else set(want)), cause
    p = stage_parts(stage, Effects.of(_one_of_each(np.random.default_rng(3))), kinds=("static",))
    assert not p.gap_um.any() and not p.lag_um.any() and p.sensor.drift_um_per_s == 0.0
    assert not p.hysteresis_half_um.any()


def test_effects_with_replaces_the_same_cause_on_the_same_actuator():
    from microctl.stage.causes import ActuatorGain

    base = Effects(actuator_gain=(ActuatorGain(1, 1.1), ActuatorGain(3, 0.9)))
    out = base.with_(ActuatorGain(3, 0.95), ActuatorGain(2, 1.0))
    assert out.actuator_gain == (ActuatorGain(1, 1.1), ActuatorGain(2, 1.0), ActuatorGain(3, 0.95))
    assert ActuatorGain.make(2, [1.2]) == ActuatorGain(2, 1.2) and ActuatorGain(2, 1.2).key == "actuator_gain[2]"


def test_register_checks_the_declaration():
    """A cause class whose dataclass fields do not match its params is refused."""
    from microctl.stage.causes import Param, register

    with pytest.raises(TypeError, match="fields"):
        @register
        class Bad(Cause):  # no dataclass fields matching params
            name = "bad"
            params = (Param("x", "1", 0.0, None, -1, 1),)
    assert "bad" not in REGISTRY


# ---- sensor ---------------------------------------------------------------------------------


@pytest.mark.parametrize("scale,quad", [(1.0, 0.0), (0.97, 0.0), (1.03, 2e-3), (0.98, -3e-3)])
def test_sensor_forward_derivative_inverse(scale, quad):
    s = Sensor(scale, quad, drift_um_per_s=0.01)
    d = np.linspace(-40.0, 40.0, 81)
    # forward against the polynomial written out; derivative against a central difference
    assert np.allclose(s.forward(d), scale * d + quad * d**2)
    assert np.allclose(s.forward(d, time_s=3.0), scale * d + quad * d**2 + 0.03)
    h = 1e-4
    assert np.allclose(s.derivative(d), (s.forward(d + h) - s.forward(d - h)) / (2 * h), atol=1e-8)
    # inverse: the root on the healthy branch (here every d is on it: |d| < |vertex|)
    assert np.allclose(s.inverse(s.forward(d)), d, atol=1e-9)
    assert np.allclose(s.inverse(s.forward(d, 3.0), time_s=3.0), d, atol=1e-9)
    assert isinstance(s.inverse(1.0), float)


def test_sensor_inverse_beyond_the_turning_point_returns_it():
    s = Sensor(1.0, 0.01)  # turns at d = -50, reading -25
    assert s.vertex_um() == pytest.approx(-50.0)
    assert s.inverse(-30.0) == pytest.approx(-50.0)
    assert s.reading_range(-60.0, 10.0) == pytest.approx((-25.0, 11.0))


def test_sensor_is_used_by_afm_and_physics(table1):
    """The AFM and the contact physics read the gauge through the same Sensor of the corrections."""
    from microctl.stage.causes import SensorNonlinearity, SensorScale

    eff = Effects(sensor_scale=SensorScale(1.02), sensor_nonlinearity=SensorNonlinearity(1e-3))
    afm = AnalyticForwardModel(replace(table1.stage, corrections=eff))
    ext = ExtendedForwardModel(table1.stage, eff)
    assert afm.sensor == ext.model.sensor == Sensor(1.02, 1e-3)
    assert (afm.scale, afm.quad) == (1.02, 1e-3)


# ---- direction of approach -----------------------------------------------------------------


def test_direction_rule_keeps_the_last_direction_within_the_tolerance():
    last = np.array([1.0, -1.0, -1.0, 1.0])
    dq = np.array([0.0, STILL_TOL_UM / 2, -0.2, 2 * STILL_TOL_UM])
    assert approach_direction(dq, last).tolist() == [1.0, -1.0, -1.0, 1.0]
    assert approach_direction(-dq, -last).tolist() == [-1.0, 1.0, 1.0, -1.0]
    run = directions_from_steps(np.array([[1.0], [0.0], [-1e-12], [-2.0], [0.0], [1e-12]]))
    assert run[:, 0].tolist() == [1, 1, 1, -1, -1, -1]


def test_held_actuator_simulator_oracle_and_extended_model_agree(table1):
    """Issue 11: backlash 0.5 µm on actuator 1 and exactly Δq1 = 0 after a downward move —
    the simulated move, its oracle and the extended model give the same reading."""
    eff = Effects(backlash=(Backlash(1, 0.5),))
    sim_cfg = replace(table1, backend=replace(table1.backend, simulated=replace(
        table1.backend.simulated, effects=eff, gauge_noise_std_um=0.0, driver_accuracy_um=0.0)))
    sim = SimulatedStage(sim_cfg)
    afm = AnalyticForwardModel(table1.stage)
    ext = ExtendedForwardModel(table1.stage, eff)
    u1 = np.linalg.lstsq(afm.K, np.array([20.0, 14.0, 12.0, 18.0]), rcond=None)[0]
    u2 = np.linalg.lstsq(afm.K, np.array([10.0, 12.0, 14.0, 12.0]), rcond=None)[0]  # q1 down
    sim.move(u1)
    sim.move(u2)
    assert sim.direction[0] == -1.0
    # next: q1 held, the others move (q1 + q3 = q2 + q4: a pose exists)
    q3 = np.array([afm.K[0] @ u2, 13.0, 17.0, 14.0])
    u3 = np.linalg.lstsq(afm.K, q3, rcond=None)[0]
    s = sim.state.copy()
    assert abs(afm.K[0] @ u3 - s[1]) < STILL_TOL_UM
    oracle = sim.true_mean(s, u3)
    model = ext.predict(s, u3, last_direction=sim.direction, time_s=sim.time_s + 1.0)[0]
    moved = sim.move(u3).t_um
    assert oracle == pytest.approx(moved, abs=1e-9)
    assert model == pytest.approx(moved, abs=1e-9)
    # and the held actuator sits on its "down" side: 0.5 µm above where "up" would put it
    up = ext.predict(s, u3, last_direction=np.array([1.0, -1.0, 1.0, 1.0]), time_s=sim.time_s)[0]
    c1 = float(afm.w @ np.linalg.pinv(afm.K)[:, 0])  # reading per µm of ball 1 (rigid limit)
    assert model - up == pytest.approx(c1 * 1.0, rel=0.02)  # −lag·(−1) − (−lag·(+1)) = +1 µm on q1
