"""The ``hysteresis`` cause: play operators against hand-derived cases, its backlash limit, and the
simulated stage, the extended model and its oracle carrying the loop's memory consistently."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from conftest import CONFIGS

from microctl.backends.simulated import SimulatedStage
from microctl.models.afm import AnalyticForwardModel
from microctl.models.extended import ExtendedForwardModel
from microctl.stage import hysteresis as hy
from microctl.stage.causes import Backlash, Effects, Hysteresis
from microctl.stage.config import load_stage_config
from microctl.stage.physics import actual_positions, contact_model, mean_reading


def test_play_operator_hand_cases():
    """One actuator, thresholds (1, 2) µm, from the zero state (z = -r): written out by hand."""
    r = np.array([[1.0, 2.0]])
    z = -r
    steps = [(5.0, [4.0, 3.0]),   # long move up: z = x - r
             (4.0, [4.0, 3.0]),   # 1 µm back: inside both plays, nothing moves
             (2.5, [3.5, 3.0]),   # 2.5 µm back: the 1 µm play follows (x + r), the 2 µm one not yet
             (0.0, [1.0, 2.0]),   # long move down: z = x + r
             (1.5, [1.0, 2.0])]   # 1.5 µm up: inside both
    for x, want in steps:
        z = hy.play_step(z, np.array([x]), r)
        np.testing.assert_array_equal(z[0], want)


def test_weights_give_the_major_loop_half_width_and_the_run_matches_single_steps():
    h, R = np.array([0.3, 0.0]), np.array([4.0, 4.0])
    r, w = hy.thresholds(R), hy.weights(h, R)
    np.testing.assert_allclose(r[0], [1.0, 2.0, 3.0, 4.0])
    np.testing.assert_allclose(w * r.sum(axis=1), h)
    # after a long move up the actuator is h short of its command, after a long move down h over
    q = np.array([[20.0, 20.0], [2.0, 2.0]])
    run = hy.play_run(r, q)
    np.testing.assert_allclose(hy.offset(w, run, q), [[-0.3, 0.0], [0.3, 0.0]], atol=1e-12)
    # a run fed q_prev = the previous command equals the plain run; a run equals step by step
    rng = np.random.default_rng(0)
    qs = rng.uniform(0, 20, (30, 2))
    qp = np.vstack([np.zeros((1, 2)), qs[:-1]])
    np.testing.assert_array_equal(hy.play_run(r, qs, qp), hy.play_run(r, qs))
    z = hy.zero_play(R)
    for k in range(30):
        z = hy.play_step(z, qs[k], r)
        np.testing.assert_array_equal(z, hy.play_run(r, qs)[k])


def test_small_loop_limit_is_backlash(table1):
    """R -> 0 closes every play at once: the actuator ends h short of its command in its last
    direction, the ``backlash`` cause of lag h (R = 1e-6 µm: the difference is O(R) and the
    round-off of the weights h / ΣR, 1e-10 µm here; 1e-5 µm bounds both)."""
    rng = np.random.default_rng(1)
    q = rng.uniform(0, 25, (60, 4))
    qp = np.vstack([np.zeros((1, 4)), q[:-1]])
    a = mean_reading(table1.stage, Effects(hysteresis=(Hysteresis(3, 0.25, 1e-6),)), q, q_prev=qp)
    b = mean_reading(table1.stage, Effects(backlash=(Backlash(3, 0.25),)), q, q_prev=qp)
    assert np.max(np.abs(a - b)) < 1e-5
    # a wide loop is not a backlash: short reversals land part-way round it
    c = mean_reading(table1.stage, Effects(hysteresis=(Hysteresis(3, 0.25, 8.0),)), q, q_prev=qp)
    assert np.max(np.abs(c - b)) > 0.05


def test_actual_positions_need_the_play_states(table1):
    model = contact_model(table1.stage, Effects(hysteresis=(Hysteresis(1, 0.2, 3.0),)))
    with pytest.raises(ValueError, match="play"):
        actual_positions(model, np.zeros(4))
    # the zero state approached from below: the actuator sits h under its command
    np.testing.assert_allclose(model.q_zero, [-0.2, 0.0, 0.0, 0.0])


def _noise_free_hysteresis_config():
    cfg = load_stage_config(CONFIGS / "stage" / "table1.yaml")
    sim = replace(cfg.backend.simulated, gauge_noise_std_um=0.0, driver_accuracy_um=0.0,
                  effects=Effects(hysteresis=(Hysteresis(2, 0.3, 5.0), Hysteresis(4, 0.2, 2.0)),
                                  backlash=(Backlash(1, 0.1),)))
    return replace(cfg, backend=replace(cfg.backend, simulated=sim))


def test_simulated_stage_extended_model_and_oracle_share_the_loop_memory():
    """Noise-free stage with two loops and a backlash: (1) the log of a run is predicted exactly by
    the extended model with the planted causes (play run along the log), (2) the oracle's truth of
    the next move equals what the stage then reads, from any history (round-off: 1e-9 µm)."""
    cfg = _noise_free_hysteresis_config()
    afm = AnalyticForwardModel(cfg.stage)
    rng = np.random.default_rng(2)
    U = afm.workspace.sample(40, rng)
    from microctl.diagnosis.data import data_from_arrays

    with SimulatedStage(cfg, seed=0) as st:
        rows = []
        for u in U:
            s = st.state
            mean = st.true_mean(s, u)
            m = st.move(u)
            assert m.t_um == pytest.approx(mean, abs=1e-9)
            rows.append((m.u, m.q_um, m.t_um, m.time_s))
    u, q, t, time_s = (np.array(x) for x in zip(*rows))
    data = data_from_arrays(u, q, t, time_s=time_s)
    ext = ExtendedForwardModel(cfg.stage, cfg.backend.simulated.effects)
    assert np.max(np.abs(ext.residual(data))) < 1e-9
    # without the loop's memory (backlash of the same half-widths instead) the run is not explained
    as_backlash = Effects(backlash=(Backlash(1, 0.1), Backlash(2, 0.3), Backlash(4, 0.2)))
    assert np.max(np.abs(ExtendedForwardModel(cfg.stage, as_backlash).residual(data))) > 0.05
