"""The AFM against independent answers: hand-derived Table I kinematics, a direct
rigid-body computation over random geometries, and CasADi vs NumPy."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from microctl.models.afm import AnalyticForwardModel
from microctl.stage.causes import ActuatorGain, Effects, SensorScale, ToolOffset
from microctl.stage.config import parse_stage_config


def test_table1_by_hand(table1):
    """Rigid-body velocity of each contact point and of t0 for p = (z, rx, ry).

    A point c on the platform moves by v + ω × c with v = (0, 0, z), ω = (rx, ry, 0), whose
    z component is z + rx·c_y − ry·c_x (mrad × mm = µm). Balls push along +z with +z normals,
    so q_i equals that z motion at c_i. The gauge reads the z motion of t0.
    """
    afm = AnalyticForwardModel(table1.stage)
    K_hand = np.array(
        [
            [1.0, 0.0, -15.0],  # c1 = (15, 0): z − 15 ry
            [1.0, -15.0, 0.0],  # c2 = (0, −15): z − 15 rx
            [1.0, 0.0, 15.0],  # c3 = (−15, 0): z + 15 ry
            [1.0, 15.0, 0.0],  # c4 = (0, 15): z + 15 rx
        ]
    )
    t0 = (50 * math.cos(math.radians(145)), 50 * math.sin(math.radians(145)))
    w_hand = np.array([1.0, t0[1], -t0[0]])
    np.testing.assert_allclose(afm.K, K_hand, atol=1e-12)
    np.testing.assert_allclose(afm.w, w_hand, atol=1e-9)
    # f_a(s, u) = [t; q] (eq. 14) at a concrete pose
    u = np.array([10.0, 0.2, -0.3])
    out = afm.predict(None, u)
    assert out[0] == pytest.approx(10.0 + 0.2 * t0[1] - (-0.3) * t0[0], abs=1e-9)
    np.testing.assert_allclose(out[1:], [10 + 4.5, 10 - 3.0, 10 - 4.5, 10 + 3.0], atol=1e-12)


def test_table1_workspace_and_range(table1):
    """The range of t: q1+q3 = q2+q4 = 2z, rx = (q4−q2)/30, ry = (q3−q1)/30; the extreme is at
    q3 = q4 = 32, q1 = q2 = 0 (z = 16, rx = ry = 32/30): t = 16 + (w_rx + w_ry)·32/30."""
    afm = AnalyticForwardModel(table1.stage)
    lo, hi = afm.t_range()
    expected = 16 + (afm.w[1] + afm.w[2]) * 32 / 30
    assert hi == pytest.approx(expected, rel=1e-9)
    assert lo == pytest.approx(32 - expected, rel=1e-9)
    np.testing.assert_allclose(afm.workspace.u_lo, [0, -32 / 30, -32 / 30], atol=1e-9)
    np.testing.assert_allclose(afm.workspace.u_hi, [32, 32 / 30, 32 / 30], atol=1e-9)
    rng = np.random.default_rng(0)
    u = afm.workspace.sample(4000, rng)
    q = afm.q_of(u)
    assert np.all(q >= -1e-9) and np.all(q <= 32 + 1e-9)
    t = afm.t_of(u)
    assert lo - 1e-9 <= t.min() and t.max() <= hi + 1e-9
    # uniform over the polytope: the z-marginal of a uniform sample is symmetric about 16
    assert abs(np.mean(u[:, 0]) - 16.0) < 0.5  # std of the mean ≈ 7/sqrt(4000) ≈ 0.11


def _random_stage(draw_values):
    """A stage dict from hypothesis-drawn values (tilted normals and directions)."""
    n_act, contacts, tilts, dirs, tool = draw_values
    acts = []
    for i in range(n_act):
        n = np.array([tilts[i][0], tilts[i][1], 1.0])
        n /= np.linalg.norm(n)
        d = np.array([dirs[i][0], dirs[i][1], 1.0])
        d /= np.linalg.norm(d)
        acts.append({"name": f"q{i + 1}", "contact_mm": list(contacts[i]), "normal": n.tolist(), "direction": d.tolist()})
    return {"stage": {"dof": ["z", "rx", "ry"], "tool": {"point_mm": list(tool)}, "actuators": acts}}


_coord = st.floats(-30, 30, allow_nan=False)
_tilt = st.floats(-0.3, 0.3, allow_nan=False)


@st.composite
def _geometries(draw):
    n_act = draw(st.integers(3, 6))
    # contacts spread on a ring with jitter so the pose is determined
    angles = [2 * math.pi * k / n_act + draw(st.floats(-0.3, 0.3)) for k in range(n_act)]
    radius = draw(st.floats(8, 25))
    contacts = [(radius * math.cos(a), radius * math.sin(a), draw(st.floats(0, 8))) for a in angles]
    tilts = [(draw(_tilt), draw(_tilt)) for _ in range(n_act)]
    dirs = [(draw(_tilt), draw(_tilt)) for _ in range(n_act)]
    tool = (draw(_coord), draw(_coord), draw(st.floats(0, 20)))
    return n_act, contacts, tilts, dirs, tool


@pytest.mark.slow
@settings(max_examples=60, deadline=None)
@given(_geometries(), st.lists(st.floats(-5, 5), min_size=3, max_size=3))
def test_general_construction_equals_rigid_body(values, p):
    """q_i from the paper's matrices equals n_i·(v + ω × c_i) / (n_i·d_i), computed directly;
    t equals s·(v + ω × t0); CasADi equals NumPy to 1e-12."""
    cfg = parse_stage_config(_random_stage(values))
    afm = AnalyticForwardModel(cfg.stage)
    p = np.asarray(p)
    v = np.array([0.0, 0.0, p[0]])
    omega = np.array([p[1], p[2], 0.0])
    for i, a in enumerate(cfg.stage.actuators):
        n, d, c = map(np.asarray, (a.normal, a.direction, a.contact_mm))
        q_direct = n @ (v + np.cross(omega, c)) / (n @ d)
        assert afm.q_of(p)[i] == pytest.approx(q_direct, abs=1e-9 * (1 + abs(q_direct)))
    t0 = np.asarray(cfg.stage.tool.point_mm)
    t_direct = np.array(cfg.stage.tool.direction) @ (v + np.cross(omega, t0))
    assert afm.t_of(p) == pytest.approx(t_direct, abs=1e-9 * (1 + abs(t_direct)))
    t_ca, q_ca = afm.f_a(np.zeros(afm.n_s), p)
    np.testing.assert_allclose(float(t_ca), afm.t_of(p), rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(np.asarray(q_ca).ravel(), afm.q_of(p), rtol=1e-12, atol=1e-12)


def test_casadi_functions_are_named(table1):
    afm = AnalyticForwardModel(table1.stage)
    assert afm.f_a.name_in() == ["s", "u"]
    assert afm.f_a.name_out() == ["t", "q"]
    out = afm.f_a(s=np.zeros(5), u=[1.0, 0.0, 0.0])
    assert float(out["t"]) == pytest.approx(1.0)


def test_static_corrections_share_inconsistency(table1):
    """A gain on one actuator makes the four ball heights inconsistent; equal elastic contacts
    share it: the pose is the least-squares fit of K p to the ball heights G K u."""
    corr = Effects(actuator_gain=(ActuatorGain(actuator=3, gain=0.9),), sensor_scale=SensorScale(1.02))
    from dataclasses import replace

    afm = AnalyticForwardModel(replace(table1.stage, corrections=corr))
    u = np.array([12.0, 0.3, 0.4])
    G = np.diag([1, 1, 0.9, 1])
    p_ls, *_ = np.linalg.lstsq(afm.K, G @ afm.K @ u, rcond=None)
    assert afm.t_of(u) == pytest.approx(1.02 * afm.w @ p_ls, rel=1e-12)
    # the command is unchanged: the drivers still get the CAD inverse kinematics
    np.testing.assert_allclose(afm.q_of(u), afm.without_corrections().q_of(u))


def test_tool_offset_correction(table1):
    """Moving t0 by (dx, dy) adds rx·dy − ry·dx to the z motion of the tool point."""
    from dataclasses import replace

    corr = Effects(tool_offset=ToolOffset(dx_mm=1.5, dy_mm=-2.0))
    afm = AnalyticForwardModel(replace(table1.stage, corrections=corr))
    base = AnalyticForwardModel(table1.stage)
    u = np.array([5.0, 0.5, -0.2])
    assert afm.t_of(u) - base.t_of(u) == pytest.approx(0.5 * -2.0 - (-0.2) * 1.5, abs=1e-12)


def test_dynamic_corrections_are_named_not_dropped(table1):
    """Backlash/contact loss/drift corrections are outside the AFM graph: the model says so."""
    from dataclasses import replace

    from microctl.stage.causes import Backlash, Drift

    assert AnalyticForwardModel(table1.stage).dynamic_corrections_note() is None
    corr = Effects(backlash=(Backlash(actuator=2, lag_um=0.2),), drift=Drift(rate_um_per_s=1e-3))
    afm = AnalyticForwardModel(replace(table1.stage, corrections=corr))
    assert afm.dynamic_corrections == ("backlash", "drift")
    assert "backlash, drift, which the AFM graph does not model" in afm.dynamic_corrections_note()
