"""The hysteresis memory in the model and the controllers (microctl.models.memory, microctl.control.memory).

Independent answers: the contact physics (microctl.stage.physics, the simulator's mean, which
solves the platform's equilibrium on the actual actuator positions) for the AFM's loop shift;
a Prandtl-Ishlinskii loop written out in this file (plain loops, not microctl.stage.hysteresis)
for the controller's constraint; the simulator's truth for the gain on a trained model.
"""

from __future__ import annotations

from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest

from microctl import api
from microctl.backends.simulated import SimulatedStage
from microctl.control.baseline import AFMController
from microctl.control.memory import MEMORY_TOL_UM, MemoryCompensated, with_memory
from microctl.models.afm import AnalyticForwardModel
from microctl.models.training import residual_dataset
from microctl.stage.causes import ActuatorGain, Effects, Hysteresis
from microctl.stage.config import load_stage_config
from microctl.stage.physics import mean_reading

LOOP = (Hysteresis(1, 0.3, 3.0), Hysteresis(2, 0.25, 5.0), Hysteresis(3, 0.35, 2.0), Hysteresis(4, 0.2, 6.0))
#: Targets with long moves and reversals of every length (µm, Table I reaches about 0-25 µm).
TARGETS = [6.0, 12.0, 10.0, 11.0, 4.0, 8.0, 7.5, 18.0, 17.0, 3.0, 5.0]


def _hand_loop_offsets(loop, q_run):
    """Each actuator's PI offset w Σ_j (z_j - q) after each command of ``q_run``, written out:
    four plays per actuator with thresholds R j / 4, weights h / Σ_j r_j, from z = -r."""
    out = np.zeros_like(q_run)
    for c in loop:
        i = c.actuator - 1
        r = [c.range_um * j / 4 for j in (1, 2, 3, 4)]
        w = c.half_width_um / sum(r)
        z = [-rj for rj in r]
        for k, q in enumerate(q_run[:, i]):
            z = [max(q - rj, min(q + rj, zj)) for zj, rj in zip(z, r)]
            out[k, i] = w * sum(zj - q for zj in z)
    return out


def _physics_run(stage, effects, Q):
    qp = np.vstack([np.zeros((1, Q.shape[1])), Q[:-1]])
    return mean_reading(stage, effects, Q, q_prev=qp)


def test_memory_shift_is_the_contact_physics_loop(table1):
    """On Table I with a loop on every actuator and a gain correction, the AFM's loop shift equals
    what the contact physics reads with the loop minus without it. Tolerance 1e-3 µm: the physics'
    elastic equilibrium is not exactly the AFM's least-squares pose (the healthy AFM differs from
    it by up to ~0.04 µm at these poses); the shift is first order in the actual positions and the
    difference of differences is second order (measured 3e-4 µm). The shift itself reaches > 0.3 µm."""
    gain = (ActuatorGain(3, 0.95),)
    stage = replace(table1.stage, corrections=Effects(hysteresis=LOOP, actuator_gain=gain))
    afm = AnalyticForwardModel(stage)
    assert afm.memory.active and afm.dynamic_corrections == ()
    U = afm.workspace.sample(60, np.random.default_rng(3))
    Q = afm.q_of(U)
    qp = np.vstack([np.zeros((1, 4)), Q[:-1]])
    loop = _physics_run(table1.stage, Effects(hysteresis=LOOP, actuator_gain=gain), Q)
    plain = _physics_run(table1.stage, Effects(actuator_gain=gain), Q)
    shift = afm.memory.reading_shift(U @ afm.w_pred, afm.memory.run_shift(Q, qp))
    assert np.max(np.abs(shift)) > 0.3
    assert np.max(np.abs((loop - plain) - shift)) < 1e-3
    # move by move from the carried play states: the same shifts
    z, step = None, []
    for q in Q:
        step.append(afm.memory.displacement_shift(z, q))
        z = afm.memory.step(z, q)
    np.testing.assert_allclose(step, afm.memory.run_shift(Q, qp), atol=1e-12)
    np.testing.assert_allclose(z, afm.memory.after_run(Q), atol=0)


def test_compensated_controller_meets_the_target_round_the_loop(table1):
    """The AFM baseline wrapped with the memory: along a target sequence with reversals its command
    satisfies AFM(u) + c . (hand-written loop offset + h) = target (to MEMORY_TOL_UM), and on the contact
    physics it lands where the healthy AFM lands on a healthy stage (same mismatch to 2e-3 µm),
    while without the memory the loop costs > 0.3 µm somewhere."""
    stage = replace(table1.stage, corrections=Effects(hysteresis=LOOP))
    afm, afm0 = AnalyticForwardModel(stage), AnalyticForwardModel(table1.stage)
    ctl = with_memory(AFMController(afm, None), afm)
    assert isinstance(ctl, MemoryCompensated)
    results = ctl.solve_sequence(TARGETS)
    assert all(r.success for r in results)
    U = np.array([r.u for r in results])
    Q = np.array([r.q for r in results])
    h = np.array([0.3, 0.25, 0.35, 0.2])
    d = U @ afm.w_pred + (_hand_loop_offsets(LOOP, Q) + h) @ afm.memory.c
    # the iteration stops once the shift moves by less than MEMORY_TOL_UM (0.1 nm)
    np.testing.assert_allclose(afm.sensor.forward(d), TARGETS, atol=MEMORY_TOL_UM + 1e-8)
    np.testing.assert_allclose([r.predicted_um for r in results], TARGETS, atol=MEMORY_TOL_UM + 1e-8)
    assert all(r.constraint_residual <= MEMORY_TOL_UM + 1e-8 for r in results)
    err = _physics_run(table1.stage, Effects(hysteresis=LOOP), Q) - TARGETS
    healthy = _physics_run(table1.stage, Effects(), Q) - afm0.t_of(U)
    assert np.max(np.abs(err - healthy)) < 2e-3
    # the same controller without the memory
    plain, s, Q0 = AFMController(afm, None), afm.zero_state(), []
    for tg in TARGETS:
        r = plain.solve(tg, s)
        Q0.append(r.q)
        s = np.concatenate([[r.predicted_um], r.q])
    Q0 = np.array(Q0)
    assert np.max(np.abs(_physics_run(table1.stage, Effects(hysteresis=LOOP), Q0) - TARGETS)) > 0.3


def test_without_hysteresis_nothing_is_wrapped(table1):
    afm = AnalyticForwardModel(table1.stage)
    base = AFMController(afm, None)
    assert not afm.memory.active and with_memory(base, afm) is base
    with pytest.raises(ValueError, match="hysteresis"):
        MemoryCompensated(base, afm)


def test_residual_dataset_takes_the_loop_out(table1):
    """A log of a stage with a loop (noise-free physics) has the residual of the same moves on the
    healthy stage once the corrections carry the loop (2e-3 µm, as above); without them the loop
    stays in the residual (> 0.3 µm)."""
    U = AnalyticForwardModel(table1.stage).workspace.sample(80, np.random.default_rng(5))
    afm_loop = AnalyticForwardModel(replace(table1.stage, corrections=Effects(hysteresis=LOOP)))
    afm0 = AnalyticForwardModel(table1.stage)
    Q = afm0.q_of(U)
    s_prev = np.hstack([np.zeros((80, 1)), np.vstack([np.zeros((1, 4)), Q[:-1]])])

    def log(t):
        return SimpleNamespace(u=U, t=t, s_prev=s_prev)

    y_loop = residual_dataset(log(_physics_run(table1.stage, Effects(hysteresis=LOOP), Q)), afm_loop).y
    y_clean = residual_dataset(log(_physics_run(table1.stage, Effects(), Q)), afm0).y
    assert np.max(np.abs(y_loop - y_clean)) < 2e-3
    y_ignored = residual_dataset(log(_physics_run(table1.stage, Effects(hysteresis=LOOP), Q)), afm0).y
    assert np.max(np.abs(y_ignored - y_clean)) > 0.3


class _Recorder:
    """A controller stand-in for the Operator: the AFM baseline with the memory, recording what it was given."""

    def __init__(self, stage):
        self.stage = stage
        self.inner = with_memory(AFMController(stage.afm, None), stage.afm)
        self.settings = self.inner.settings
        self.given: list = []
        self.directions: list = []

    def solve(self, target_um, state, memory=None, direction=None):
        self.given.append(None if memory is None else memory.copy())
        self.directions.append(None if direction is None else np.array(direction))
        return self.inner.solve(target_um, state, memory=memory)


def test_operator_steps_the_play_states_with_the_commands_it_sends():
    """The play states the Operator passes before move k are the loop's after the commands it sent
    (from the backend's q at the start), and match the simulated stage's own play states."""
    cfg = load_stage_config("sim_paper")
    loop = (Hysteresis(2, 0.3, 4.0), Hysteresis(4, 0.2, 3.0))
    cfg = replace(cfg, stage=replace(cfg.stage, corrections=replace(cfg.stage.corrections, hysteresis=loop)),
                  backend=replace(cfg.backend, simulated=replace(cfg.backend.simulated, effects=Effects(hysteresis=loop))))
    stage = api.Stage(cfg, AnalyticForwardModel(cfg.stage))
    rec = _Recorder(stage)
    backend = SimulatedStage(cfg, seed=1)
    sent = []
    with api.Operator(rec, backend) as op:
        for tg in (10.0, 30.0, 20.0, 25.0, 5.0):
            m = op.move(tg)
            sent.append(m.q_um)
            np.testing.assert_allclose(op.memory[[1, 3]], backend.play[[1, 3]], atol=1e-12)
    mem = stage.afm.memory
    for k, z in enumerate(rec.given):
        want = mem.after_run(np.array(sent[:k]), mem.zero()) if k else mem.zero()
        np.testing.assert_allclose(z, want, atol=1e-12)
    # and each actuator's last direction of motion (+1 from the zero state; a held actuator keeps
    # it; held = a command change of at most 1e-6 µm, the documented tolerance: the solver's
    # commands for a held actuator can differ from the last by a rounding error, 1e-17 µm)
    q = np.vstack([np.zeros(len(sent[0]))] + sent)
    last = np.ones(q.shape[1])
    for k, d in enumerate(rec.directions):
        np.testing.assert_array_equal(d, last)
        step = q[k + 1] - q[k]
        last = np.where(np.abs(step) > 1e-6, np.sign(step), last)


@pytest.mark.slow
def test_trained_controller_with_the_memory_reaches_the_floor():
    """End to end on ``sim_paper`` with a loop on all four actuators (rig 1 of
    scripts/bench_memory.py, 120 training moves, 12 targets): the controller with the loop in its
    corrections has a true RMS error below half of the one without, and within 0.02 µm of the same
    rig without any loop (the floor: stick-slip and the GP's accuracy). The bench measures the same
    over ten rigs."""
    from pathlib import Path
    import tempfile

    from script_loader import load_script

    bench = load_script("bench_memory")
    from microctl.testing.plant import simulate

    base = api.load_stage("sim_paper")
    plain, mem, clean, loop = bench._rig(base, 1)
    assert len(loop) == 4
    lo, hi = base.afm.t_range()
    targets = np.random.default_rng(0).uniform(lo + 0.15 * (hi - lo), hi - 0.15 * (hi - lo), 12)
    rms = {}
    with tempfile.TemporaryDirectory() as tmp:
        for name, stage in (("without", plain), ("memory", mem), ("clean", clean)):
            log = Path(tmp) / f"{name}.csv"
            simulate(stage.config, stage.config.backend.simulated.effects, 120, seed=11, log_path=log)
            api.train(log, stage, out=Path(tmp) / f"{name}.npz", seed=0)
            e, _ = bench._drive(stage, Path(tmp) / f"{name}.npz", targets, seed=12)
            rms[name] = float(np.sqrt(np.mean(e ** 2)))
    assert rms["memory"] < 0.5 * rms["without"], rms
    assert abs(rms["memory"] - rms["clean"]) < 0.02, rms


def test_experiment_moves_meet_the_target_with_the_play_states(table1):
    """The incremental phase's solve step (experiments.runner._solve) wraps both the controller
    and its fallback when it is given play states, and its command meets the target with them."""
    from microctl.experiments.runner import _solve

    afm = AnalyticForwardModel(replace(table1.stage, corrections=Effects(hysteresis=LOOP)))
    z = afm.memory.after_run(np.array([[20.0, 20.0, 20.0, 20.0], [2.0, 3.0, 2.0, 3.0]]))
    run = SimpleNamespace(afm=afm, say=lambda msg: None)
    res = _solve(AFMController(afm, None), 9.0, afm.zero_state(), None, run, {"fallbacks": 0},
                 fallback=AFMController(afm, None), memory=z)
    shift = afm.memory.reading_shift(afm.w_pred @ res.u, afm.memory.displacement_shift(z, res.q))
    assert abs(float(afm.t_of(res.u[None, :])[0]) + shift - 9.0) < MEMORY_TOL_UM + 1e-8
    assert abs(res.hysteresis_um - shift) < 1e-12 and abs(shift) > 0.05


def test_sequence_plan_meets_every_target_round_the_loop(table1):
    """The sequence planner wrapped with the memory: every planned command meets its target with
    the hand-written loop run along the planned commands (to MEMORY_TOL_UM), on an EAFM whose mean is the
    AFM's (a fixed model with zero mean correction), and the CLI path's planner is the same."""
    import math

    from microctl.control.sequence import SequenceController
    from microctl.control.settings import ControllerSettings
    from microctl.models.eafm import EAFM, bind_to_stage
    from microctl.testing import fixed_hyperparameter_model

    afm = AnalyticForwardModel(replace(table1.stage, corrections=Effects(hysteresis=LOOP)))
    rng = np.random.default_rng(0)
    U = afm.workspace.sample(40, rng)
    S = np.column_stack([rng.uniform(0, 25, 40), rng.uniform(0, 30, (40, 4))])
    m = fixed_hyperparameter_model(np.hstack([S, U]), 0.01 * rng.standard_normal(40), np.full(40, math.log(1e-4)),
                                   f_log_lengthscales=np.full(8, 0.5), g_log_signal_var=-12.0)
    model = bind_to_stage(replace(m, f_alpha=np.zeros(40), y_mean=0.0), afm)
    targets = [12.0, 6.0, 9.0, 7.5]
    plan = with_memory(SequenceController(EAFM(afm, model), ControllerSettings(epistemic=False)), afm).plan(
        targets, memory=afm.memory.zero())
    assert plan.success
    Uq = np.array([st.u for st in plan.steps])
    Q = np.array([st.q for st in plan.steps])
    h = np.array([c.half_width_um for c in LOOP])
    d = Uq @ afm.w_pred + (_hand_loop_offsets(LOOP, Q) + h) @ afm.memory.c
    np.testing.assert_allclose(afm.sensor.forward(d), targets, atol=MEMORY_TOL_UM + 1e-8)
    np.testing.assert_allclose([st.predicted_um for st in plan.steps], targets, atol=MEMORY_TOL_UM + 1e-8)
    assert max(abs(st.hysteresis_um) for st in plan.steps) > 0.05


def test_absolute_experiment_predictions_carry_the_loop(table1):
    """The absolute experiment's commands (zero, point 0, zero, point 1, ...): its loop shifts equal
    the contact physics with the loop minus without along that run (1e-3 µm, as above)."""
    from microctl.experiments.runner import _absolute_loop_shifts

    afm = AnalyticForwardModel(replace(table1.stage, corrections=Effects(hysteresis=LOOP)))
    U = afm.workspace.sample(12, np.random.default_rng(9))
    shifts = _absolute_loop_shifts(afm, U)
    run = np.zeros((2 * len(U), 4))
    run[1::2] = afm.q_of(U)
    loop = _physics_run(table1.stage, Effects(hysteresis=LOOP), run)[1::2]
    plain = _physics_run(table1.stage, Effects(), run)[1::2]
    assert np.max(np.abs(shifts)) > 0.05  # from zero most moves go up, the loop matters after reversals
    np.testing.assert_allclose(shifts, loop - plain, atol=1e-3)
    assert not np.any(_absolute_loop_shifts(AnalyticForwardModel(table1.stage), U))
