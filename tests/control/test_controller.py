"""The optimal controller (eq. 4) and the baselines, each checked against an independent answer."""

from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np
import pytest

from microctl.control.controller import (
    AFMController,
    ControllerSettings,
    EAFMMeanController,
    OptimalController,
)
from microctl.errors import ConfigError, UnreachableTargetError
from microctl.models.afm import AnalyticForwardModel
from microctl.models.eafm import EAFM, bind_to_stage
from microctl.stage.config import load_stage_config
from microctl.testing import fixed_hyperparameter_model

ROOT = Path(__file__).resolve().parents[2]
WELL = (0.5, -0.3)  # planted low-noise region in (rx, ry), mrad: it crosses every target's redundant set


@pytest.fixture(scope="module")
def afm() -> AnalyticForwardModel:
    return AnalyticForwardModel(load_stage_config(ROOT / "configs/stage/table1.yaml").stage)


def planted_model(afm: AnalyticForwardModel, n: int = 120, seed: int = 0):
    """Residual GP whose noise std is 0.2 µm except 0.02 µm near (rx, ry) = WELL."""
    rng = np.random.default_rng(seed)
    U = afm.workspace.sample(n, rng)
    S = np.column_stack([rng.uniform(0, 30, n), rng.uniform(0, 32, (n, afm.n_q))])
    ln = np.log(0.2**2) + (np.log(0.02**2) - np.log(0.2**2)) * np.exp(
        -((U[:, 1] - WELL[0]) ** 2 + (U[:, 2] - WELL[1]) ** 2) / (2 * 0.15**2))
    y = 0.3 * np.sin(U[:, 0] / 8) + 0.2 * U[:, 1] + np.exp(ln / 2) * rng.standard_normal(n)
    m = fixed_hyperparameter_model(np.hstack([S, U]), y, ln,
                                   f_log_lengthscales=np.array([3.0, 3, 3, 3, 3, 0.0, -0.7, -0.7]))
    return bind_to_stage(m, afm)


@pytest.fixture(scope="module")
def eafm(afm):
    return EAFM(afm, planted_model(afm))


@pytest.fixture(scope="module")
def opt(eafm):
    return OptimalController(eafm, ControllerSettings(prefer_least_motion=False))  # eq. 4 itself


def _states(afm, m, seed=0):
    rng = np.random.default_rng(seed)
    return np.column_stack([rng.uniform(0, 30, m), rng.uniform(0, 32, (m, afm.n_q))])


def _check_valid(res, afm, eafm, target):
    q = afm.K @ res.u
    assert np.all(q >= afm.lo - 1e-9) and np.all(q <= afm.hi + 1e-9)
    assert np.all(res.q >= afm.lo) and np.all(res.q <= afm.hi)
    t = eafm.predict(res.state, res.u).t_mean[0]
    assert abs(t - target) <= 1e-8


def test_planted_low_noise_region_is_chosen(afm, eafm, opt):
    """The paper's objective (noise only) lands in the planted well (within its 0.15 mrad width);
    the default, which adds f's posterior variance, stays in it too (the well's noise variance,
    4e-4 µm², is of the order of f's variance there, so its pose may move towards the data by a
    fraction of the width: 0.25 mrad), and its expected squared error (noise + f variance,
    evaluated by the NumPy posterior) is no larger than at the noise-only pose."""
    base = AFMController(afm, reporter=eafm)
    noise_only = OptimalController(eafm, ControllerSettings(epistemic=False))
    for target in (12.0, 18.0, 24.0):  # targets whose redundant set crosses the well inside the ranges
        r0 = noise_only.solve(target)
        r = opt.solve(target)
        b = base.solve(target)
        assert r.success and r0.success
        assert np.hypot(r0.u[1] - WELL[0], r0.u[2] - WELL[1]) < 0.15
        assert np.hypot(r.u[1] - WELL[0], r.u[2] - WELL[1]) < 0.25
        assert np.hypot(b.u[1] - WELL[0], b.u[2] - WELL[1]) > 0.3
        assert r.predicted_std_um < b.predicted_std_um
        assert abs(float(afm.t_of(b.u)) - target) <= 1e-8
        s = np.zeros(afm.n_s)

        def mse(u):
            p = eafm.predict(s, u[None, :])
            return float(np.exp(p.g_mean[0] + 1.645 * np.sqrt(p.g_var[0])) + p.f_var[0])
        assert mse(r.u) <= mse(r0.u) * (1 + 1e-6)


@pytest.mark.parametrize("cls", [OptimalController, EAFMMeanController])
def test_constraint_and_ranges_on_every_solution(afm, eafm, cls):
    ctl = cls(eafm)
    rng = np.random.default_rng(2)
    lo, hi = afm.t_range()
    for s, target in zip(_states(afm, 15), rng.uniform(lo + 2, hi - 2, 15)):
        r = ctl.solve(target, s)
        assert r.success, r.status
        _check_valid(r, afm, eafm, target)


def test_afm_baseline_is_the_smallest_motion(afm):
    ctl = AFMController(afm)
    rng = np.random.default_rng(3)
    for s in _states(afm, 6, seed=3):
        target = rng.uniform(0, 40)
        r = ctl.solve(target, s)
        assert abs(float(afm.t_of(r.u)) - target) <= 1e-8
        q = afm.K @ r.u
        assert np.all(q >= afm.lo - 1e-9) and np.all(q <= afm.hi + 1e-9)
        # independent: random feasible points of the same plane never move the actuators less
        U = afm.workspace.sample(4000, rng)
        U = U + np.outer((target - U @ afm.w_pred) / (afm.w_pred @ afm.w_pred), afm.w_pred)
        U = U[afm.workspace.contains(U)]
        other = np.sum((U @ afm.K.T - s[1:]) ** 2, axis=1)
        assert r.objective <= other.min() + 1e-9


def test_afm_baseline_closed_form_equals_ipopt(afm, nlpsol_calls):
    """Without IPOPT: the plane's minimiser when every range holds, else the active-set QP step
    from it; both are the convex QP's optimum, so IPOPT from the same point must agree."""
    ctl = AFMController(afm)
    rng = np.random.default_rng(11)
    closed = active = 0
    for s in _states(afm, 150, seed=11):
        target = rng.uniform(0, 40)
        r = ctl.solve(target, s)
        qp = s[1:]
        x, st = ctl._run(ctl._ipopt(), r.u, np.concatenate([[ctl.rset.d_of_target(target)], qp]),
                         afm.workspace.u_lo, afm.workspace.u_hi, np.concatenate([[0.0], afm.lo]),
                         np.concatenate([[0.0], afm.hi]))
        assert st["success"]
        # IPOPT's tolerances (its constraint violation on the plane and an active range, and its
        # stopping tolerance) let its objective fall up to ~1e-6 relative below the exact optimum
        assert np.sum((afm.K @ r.u - qp) ** 2) <= np.sum((afm.K @ x - qp) ** 2) * (1 + 1e-5) + 1e-9
        assert "closed form" in r.status or "active-set QP" in r.status, r.status
        assert np.max(np.abs(x - r.u)) <= 1e-5
        closed += "closed form" in r.status
        active += "active-set QP" in r.status
    # both exact branches ran (from random states some plane minimisers leave a range); IPOPT
    # was built here by the test alone
    assert closed >= 5 and active >= 5, (closed, active)
    assert nlpsol_calls == ["afm_ipopt"]


def _fd_grad(f, u, h):
    g = np.zeros(u.size)
    for j in range(u.size):
        e = np.zeros(u.size)
        e[j] = h[j]
        g[j] = (f(u + e) - f(u - e)) / (2 * h[j])
    return g


@pytest.mark.parametrize("r_e,epistemic", [("noise_median", True), ("noise_mean", True),
                                            ("noise_quantile", True), ("noise_quantile", False)])
def test_first_order_optimality(afm, eafm, r_e, epistemic):
    opt_ = OptimalController(eafm, ControllerSettings(r_e=r_e, epistemic=epistemic, prefer_least_motion=False))
    rng = np.random.default_rng(4)
    for s, target in zip(_states(afm, 6, seed=5), rng.uniform(-20, 50, 6)):
        r = opt_.solve(target, s)
        assert r.success
        _assert_first_order_optimal(afm, eafm, s, r.u, lambda v: _r_e(eafm, s, v, r_e, epistemic=epistemic))


def _assert_first_order_optimal(afm, eafm, s, u, r_e_of):
    """KKT of eq. 4 at u from s: the gradient of ``1 - exp(-r_e_of(v))`` (finite differences of
    the NumPy reference) is a combination of the constraint's gradient and the active range
    bounds' normals, with non-negative multipliers on the bounds."""
    h = np.array([1e-5, 1e-7, 1e-7])

    def obj(v):  # eq. 4 from the NumPy reference prediction
        return float(-np.expm1(-r_e_of(v)))

    gJ = _fd_grad(obj, u, h)
    gc = _fd_grad(lambda v: float(eafm.predict(s, v).t_mean[0]), u, h)
    q = afm.K @ u
    rows, signs = [gc], [0.0]
    for j in range(afm.n_q):
        if q[j] - afm.lo[j] < 1e-6:
            rows.append(afm.K[j]); signs.append(1.0)   # lower bound: multiplier >= 0
        elif afm.hi[j] - q[j] < 1e-6:
            rows.append(-afm.K[j]); signs.append(1.0)  # upper bound
    A = np.array(rows).T
    coef, *_ = np.linalg.lstsq(A, gJ, rcond=None)
    resid = gJ - A @ coef
    assert np.linalg.norm(resid) <= 1e-4 * max(np.linalg.norm(gJ), 1e-12) + 1e-12
    for c, sg in zip(coef[1:], signs[1:]):
        assert c >= -1e-6 * np.linalg.norm(gJ)


def _r_e(eafm, s, u, r_e, kappa=1.645, epistemic=True):
    """r_e of eq. 4 written here from the NumPy prediction (objectives module docstring), plus
    f's posterior variance with ``epistemic`` (the default objective)."""
    p = eafm.predict(s, u)
    f_var = float(p.f_var[0]) if epistemic else 0.0
    if r_e == "noise_median":
        return float(np.exp(p.g_mean[0])) + f_var
    if r_e == "noise_quantile":
        return float(np.exp(p.g_mean[0] + kappa * np.sqrt(p.g_var[0]))) + f_var
    return float(np.exp(p.g_mean[0] + 0.5 * p.g_var[0])) + f_var


def test_reaches_the_dense_grid_optimum(afm, eafm, opt):
    # independent answer: a dense grid over the redundant set, Newton-projected
    rng = np.random.default_rng(6)
    for target in rng.uniform(-30, 60, 6):
        r = opt.solve(target)
        U, obj, _ = opt._seeds(afm.zero_state(), target, 81)
        assert r.objective <= np.min(obj) * (1 + 1e-6)


def test_unreachable_target_gives_interval(afm, eafm, opt):
    with pytest.raises(UnreachableTargetError, match=r"unreachable.*reaches \[-?[0-9.]+, [0-9.]+\] µm"):
        opt.solve(500.0)
    # the bound in full precision (the hand-derived Table I range, test_afm), not rounded
    lo, hi = afm.t_range()
    with pytest.raises(UnreachableTargetError, match=rf"AFM reaches \[{re.escape(repr(lo))}, {re.escape(repr(hi))}\]"):
        AFMController(afm).solve(-500.0)


def test_solver_built_once_per_model(afm, eafm, nlpsol_calls):
    # IPOPT alone: built at the first solve, reused after
    ctl = OptimalController(eafm, ControllerSettings(fast_path=False, prefer_least_motion=False))
    assert nlpsol_calls == [] and ctl.n_builds == 0
    for s, t in zip(_states(afm, 5, seed=7), (0.0, 10.0, 20.0, 30.0, -10.0)):
        ctl.solve(t, s)
    assert len(nlpsol_calls) == 1 and ctl.n_builds == 1


def test_ipopt_built_only_when_the_fast_path_needs_it(afm, eafm, nlpsol_calls):
    ctl = OptimalController(eafm)
    results = [ctl.solve(t, s) for s, t in zip(_states(afm, 5, seed=7), (0.0, 10.0, 20.0, 30.0, -10.0))]
    assert all(r.success for r in results)
    # the fast path converged everywhere here, so no IPOPT instance was made; at most one ever
    assert nlpsol_calls == [] and ctl.n_builds == 0
    ctl._ipopt()
    ctl._ipopt()
    assert len(nlpsol_calls) == 1 and ctl.n_builds == 1


def test_ipopt_failure_never_leaves_the_ranges(afm, eafm):
    ctl = OptimalController(eafm, ControllerSettings(max_iter=1, fast_path=False))  # IPOPT alone
    for target in (3.0, 25.0):
        r = ctl.solve(target)
        assert not r.success and "fallback to seed" in r.status
        _check_valid(r, afm, eafm, target)


def test_warm_started_sequence(afm, eafm, opt):
    res = opt.solve_sequence([0.0, 7.0, 14.0, 21.0, 28.0])
    for r, t in zip(res, (0.0, 7.0, 14.0, 21.0, 28.0)):
        assert r.success
        _check_valid(r, afm, eafm, t)
        assert r.objective <= opt.solve(t, r.state).objective * (1 + 1e-6)


def test_mean_baseline_moves_less_than_optimal(afm, eafm, opt):
    mean = EAFMMeanController(eafm)
    for t in (4.0, 18.0):
        a, b = mean.solve(t), opt.solve(t)
        assert a.objective <= np.sum((afm.K @ b.u) ** 2) + 1e-9


def test_bad_settings_and_state(eafm, opt):
    with pytest.raises(ConfigError, match="r_e"):
        ControllerSettings(r_e="variance")
    with pytest.raises(ConfigError, match="state"):
        opt.solve(1.0, np.zeros(3))


def test_compare_noise_probability(afm, eafm, opt):
    """P(g_a < g_b) from the joint posterior, recomputed here from eafm.g_joint and the normal
    CDF written out with math.erf; complementary in a and b; the planted quiet well's pose is
    credibly quieter than a pose outside it (their noise stds differ 10x: 0.02 vs 0.2 µm)."""
    from microctl.control.controller import compare_noise

    s = afm.zero_state()
    quiet = opt.solve(20.0, s)
    far = AFMController(afm).solve(20.0, s)
    c = compare_noise(eafm, s, quiet.u, far.u)
    mean, cov = eafm.g_joint(s, np.vstack([quiet.u, far.u]))
    sd = math.sqrt(cov[0, 0] + cov[1, 1] - 2 * cov[0, 1])
    p = 0.5 * (1 + math.erf(-(mean[0] - mean[1]) / sd / math.sqrt(2)))
    assert c.prob_quieter == pytest.approx(p, rel=1e-9)
    assert compare_noise(eafm, s, far.u, quiet.u).prob_quieter == pytest.approx(1 - p, abs=1e-12)
    assert c.credible and c.prob_quieter > 0.99


# --------------------------------------------------------------------------- a registered objective


@pytest.fixture
def second_moment():
    """A toy r_e summary, registered for the test only: ``exp(mu_g + s_g^2)``, the root of the
    second moment E[exp(2 g)] of the log-normal noise variance."""
    from microctl.control.noise_summaries import R_E_SUMMARIES, NoiseSummary

    class NoiseSecondMoment(NoiseSummary):
        name = "toy_second_moment"
        description = "exp(mu_g + s_g^2): the root of the noise variance's second moment"

        def log_r(self, g_mean, g_var, kappa, sqrt):
            return g_mean + g_var

    R_E_SUMMARIES.register(NoiseSecondMoment)
    yield NoiseSecondMoment.name
    R_E_SUMMARIES.unregister(NoiseSecondMoment.name)


def test_a_registered_r_e_summary_is_a_setting_and_is_solved(afm, eafm, second_moment):
    """One new class registered under a new name: the settings accept the name, the objective
    needs g's variance, and the controller's optimum meets the constraint, the ranges and the
    first-order conditions of eq. 4 with r_e = exp(mu_g + s_g^2) written here from the NumPy
    prediction; the sequence controller solves it too (each move on its target)."""
    from microctl.control.sequence import SequenceController

    settings = ControllerSettings(r_e=second_moment, epistemic=False, prefer_least_motion=False)
    assert settings.objective().needs == ("t_mean", "g_mean", "g_var")

    def r_e(s, v):
        p = eafm.predict(s, v)
        return float(np.exp(p.g_mean[0] + p.g_var[0]))

    opt_ = OptimalController(eafm, settings)
    rng = np.random.default_rng(8)
    for s, target in zip(_states(afm, 3, seed=9), rng.uniform(0, 40, 3)):
        r = opt_.solve(target, s)
        assert r.success, r.status
        _check_valid(r, afm, eafm, target)
        assert r.objective == pytest.approx(-math.expm1(-r_e(s, r.u)), rel=1e-10)
        _assert_first_order_optimal(afm, eafm, s, r.u, lambda v: r_e(s, v))
    plan = SequenceController(eafm, settings).plan([10.0, 20.0])
    assert plan.success
    for step, t, r in zip(plan.steps, (10.0, 20.0), plan.r_e_um2):
        _check_valid(step, afm, eafm, t)
        assert r == pytest.approx(r_e(step.state, step.u), rel=1e-10)


def test_an_unregistered_r_e_summary_is_refused():
    with pytest.raises(ConfigError, match="r_e: must be one of noise_quantile, noise_mean, noise_median"):
        ControllerSettings(r_e="toy_second_moment")


def test_result_states_the_bias_uncertainty_beside_the_scatter(afm, eafm, opt):
    """bias_std_um is the std of the GP's mean correction at the command (from the model's own
    predictive distribution, VHGPR.predict), and with the noise it makes the predictive std:
    predicted_std^2 = bias_std^2 + noise_std^2 (noise_std^2 = E[exp(g)] = exp(mu_g + s_g^2/2))."""
    s = _states(afm, 1, seed=4)[0]
    res = opt.solve(14.0, s)
    x = np.concatenate([s, res.u])[None, :]
    f_var = eafm.model.predict(x).f_var[0]
    assert res.bias_std_um == pytest.approx(np.sqrt(f_var), rel=1e-9)
    assert res.predicted_std_um**2 == pytest.approx(res.bias_std_um**2 + res.noise_std_um**2, rel=1e-9)
    assert res.to_dict()["bias_std_um"] == res.bias_std_um


def test_a_saturated_objective_still_finds_the_quiet_pose(afm, eafm, opt):
    """eq. 4's 1 - exp(-r) is 1 to machine precision at every pose once r exceeds ~37 (µm², the
    paper-scale rig's noise variances are tens), so a solver on it cannot tell the quietest pose
    from one far noisier. The controller minimises r itself (the same argmin). Planted: the
    quiet well of ``planted_model`` with r multiplied by 1e5 (r ~ 40 in the well, 4000 outside,
    so 1 - exp(-r) == 1.0 everywhere in double): the controller must land where it lands on the
    unscaled r (same pose to 0.05 µm of actuator command) and report the objective's value."""
    from dataclasses import dataclass

    from microctl.control.controller import EAFMController
    from microctl.control.objectives import NoiseVariance

    @dataclass(frozen=True)
    class Scaled(NoiseVariance):
        def r_mx(self, s, u, e, K):
            return 1e5 * super().r_mx(s, u, e, K)

        def r_np(self, eafm, s, U, *, seeding=False):
            return 1e5 * super().r_np(eafm, s, U, seeding=seeding)

    scaled = EAFMController(eafm, Scaled(), opt.settings, name="scaled")
    for target in (6.0, 14.0):
        a, b = opt.solve(target), scaled.solve(target)
        assert np.all(scaled.objective.evaluate(eafm, afm.zero_state(), b.u[None, :]) == 1.0)
        assert np.max(np.abs(a.q - b.q)) < 0.05, (a.q, b.q)
        assert b.predicted_std_um == pytest.approx(a.predicted_std_um, rel=0.01)
        assert b.objective == 1.0 and 0.0 < a.objective < 1.0
