"""The controller's fast path (microctl/control/fastpath.py) against IPOPT and against the KKT conditions."""

from __future__ import annotations

import numpy as np
import pytest
from test_controller import ROOT, _check_valid, _states, planted_model

from microctl.control.controller import ControllerSettings, OptimalController
from microctl.control.fastpath import ActiveSetQP, _reduced_convex
from microctl.models.afm import AnalyticForwardModel
from microctl.models.eafm import EAFM
from microctl.stage.config import load_stage_config


@pytest.fixture(scope="module")
def afm() -> AnalyticForwardModel:
    return AnalyticForwardModel(load_stage_config(ROOT / "configs/stage/table1.yaml").stage)


@pytest.fixture(scope="module")
def pair(afm):
    """The same EAFM (a nonlinear mean and a low-noise well: several local minima) with and without the fast path."""
    eafm = EAFM(afm, planted_model(afm, seed=3))
    return eafm, OptimalController(eafm), OptimalController(eafm, ControllerSettings(fast_path=False))


def _targets(ctl, states, rng):
    rg = np.array([ctl.reachable_interval(s) for s in states])
    return rg[:, 0] + (0.03 + 0.94 * rng.uniform(size=len(states))) * (rg[:, 1] - rg[:, 0])


def test_qp_step_satisfies_its_kkt_conditions():
    """The enumerated active-set QP returns the KKT point of random convex QPs (checked term by term)."""
    rng = np.random.default_rng(0)
    K = rng.normal(size=(4, 3))
    active = 0
    for _ in range(300):
        u = rng.uniform(-3, 3, 3)
        q = K @ u  # ranges a short way either side of u, so steps press against them
        sqp = ActiveSetQP(K, q - rng.uniform(0, 0.5, 4), q + rng.uniform(0, 0.5, 4))
        L = rng.normal(size=(3, 3))
        B = L @ L.T + 1e-3 * np.eye(3)
        g, a = rng.normal(size=3) * 10, rng.normal(size=3)
        slack = sqp.b - sqp.A @ u
        out = sqp.solve(B, g, a, 0.0, slack)
        assert out is not None  # d = 0 is feasible, so a minimum exists
        d, lam, mu = out
        active += np.any(mu > 0)
        assert np.max(np.abs(B @ d + g - lam * a - sqp.A.T @ mu)) <= 1e-8 * (1 + np.abs(g).max())
        assert abs(a @ d) <= 1e-9
        assert np.all(sqp.A @ d >= slack - 1e-8) and np.all(mu >= -1e-12)
        assert np.max(np.abs(mu * (sqp.A @ d - slack))) <= 1e-8
    assert active > 100  # the ranges mattered in most of them


def test_tangent_convexification_keeps_positive_curvature():
    rng = np.random.default_rng(1)
    for _ in range(50):
        B = rng.normal(size=(3, 3))
        a = rng.normal(size=3)
        B = B + B.T
        Bm = _reduced_convex(B, a)
        Z = np.linalg.svd(a[None, :])[2][1:].T  # an orthonormal basis of the tangent space
        assert np.all(np.linalg.eigvalsh(Z.T @ Bm @ Z) > 0)
        if np.all(np.linalg.eigvalsh(Z.T @ B @ Z) > 1e-9):  # already convex there: unchanged
            np.testing.assert_allclose(Bm, 0.5 * (B + B.T))


def test_fast_path_matches_ipopt_from_the_same_starts(afm, pair):
    """At 40 random (state, target), from the controller's own seeds: the SQP's point passes the KKT,
    target and range checks and its objective equals IPOPT's from the same start (same local minimum)."""
    eafm, fast, slow = pair
    rng = np.random.default_rng(11)
    states = _states(afm, 40, seed=11)
    targets = _targets(slow, states, rng)
    compared = 0
    for s, t in zip(states, targets):
        U, obj, mins = fast._seeds(s, float(t), fast.settings.grid)
        for i in mins[:2]:
            x, st = fast._fast.solve(U[i], s, float(t))
            assert st["success"], st
            assert st["kkt"] <= fast.settings.ipopt_tol
            q = afm.K @ x
            assert np.all(q >= afm.lo - 1e-9) and np.all(q <= afm.hi + 1e-9)
            assert abs(eafm.predict(s, x).t_mean[0] - t) <= 1e-8
            jref = float(slow._objective_np(s, U[i][None, :], seeding=True)[0])
            xi, sti = slow._run(slow._ipopt(), U[i], np.concatenate([[t], s, [jref]]), afm.workspace.u_lo,
                                afm.workspace.u_hi, slow._lbg, slow._ubg)
            if not sti["success"]:
                continue
            j_fast = float(slow._objective_np(s, x[None, :])[0])
            j_ipopt = float(slow._objective_np(s, xi[None, :])[0])
            assert j_fast == pytest.approx(st["objective"], rel=1e-9)
            assert j_fast <= j_ipopt * (1 + 1e-6) + 1e-15  # never worse; IPOPT stops a barrier's width off a bound
            compared += 1
    assert compared >= 60


def test_controller_with_fast_path_is_as_good_as_ipopt(afm, pair):
    eafm, fast, slow = pair
    rng = np.random.default_rng(12)
    states = _states(afm, 30, seed=12)
    targets = _targets(slow, states, rng)
    for s, t in zip(states, targets):
        a, b = fast.solve(t, s), slow.solve(t, s)
        assert a.success and a.status == "Solve_Succeeded"
        _check_valid(a, afm, eafm, t)
        assert a.objective <= b.objective * (1 + 1e-6) + 1e-15


def test_a_start_the_fast_path_cannot_finish_goes_to_ipopt(afm, pair, monkeypatch):
    eafm, fast, slow = pair
    monkeypatch.setattr(fast._fast, "max_iter", 0)  # the SQP gives up at once
    calls = []
    run = fast._run
    monkeypatch.setattr(fast, "_run", lambda *a: calls.append(1) or run(*a))
    s = _states(afm, 1, seed=13)[0]
    r = fast.solve(10.0, s)
    assert calls and r.success and r.iterations > 0
    assert r.objective == pytest.approx(slow.solve(10.0, s).objective, rel=1e-6)


def test_the_bound_buffer_evaluates_exactly_as_the_plain_call(afm, pair, monkeypatch):
    """FastSQP evaluates its graph through a CasADi buffer bound to fixed arrays; the answer must
    be the plain call's, bit for bit (independent answer: the same Function called with DMs), also
    after other evaluations have overwritten the buffer's arrays, and a solve without the buffer
    returns the same command."""
    eafm, fast, _ = pair
    sqp = fast._fast
    assert sqp._buffer is not None  # casadi >= 3.6 (pyproject) has buffers
    rng = np.random.default_rng(21)
    S = _states(afm, 4, seed=22)
    U = rng.uniform(afm.workspace.u_lo, afm.workspace.u_hi, size=(4, afm.n_p))
    def plain(u, s, lam):  # the same evaluation through the plain call
        monkeypatch.setattr(sqp, "_buffer", None)
        try:
            return sqp._eval(u, s, lam)
        finally:
            monkeypatch.undo()

    def same(a, b):
        for x, y in zip(a, b):
            np.testing.assert_array_equal(x, y)

    first = sqp._eval(U[0], S[0], 0.3)
    for u, s, lam in zip(U, S, rng.normal(size=4)):
        same(sqp._eval(u, s, float(lam)), plain(u, s, float(lam)))
    # a result returned earlier is a copy: later evaluations do not change it
    same(first, plain(U[0], S[0], 0.3))
    t = float(_targets(fast, S[:1], rng)[0])
    x_buf, st_buf = sqp.solve(U[0], S[0], t)
    monkeypatch.setattr(sqp, "_buffer", None)
    x_plain, st_plain = sqp.solve(U[0], S[0], t)
    np.testing.assert_array_equal(x_buf, x_plain)
    assert st_buf["iter"] == st_plain["iter"]
