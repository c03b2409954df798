"""The move's context (each actuator's last direction) and the reversal noise source that reads it.

The hidden effect here is hysteresis scatter written in this file from the command sequence
(not through the package's direction tracking or its dictionary): a reading is scattered only
where an actuator turns round. The package must find it on that actuator, predict the scatter
on reversing moves and not on continuing ones, and keep CasADi, NumPy and the model file in
agreement for a model whose inputs carry the context.
"""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import casadi as ca
import numpy as np
import pytest

from microctl.control.context import ByDirection
from microctl.gp.fitted import FittedVHGPR
from microctl.gp.kernels import Kernel
from microctl.measurement.design import training_moves
from microctl.models import direction
from microctl.models.afm import AnalyticForwardModel
from microctl.models.eafm import EAFM
from microctl.models.noise_dictionary import candidate_features, select_features
from microctl.models.training import ResidualModelSettings, residual_dataset, train_residual_model
from microctl.stage.config import load_stage_config

ROOT = Path(__file__).resolve().parents[2]
GAUGE_UM, REV_UM, REV_SCALE_UM, REV_ACT = 0.03, 0.25, 0.5, 2  # actuator 3 (0-based 2)


@pytest.fixture(scope="module")
def afm():
    return AnalyticForwardModel(load_stage_config(ROOT / "configs/stage/sim_paper.yaml").stage)


def test_log_directions_worked_by_hand():
    """Two actuators: up, hold, down, an unlogged jump up, then a hold of the first (rows by hand)."""
    q_prev = np.array([[0, 0], [1, 0], [1, 2], [0.5, 2], [0.8, 1]], float)  # row 4 starts after a jump 0.5 -> 0.8
    q = np.array([[1, 0], [1, 2], [0.5, 2], [0.5, 1], [0.8, 3]], float)
    want = np.array([[1, 1],     # the zero state: +1
                     [1, 1],     # after 0 -> 1 (up), 0 held
                     [1, 1],     # after 1 held, 0 -> 2 (up)
                     [-1, 1],    # after 1 -> 0.5 (down), 2 held
                     [1, -1]],   # after 2 -> 1 (down), then the unlogged jump 0.5 -> 0.8 (up)
                    float)
    np.testing.assert_array_equal(direction.log_directions(q_prev, q), want)
    np.testing.assert_array_equal(direction.after_move([1, -1], [2, 2], [2, 3]), [1, 1])
    np.testing.assert_array_equal(direction.at_commands([0.0, -1.0, 3.0]), [1, -1, 1])  # one move from zero


def test_kernels_ignore_the_columns_beyond_their_lengthscales():
    rng = np.random.default_rng(3)
    k = Kernel(rng.normal(size=3), 0.3, -2.0, rng.normal(size=3))
    X, Z = rng.normal(size=(7, 3)), rng.normal(size=(5, 3))
    Xc, Zc = np.hstack([X, rng.normal(size=(7, 2))]), np.hstack([Z, rng.normal(size=(5, 2))])
    np.testing.assert_array_equal(k.matrix(Xc, Zc), k.matrix(X, Z))
    np.testing.assert_array_equal(k.diag(Xc), k.diag(X))
    v, g = k.cross_grad(Xc, k.cross_terms(Zc, np.ones(5)))
    v0, g0 = k.cross_grad(X, k.cross_terms(Z, np.ones(5)))
    np.testing.assert_array_equal(v, v0)
    np.testing.assert_array_equal(g[:, :3], g0)
    assert g.shape == (7, 5) and not np.any(g[:, 3:])
    xs = ca.MX.sym("x", 5)
    col = ca.Function("k", [xs], [k.casadi_column(xs, Zc)])
    np.testing.assert_allclose(np.array(col(Xc[0])).ravel(), k.matrix(X[:1], Z).ravel(), rtol=1e-12)


def _reversal_log(afm, n: int, seed: int, rev_um: float):
    """The covering design run from the zero state; readings: the AFM's plus gauge noise plus, where
    actuator 3 turns round, N(0, (rev_um (1 - exp(-|dq| / 0.5)))^2) (directions tracked here)."""
    rng = np.random.default_rng(seed)
    U = training_moves(afm, "covering", n, seed)
    Q = U @ afm.K.T
    Qp = np.vstack([np.zeros(afm.n_q), Q[:-1]])
    last, sd = 1.0, np.empty(n)
    for k in range(n):
        dq = Q[k, REV_ACT] - Qp[k, REV_ACT]
        new = last if dq == 0 else float(np.sign(dq))
        sd[k] = rev_um * (1 - np.exp(-abs(dq) / REV_SCALE_UM)) if new != last else 0.0
        last = new
    t = np.asarray(afm.t_of(U)) + np.sqrt(GAUGE_UM**2 + sd**2) * rng.standard_normal(n)
    t_prev = np.concatenate([[0.0], t[:-1]])
    return SimpleNamespace(u=U, t=t, s_prev=np.column_stack([t_prev, Qp]))


@pytest.fixture(scope="module")
def reversal_model(afm):
    data = residual_dataset(_reversal_log(afm, 200, 5, REV_UM), afm)
    # the reversal alone: no trend in f of the other selected sources (the mean-shift trend,
    # tests/models/test_mean_shift.py), which moves the plans these tests read the directions of
    return train_residual_model(data, afm, ResidualModelSettings(restarts=1, mean_shift=False))


def test_a_planted_reversal_is_found_on_its_actuator(afm, reversal_model):
    sel = reversal_model.info["noise_selection"]["selected"]
    assert any(nm.startswith("dq3:rev") for nm in sel), sel
    assert reversal_model.n_context == afm.n_q and reversal_model.x_names[-afm.n_q:] == tuple(
        f"dir{i + 1}_prev" for i in range(afm.n_q))


def test_the_predicted_scatter_is_high_only_where_the_actuator_turns_round(afm, reversal_model):
    """A 3 µm step of actuator 3 (the platform's z with tilt kept) from a mid pose: after it last moved
    down, a step up is a reversal; after it last moved up, the same step is not."""
    eafm = EAFM(afm, reversal_model)
    q_prev = np.full(afm.n_q, 12.0)
    u_prev = np.linalg.lstsq(afm.K, q_prev, rcond=None)[0]
    s = np.concatenate([[float(afm.t_of(u_prev))], q_prev])
    q = q_prev.copy()
    q[REV_ACT] += 3.0
    u = np.linalg.lstsq(afm.K, q, rcond=None)[0]
    up, down = np.ones(afm.n_q), np.ones(afm.n_q)
    down[REV_ACT] = -1.0
    noise = {}
    for name, d in (("continuing", up), ("reversing", down)):
        p = eafm.with_direction(d).predict(s, u)
        noise[name] = float(np.exp(p.g_mean[0]))
    truth_rev = GAUGE_UM**2 + (REV_UM * (1 - np.exp(-3.0 / REV_SCALE_UM))) ** 2
    # the reversing move's predicted variance is within a factor 2 of the truth (200 moves, about
    # 40 of them reversals of actuator 3), the continuing one's below a quarter of it
    assert truth_rev / 2 < noise["reversing"] < 2 * truth_rev, noise
    assert noise["continuing"] < truth_rev / 4, noise


def test_casadi_numpy_and_the_model_file_agree_with_a_context(afm, reversal_model, tmp_path):
    rng = np.random.default_rng(11)
    path = tmp_path / "rev.npz"
    reversal_model.save(path)
    back = FittedVHGPR.load(path)
    U = afm.workspace.sample(6, rng)
    S = np.column_stack([rng.uniform(0, 20, 6), afm.workspace.sample(6, rng) @ afm.K.T])
    for d in (np.ones(afm.n_q), np.array([1.0, -1.0, -1.0, 1.0])):
        e, e2 = EAFM(afm, reversal_model).with_direction(d), EAFM(afm, back).with_direction(d)
        for s, u in zip(S, U):
            p = e.predict(s, u)
            out = e.function(s=s, u=u)
            for k in ("t_mean", "f_var", "g_mean", "g_var"):
                np.testing.assert_allclose(float(out[k]), float(getattr(p, k)[0]), rtol=1e-9, atol=1e-12)
            np.testing.assert_array_equal(e2.predict(s, u).g_mean, p.g_mean)
        m, v = e.g_np_pairs(S[:2], U)
        for i in range(2):
            m1, v1 = e.g_np(S[i], U)
            np.testing.assert_allclose(m[i], m1, rtol=1e-10)
            np.testing.assert_allclose(v[i], v1, rtol=1e-10)


def test_one_controller_per_direction_and_one_for_a_model_without_it(afm, reversal_model):
    built = []
    by = ByDirection(EAFM(afm, reversal_model), lambda e: built.append(e) or len(built))
    a, b = by(None), by([1, 1, -1, 1])
    assert (a, b, by([1, 1, 1, 1]), by([1, 1, -1, 1])) == (1, 2, 1, 2)
    assert built[1].direction.tolist() == [1, 1, -1, 1]
    with pytest.raises(ValueError, match="last directions"):
        by([1, 0, 1, 1])


def test_clean_readings_select_no_reversal(afm):
    """Gauge noise only, on the covering design with its directions: no source at all on >= 18 of 20
    seeds (family-wise level 0.05 over every candidate, reversals included; the binomial 95 % upper
    bound on false selections at 5 % is 2.7 of 20), and never a reversal on more than 2."""
    hits = revs = 0
    for seed in range(20):
        log = _reversal_log(afm, 200, 200 + seed, 0.0)
        data = residual_dataset(log, afm)
        X = data.context_inputs(afm.n_q)
        cands = candidate_features(afm, context=True).rescaled(X)
        r = data.y - data.y.mean()
        sel = select_features(r, cands.values(X), cands.names)
        hits += bool(sel.names)
        revs += any(":rev" in nm for nm in sel.names)
    assert hits <= 2 and revs <= 2, (hits, revs)


def test_the_api_controller_solves_with_the_direction_it_is_given(afm, reversal_model):
    """``api.Controller.solve(direction=...)`` uses that direction's model: each direction's
    command is at least as quiet under its own model as the other direction's command (both
    reach the target), its stated noise is that model's at the command, and it does not turn
    the planted actuator round."""
    from microctl import api

    stage = api.load_stage(ROOT / "configs/stage/sim_paper.yaml")
    ctl = api.Controller(stage, reversal_model)
    q_prev = np.full(afm.n_q, 12.0)
    u_prev = np.linalg.lstsq(afm.K, q_prev, rcond=None)[0]
    s = np.concatenate([[float(afm.t_of(u_prev))], q_prev])
    target = float(afm.t_of(u_prev)) + 3.0
    down = np.ones(afm.n_q)
    down[REV_ACT] = -1.0
    res = {k: ctl.solve(target, s, direction=d) for k, d in (("up", None), ("down", down))}
    eafm = {"up": EAFM(afm, reversal_model), "down": EAFM(afm, reversal_model).with_direction(down)}
    for k, other in (("up", "down"), ("down", "up")):
        own = float(np.exp(eafm[k].predict(s, res[k].u).g_mean[0]))
        alt = float(np.exp(eafm[k].predict(s, res[other].u).g_mean[0]))
        assert abs(res[k].predicted_um - target) < 1e-6
        assert own <= alt * 1.05, (k, own, alt)
        np.testing.assert_allclose(res[k].noise_std_um ** 2, own, rtol=0.25)
    # neither turns actuator 3 round (a reversal of more than 0.1 µm: about a fifth of the planted
    # scatter's saturation step), so the two commands move it in opposite directions
    assert res["up"].q[REV_ACT] - q_prev[REV_ACT] >= -0.1 and res["down"].q[REV_ACT] - q_prev[REV_ACT] <= 0.1


def _directions_by_hand(Q: np.ndarray) -> list[np.ndarray]:
    """Each actuator's last direction before every move of the commands Q (rows: the zero state,
    then the commands in order), by this file's rule: the sign of the step, a step of at most
    1e-6 µm holds the direction, the zero state counts as up."""
    last, hand = np.ones(Q.shape[1]), []
    for k in range(1, len(Q)):
        hand.append(last.copy())
        dq = Q[k] - Q[k - 1]
        last = np.where(np.abs(dq) > 1e-6, np.sign(dq), last)
    return hand


def test_the_runner_replans_a_sequence_from_the_directions_of_the_commands_sent(afm, reversal_model, tmp_path,
                                                                                 monkeypatch):
    """The experiments' re-planning sequence controller (``eafm_sequence``), on a model that reads
    the directions: every re-plan is made with each actuator's last direction of motion before
    that move, recomputed here from the incremental log's commands by the rule written in this
    file (sign of the step, a hold keeps the direction, the zero state counts as up); a
    down-and-up target list turns actuators round, so the directions change along it."""
    from dataclasses import replace

    from microctl.experiments import runner
    from microctl.experiments.config import load_experiment_config
    from microctl.measurement.log import read_log

    cfg = load_experiment_config(ROOT / "configs/experiments/paper.yaml")
    cfg = replace(cfg, controllers=("afm", "eafm_sequence"),
                  incremental=replace(cfg.incremental, targets_um=(9.0, 4.0, 8.0), trials=1))
    run = runner._Run(cfg=cfg, out=tmp_path, stage_config=cfg.stage_config, factory=runner.default_backend_factory,
                      quiet=True, afm=afm)
    seen = []
    build = ByDirection.__call__

    def spy(self, direction=None):  # the runner's per-controller factory carries the controller's name
        if (self._make.__defaults__ or (None,))[0] == "eafm_sequence":
            seen.append(np.ones(afm.n_q) if direction is None else np.asarray(direction, dtype=float).copy())
        return build(self, direction)

    monkeypatch.setattr(ByDirection, "__call__", spy)
    runner._incremental(run, EAFM(afm, reversal_model))
    log = read_log(tmp_path / runner.LOG_NAMES["incremental"], cfg.stage_config.stage)
    rows = [k for k, c in enumerate(log.extra["controller"]) if c == "eafm_sequence"]
    Q = np.asarray(log.q)[rows]  # the zero state, then the three targets' commands
    hand = _directions_by_hand(Q)
    assert len(seen) == 3
    np.testing.assert_array_equal(np.array(seen), np.array(hand))
    assert np.any(np.array(hand) < 0)  # the list turned some actuator round


def test_refinement_plans_each_move_with_the_directions_of_the_commands_sent(afm, reversal_model):
    """Refinement (microctl.control.refine) on a model that reads the directions: every solve and
    every exploration of candidates is made with each actuator's last direction before that move,
    recomputed here from the commands the stage executed by the rule written in this file; the
    return to the zero state that starts the second episode turns actuators round, so the
    directions change along the moves."""
    from microctl.backends.simulated import SimulatedStage
    from microctl.control.controller import OptimalController
    from microctl.control.refine import refinement_moves

    class Spy:  # records the direction of the model each planning call was made with
        def __init__(self, eafm):
            self.inner, self.eafm = OptimalController(eafm), eafm

        def solve(self, *a, **k):
            seen.append(("solve", self.eafm.direction.copy()))
            return self.inner.solve(*a, **k)

        def candidates(self, *a, **k):
            seen.append(("candidates", self.eafm.direction.copy()))
            return self.inner.candidates(*a, **k)

    seen, Q = [], [np.zeros(afm.n_q)]
    cfg = load_stage_config(ROOT / "configs/stage/sim_paper.yaml")
    with SimulatedStage(cfg, seed=3) as st:
        for mv in refinement_moves(ByDirection(EAFM(afm, reversal_model), Spy), 10, (2.0, 30.0),
                                   np.random.default_rng(4), lambda: st.state):
            st.move(mv.u)
            Q.append(np.asarray(st.state[1:], dtype=float).copy())
    hand = _directions_by_hand(np.array(Q))
    planned = [k for k in range(len(Q) - 1) if np.any(Q[k + 1] != 0)]  # the moves that are not returns to zero
    assert len(planned) == 8
    solves = [d for what, d in seen if what == "solve"]
    np.testing.assert_array_equal(np.array(solves), np.array([hand[k] for k in planned]))
    assert all(any(np.array_equal(d, hand[k]) for k in planned) for what, d in seen if what == "candidates")
    assert np.any(np.array([hand[k] for k in planned]) < 0)  # some move was planned after a reversal


def test_a_malformed_direction_is_a_config_error_naming_what_is_valid(afm, reversal_model):
    """A direction of the wrong length or with a value other than +1/-1 is refused with one line
    that says what is valid; ConfigError is a ValueError."""
    from microctl.errors import ConfigError

    eafm = EAFM(afm, reversal_model)
    for bad in ([1.0, 1.0, 1.0], [1.0, 0.0, 1.0, -1.0], [1.0, 2.0, 1.0, 1.0]):
        with pytest.raises(ConfigError, match=r"must be 4 values of \+1 or -1, got"):
            eafm.with_direction(np.array(bad))
    with pytest.raises(ValueError, match=r"values of \+1 or -1"):
        EAFM(afm, reversal_model, direction=np.array([1.0, -1.0]))
