"""The rig families' truth (scripts/rig_families.py) against Monte Carlo of their own simulator.

The exact moments (``FamilyStage.moments``: the noise-free reading and the affine propagation
of the actuator scatter) must agree with the readings of many independent stages making the
same two moves, and the Monte Carlo fallback (``mc_moments``) with both.
"""

from __future__ import annotations

import importlib
import sys
from pathlib import Path

import numpy as np
import pytest

_SCRIPTS = Path(__file__).resolve().parents[1] / "scripts"


def _families():
    if str(_SCRIPTS) not in sys.path:
        sys.path.insert(0, str(_SCRIPTS))
    return importlib.import_module("rig_families")


rf = _families()
N_DRAWS = 800


def _two_moves(rig):
    """A first move to 18 µm and a second one down to 6 µm (turns actuators round), from the
    redundant set's grid."""
    from microctl.control.controller import RedundantSet
    from microctl.models.afm import AnalyticForwardModel

    afm = AnalyticForwardModel(rig.config.stage)
    rs = RedundantSet(afm)
    U1, _ = rs.grid(18.0, 5)
    U2, _ = rs.grid(6.0, 5)

    def ok(U):
        q = U @ afm.K.T
        return U[np.all((q >= 0.0) & (q <= 32.0), axis=1)]

    U1, U2 = ok(U1), ok(U2)
    return U1[len(U1) // 3], U2[(2 * len(U2)) // 3]


@pytest.mark.parametrize("family,seed", [("clean", 1), ("stick_slip", 2), ("stroke_patch", 3), ("light_ball", 2),
                                         ("settling", 4), ("reversal", 5), ("stiction", 6), ("extension", 7),
                                         ("mix", 8), ("gauge_tilt", 9), ("hinge_slip", 10)])
def test_exact_moments_match_monte_carlo_of_the_simulator(family, seed):
    rig = rf.make_family_rig(family, seed)
    u1, u2 = _two_moves(rig)
    readings = np.empty(N_DRAWS)
    for k in range(N_DRAWS):
        st = rig.stage(1000 + k)
        st.move(u1)
        if k == 0:  # the truth from the state (and direction history) the move starts at
            s, st0 = st.state, rig.stage(1000)
            st0.move(u1)
        readings[k] = st.move(u2).t_um
    mean, var, exact = st0.moments(s, u2[None, :])
    assert exact[0]
    sd = float(np.sqrt(var[0]))
    se_mean = sd / np.sqrt(N_DRAWS)
    assert abs(readings.mean() - mean[0]) < 5.0 * se_mean
    # std of a sample std ~ sd / sqrt(2 N): 5 of them
    assert abs(readings.std(ddof=1) / sd - 1.0) < 5.0 / np.sqrt(2 * N_DRAWS)
    mc_mean, mc_var = st0.mc_moments(s, u2[None, :], n_draws=20000, seed=3)
    assert abs(np.sqrt(mc_var[0]) / sd - 1.0) < 5.0 / np.sqrt(2 * 20000)
    assert abs(mc_mean[0] - mean[0]) < 5.0 * sd / np.sqrt(20000)


def test_family_noise_structures_do_what_they_say():
    """Each structure's actuator scatter responds to what its docstring names, and only to it."""
    q_prev = np.array([[10.0, 10.0, 10.0, 10.0]])
    force = np.full((1, 4), 100.0)
    no_rev = np.zeros((1, 4), dtype=bool)
    ss = {"kind": "stick_slip", "act": [0], "c": [0.05]}
    assert rf._term_std(ss, q_prev, q_prev + 4.0, no_rev, force, 100.0)[0, 0] == pytest.approx(0.2)
    assert rf._term_std(ss, q_prev, q_prev, no_rev, force, 100.0)[0, 0] == 0.0
    patch = {"kind": "stroke_patch", "act": [1], "lo": 12.0, "hi": 18.0, "edge": 0.5, "a": 0.2}
    inside = rf._term_std(patch, q_prev, np.array([[0.0, 15.0, 0.0, 0.0]]), no_rev, force, 100.0)
    outside = rf._term_std(patch, q_prev, np.array([[0.0, 25.0, 0.0, 0.0]]), no_rev, force, 100.0)
    assert inside[0, 1] == pytest.approx(0.2, rel=1e-3) and outside[0, 1] < 1e-6
    rev = {"kind": "reversal", "act": [2], "r": [0.2], "scale": 0.5}
    turned = np.array([[False, False, True, False]])
    assert rf._term_std(rev, q_prev, q_prev - 5.0, turned, force, 100.0)[0, 2] == pytest.approx(0.2, rel=1e-3)
    assert rf._term_std(rev, q_prev, q_prev + 5.0, no_rev, force, 100.0)[0, 2] == 0.0
    light = {"kind": "light_ball", "act": [0, 1, 2, 3], "s0": 0.02, "gamma": 1.0, "cap": 0.5}
    f = np.array([[100.0, 50.0, 25.0, 0.0]])
    sd = rf._term_std(light, q_prev, q_prev, no_rev, f, 100.0)[0]
    assert sd[:3] == pytest.approx([0.02, 0.04, 0.08]) and sd[3] == 0.5


def test_a_held_actuator_keeps_its_direction_through_round_off():
    """A step of floating-point round-off (1e-12 µm either way) holds the actuator: it keeps its
    direction and does not turn round (so the next step up is no reversal); a step of 1e-3 µm
    down does turn it round, and an exact 0 keeps it, as the family's docstring says."""
    st = rf.make_family_rig("reversal", 0).stage(1)
    dq = np.array([[-1e-12, 1e-12, 0.0, -1e-3], [2.0, -2.0, 3.0, 5.0]])
    last = np.array([[1.0, -1.0, -1.0, 1.0], [1.0, 1.0, 1.0, 1.0]])
    new, turned = st._directions(dq, last)
    np.testing.assert_array_equal(new, [[1.0, -1.0, -1.0, -1.0], [1.0, -1.0, 1.0, 1.0]])
    np.testing.assert_array_equal(turned, [[False, False, False, True], [False, True, False, False]])
    assert rf.HELD_UM == 1e-6


def test_reading_level_structures_do_what_they_say():
    """The tilted gauge's variance follows the pose's tilt only; the hinge's slip follows the tilt
    change of the move only (a pure lift adds nothing), each by its docstring's formula."""
    tilt = {"kind": "gauge_tilt", "act": [], "a": 0.2, "k": 1.5, "theta_max": 2.0}
    p = np.array([[5.0, 0.0, 0.0], [5.0, 1.2, 1.6], [9.0, 1.2, 1.6]])  # tilt 0, 2, 2 mrad
    assert rf._tilt_var([tilt], p) == pytest.approx([0.0, 0.04, 0.04])
    hinge = {"kind": "hinge_slip", "act": [], "c": [0.05, 0.02]}
    p_prev = np.array([[1.0, 0.5, -0.5]])
    moves = np.array([[7.0, 0.5, -0.5], [1.0, 1.5, -0.5], [1.0, 0.5, 1.5]])
    assert rf._slip_sd([hinge], np.repeat(p_prev, 3, axis=0), moves) == pytest.approx(
        np.array([[0.0, 0.0], [0.05, 0.0], [0.0, 0.04]]))
    # on a rig: a pure lift (equal steps on every actuator) is quiet, the same travel tilted is not
    rig = rf.make_family_rig("hinge_slip", 3)
    st = rig.stage(1)
    s0 = st.state
    from microctl.models.afm import AnalyticForwardModel

    afm = AnalyticForwardModel(rig.config.stage)
    lift, tilted = np.linalg.lstsq(afm.K, np.full(4, 8.0), rcond=None)[0], np.linalg.lstsq(
        afm.K, np.array([16.0, 8.0, 0.0, 8.0]), rcond=None)[0]
    v_lift, v_tilt = st.true_var(s0, lift), st.true_var(s0, tilted)
    assert v_tilt > 4.0 * v_lift


def test_rigs_are_seeded_and_keep_every_ball_loaded():
    a, b = rf.make_family_rig("light_ball", 4), rf.make_family_rig("light_ball", 4)
    assert a.describe() == b.describe()
    assert rf._all_balls_loaded(a.config)
    assert rf.make_family_rig("clean", 0).terms == [] and rf.make_family_rig("clean", 0).driver_std_um == 0.0


def test_true_sources_name_dictionary_quantities_of_the_terms():
    """The ``told`` reference's names (FamilyRig.true_sources) are quantities of the package's noise
    dictionary for the rig's stage, one per physical carrier of the drawn terms."""
    from microctl.models.afm import AnalyticForwardModel
    from microctl.models.noise_dictionary import candidate_features, quantity

    want = {"clean": lambda t: [], "stick_slip": lambda t: [f"dq{i + 1}" for i in t["act"]],
            "stroke_patch": lambda t: [f"q{i + 1}" for i in t["act"]], "light_ball": lambda t: [f"f{t['ball'] + 1}"],
            "gauge_tilt": lambda t: ["rx", "ry"], "hinge_slip": lambda t: ["drx", "dry"]}
    for family, expect in want.items():
        rig = rf.make_family_rig(family, 3)
        names = rig.true_sources()
        assert list(names) == [q for t in rig.terms for q in expect(t)], family
        quantities = {quantity(nm) for nm in candidate_features(AnalyticForwardModel(rig.config.stage), context=True).names}
        assert set(names) <= quantities, family
    mix = rf.make_family_rig("mix", 5)
    assert len(mix.true_sources()) >= 2 and mix.true_sources()[0] == f"dq{mix.terms[0]['act'][0] + 1}"
