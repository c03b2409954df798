"""Contact physics against hand-derived answers."""

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from microctl.models.afm import AnalyticForwardModel
from microctl.stage.causes import (
    ActuatorGain,
    Backlash,
    ContactLoss,
    Drift,
    Effects,
    SensorScale,
    ToolOffset,
)
from microctl.stage.config import load_stage_config
from microctl.stage.geometry import Physics
from microctl.stage.kinematics import inverse_kinematics_matrix, tool_vector
from microctl.stage.physics import (
    contact_model,
    equilibrium,
    mean_reading,
    move_directions,
)

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def stage():
    return load_stage_config(ROOT / "configs/stage/table1.yaml").stage


@pytest.fixture(scope="module")
def stiff(stage):
    return replace(stage, physics=Physics(contact_stiffness_n_per_um=1e9))


@pytest.fixture(scope="module")
def rigid(stage):
    """Stiff contacts with a preload that keeps every ball closed (2.5 µm each)."""
    return replace(stage, physics=Physics(contact_stiffness_n_per_um=1e7, preload_n=1e8))


@pytest.fixture(scope="module")
def moves(stage):
    afm = AnalyticForwardModel(stage)
    u = afm.workspace.sample(300, np.random.default_rng(0))
    return afm, u, afm.q_of(u)


def test_rest_compression_is_preload_shared(stage):
    m = contact_model(stage, Effects())
    # four equal balls carry 100 N at 20 N/µm: 1.25 µm each (flexure z compliance negligible)
    assert m.p_zero[0] == pytest.approx(-100 / (4 * 20 + 0.01), rel=1e-9)


def test_stiff_contacts_match_afm(stiff, moves):
    afm, u, q = moves
    assert np.max(np.abs(mean_reading(stiff, Effects(), q) - afm.t_of(u))) < 1e-6


def test_default_physics_matches_afm_within_noise(stage, moves):
    afm, u, q = moves
    assert np.max(np.abs(mean_reading(stage, Effects(), q) - afm.t_of(u))) < 0.05


def test_gain_is_shared_elastically_as_least_squares(rigid, moves):
    afm, u, q = moves
    e = Effects(actuator_gain=(ActuatorGain(3, 0.9),))
    # balls at G q; equal contacts share the inconsistency: least-squares pose of the heights
    G = np.diag([1, 1, 0.9, 1])
    expect = (q @ G.T) @ np.linalg.pinv(afm.K).T @ afm.w
    assert np.allclose(mean_reading(rigid, e, q), expect, atol=1e-4)
    assert np.max(np.abs(expect - afm.t_of(u))) > 0.5


def test_sensor_scale_and_tool_offset_and_drift(stiff, stage, moves):
    afm, u, q = moves
    assert np.allclose(mean_reading(stiff, Effects(sensor_scale=SensorScale(0.9)), q), 0.9 * afm.t_of(u), atol=1e-5)
    # tool offset (dx, dy): translation of the point gains ω × (dx, dy, 0) along z:
    # Δw_rx = dy, Δw_ry = -dx
    e = Effects(tool_offset=ToolOffset(2.0, -3.0))
    w = afm.w + np.array([0.0, -3.0, -2.0])
    assert np.allclose(mean_reading(stiff, e, q), u @ w, atol=1e-5)
    r = mean_reading(stiff, Effects(drift=Drift(0.01)), q, time_s=np.arange(len(q)) * 2.0)
    assert np.allclose(r - afm.t_of(u), 0.01 * np.arange(len(q)) * 2.0, atol=1e-5)


def test_backlash_direction_and_carry_over(rigid):
    stiff = rigid
    q = np.array([[10, 10, 10, 10], [5, 10, 15, 10], [5, 10, 15, 10], [8, 10, 12, 10]], dtype=float)
    d = move_directions(q)
    assert d[:, 0].tolist() == [1, -1, -1, 1]
    assert d[:, 1].tolist() == [1, 1, 1, 1]
    e = Effects(backlash=(Backlash(1, 0.5),))
    K = inverse_kinematics_matrix(stiff)
    w = tool_vector(stiff)
    r = mean_reading(stiff, e, q, direction=d)
    # zero state sits at -0.5 on q1 ("up"); moving up ends 0.5 short, moving down 0.5 long.
    # The rigid pose of the ball heights, relative to the zero state's pose.
    lag = np.where(d[:, 0] > 0, -0.5, 0.5)
    qa = q.copy()
    qa[:, 0] += lag
    q0 = np.array([-0.5, 0, 0, 0])
    expect = (qa - q0) @ np.linalg.pinv(K).T @ w
    assert np.allclose(r, expect, atol=1e-4)


def test_contact_loss_gives_a_kink(stage):
    afm = AnalyticForwardModel(stage)
    e = Effects(contact_loss=(ContactLoss(2, 8.0),))  # > preload / k_c = 5 µm
    rx = np.linspace(-1.0, 1.0, 81)
    U = np.column_stack([np.full_like(rx, 16.0), rx, np.zeros_like(rx)])
    t = mean_reading(stage, e, afm.q_of(U))
    _, active = equilibrium(stage, e, afm.q_of(U))
    slope = np.diff(t) / np.diff(rx)
    afm_slope = afm.w[1]
    # far from the kink the slope is the AFM's; in between the platform sits in a dead zone
    assert slope[:10] == pytest.approx(afm_slope, rel=0.02)
    assert slope[-10:] == pytest.approx(afm_slope, rel=0.02)
    assert np.min(slope) < 0.2 * afm_slope
    assert not active[:, 1].all()  # ball 2 carries no load over part of the sweep
    # a small gap is made up by the preload: no kink
    t_small = mean_reading(stage, Effects(contact_loss=(ContactLoss(2, 2.0),)), afm.q_of(U))
    assert np.min(np.diff(t_small) / np.diff(rx)) > 0.95 * afm_slope


def test_batch_equals_single(stage, moves):
    _, _, q = moves
    e = Effects(contact_loss=(ContactLoss(1, 7.0),), actuator_gain=(ActuatorGain(2, 1.1),))
    p, act = equilibrium(stage, e, q[:20])
    for k in range(20):
        pk, ak = equilibrium(stage, e, q[k])
        assert np.allclose(pk[0], p[k], atol=1e-9)
        assert (ak[0] == act[k]).all()


def test_degenerate_contact_on_load_diagonal_converges():
    stage = load_stage_config(ROOT / "configs/stage/table1.yaml").stage
    stiff = replace(stage, physics=Physics(contact_stiffness_n_per_um=1e9))
    p, active = equilibrium(stiff, Effects(backlash=(Backlash(1, 0.5),)), np.array([[9.5, 10, 10, 10]]))
    assert np.isfinite(p).all() and active[0, 1] and active[0, 3]
