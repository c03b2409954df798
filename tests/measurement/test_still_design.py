"""The ``covering_still`` training design: still moves, and the noise floor they identify."""

from pathlib import Path

import numpy as np

from microctl.measurement.design import STILL_EVERY, training_moves
from microctl.models.afm import AnalyticForwardModel
from microctl.models.noise_dictionary import candidate_features, fit_variance_with, select_features
from microctl.stage.config import load_stage_config

ROOT = Path(__file__).resolve().parents[2]


def _afm() -> AnalyticForwardModel:
    return AnalyticForwardModel(load_stage_config(str(ROOT / "configs/stage/table1.yaml")).stage)


def _inputs(afm: AnalyticForwardModel, U: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """x = [t_prev; q_prev; u] (eq. 3) of a move sequence from the zero state (t_prev is not read
    here), and each move's step of the pose, u - u_prev; shapes (n, n_s + n_p) and (n, n_p)."""
    U_prev = np.vstack([np.zeros(afm.n_p), U[:-1]])
    return np.hstack([np.zeros((len(U), 1)), U_prev @ afm.K.T, U]), U - U_prev


def test_still_moves_repeat_the_previous_command_and_the_rest_is_the_covering_design():
    """Moves 20, 40, ... (1-based) are the previous command again, so every step candidate of the
    noise dictionary (the actuators' and the platform's) takes there its value at a zero step, the
    smallest over the design (0 but for the smooth breakaway steps, small there); every other
    move is the covering design's with the same seed."""
    afm = _afm()
    n = 130
    u = training_moves(afm, "covering_still", n, seed=3)
    cov = training_moves(afm, "covering", n, seed=3)
    still = np.arange(STILL_EVERY - 1, n, STILL_EVERY)
    assert still.tolist() == [19, 39, 59, 79, 99, 119]
    np.testing.assert_array_equal(u[still], u[still - 1])
    other = np.setdiff1d(np.arange(n), still)
    np.testing.assert_array_equal(u[other], cov[other])
    assert afm.workspace.contains(u).all()
    X, _ = _inputs(afm, u)
    cands = candidate_features(afm)
    steps = [j for j, nm in enumerate(cands.names) if nm.startswith("d")]  # dq<i>:*, d<c>:sq
    assert {"dq1:sq", "dq4:sat", "dz:sq", "drx:sq"} <= {cands.names[j] for j in steps}
    vals = cands.values(X)[:, steps]
    assert np.all(vals[still] <= vals.min(axis=0) + 1e-12)
    assert np.max(vals[still]) < 0.05 and np.median(vals[still]) < 1e-12
    # the move after a still one moves: a still move is never followed by another
    assert np.all(np.abs(np.diff(u, axis=0))[still].max(axis=1) > 0)


def test_still_moves_identify_a_floor_the_step_sources_would_hide():
    """A hidden effect: residuals whose variance is a 0.03 µm floor plus a hinge's slip, 0.3 µm per
    mrad of the platform's *actual* rotation, which mixes in 0.03 mrad per µm of lift (a hinge axis
    off the CAD's: the dictionary's drx and dry are the nominal rotations, so no candidate has the
    true shape). On 125 moves the selection is run and the floor fitted with the sources it chose.
    With the still moves the floor's std is within a factor 2 of the planted one (its variance
    within 4x: beyond that the repeatability predicted at a quiet pose fails the calibration bar
    [0.67, 1.5] whatever else is right) on >= 19 of 20 seeds; the covering design alone does so on
    18 of these 20 (the floor traded for the step sources), so the bar can fail."""
    afm = _afm()
    n, floor, c, mix = 125, 0.03, 0.3, 0.03
    ok = 0
    for seed in range(20):
        U = training_moves(afm, "covering_still", n, seed)
        X, du = _inputs(afm, U)
        v = floor**2 + (c * (du[:, 1] + mix * du[:, 0])) ** 2 + (c * (du[:, 2] - mix * du[:, 0])) ** 2
        r = np.sqrt(v) * np.random.default_rng(1000 + seed).standard_normal(n)
        cands = candidate_features(afm).rescaled(X)
        Phi = cands.values(X)
        sel = select_features(r, Phi, cands.names)
        _, coef = fit_variance_with(r**2, Phi[:, list(sel.indices)], None, None)
        ok += 0.5 <= np.sqrt(coef[0]) / floor <= 2.0
    assert ok >= 19, ok
