"""The corrupt-reading screen of training (microctl.models.outlier_screen).

Data: heteroscedastic residuals drawn here with NumPy from a stated variance model, and a
measurement log of the independent stage generator (tests/independent_stage.py: its own contact
physics, stick-slip and log writer). Seeds fixed; tolerances stated with each assertion.
"""

from __future__ import annotations

import contextlib
import io
from dataclasses import replace

import independent_stage as ind
import numpy as np
import pytest
from conftest import CONFIGS

from microctl.models.noise_dictionary import fit_variance_with, variance_design
from microctl.models.outlier_screen import (
    MIN_NU,
    SCREEN_ALPHA,
    bonferroni_bound,
    deletion_residuals,
    max_screened,
    screen_rows,
    suspect_rows,
    tail_bound,
)


def _hetero(seed: int, n: int = 200) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Residuals with variance 0.01 + 0.04 phi, phi = step^2 for a uniform step in [0, 4] µm
    (stick-slip of 0.2 µm per µm on a 0.1 µm floor); returns (r, Phi (n, 1), variance)."""
    rng = np.random.default_rng(seed)
    step = rng.uniform(0.0, 4.0, n)
    phi = step**2
    v = 0.01 + 0.04 * phi
    return np.sqrt(v) * rng.standard_normal(n), phi[:, None], v


def test_bound_is_the_two_sided_bonferroni_quantile():
    """Independent of the module's NormalDist: scipy's normal quantile, 1e-12."""
    from scipy import stats

    for n in (10, 125, 2000):
        assert bonferroni_bound(n, 0.01) == pytest.approx(stats.norm.isf(0.01 / (2 * n)), abs=1e-12)


def test_tail_bound_reads_the_tails_of_the_bulk_and_not_the_corrupt_rows():
    """Large seeded samples (the quantile ratio's sampling error is then below 1 %): Gaussian
    residuals give the Gaussian bound within 3 %; unit-variance Student t with 7 degrees of
    freedom give nu in [6, 8.5] and the t bound at that nu (scipy, 1e-9); one row in 200 that
    is 100 standard deviations off moves nu by less than 1.5 (more would move it further, so
    training leaves the rows the screen suspects out of the estimate); a ratio beyond t_5's
    gives MIN_NU."""
    from scipy import stats

    rng = np.random.default_rng(8)
    b, nu = tail_bound(rng.standard_normal(200_000), 285)
    assert b == pytest.approx(bonferroni_bound(285), rel=0.03) and (nu > 40 or nu == np.inf)
    t7 = rng.standard_t(7, 200_000) * np.sqrt(5 / 7)
    b, nu = tail_bound(t7, 285)
    assert 6 <= nu <= 8.5 and b == pytest.approx(stats.t.isf(1e-3 / 570, nu) * np.sqrt((nu - 2) / nu), rel=1e-9)
    bad = t7.copy()
    bad[::200] = 100.0
    assert abs(tail_bound(bad, 285)[1] - nu) < 1.5
    assert tail_bound(rng.standard_cauchy(10_000), 285)[1] == MIN_NU


def test_deletion_residual_of_the_floor_alone_is_the_leave_one_out_rms():
    """With no source (the floor alone) the maximum-likelihood variance without row i is the mean
    of the other squared residuals, so z_(-i) = r_i / rms_(j != i) r_j (closed form; 1e-4 relative:
    the L-BFGS-B fit's tolerance)."""
    r = np.random.default_rng(3).standard_normal(60)
    rows = np.array([0, 17, 59])
    z = deletion_residuals(r, np.zeros((60, 0)), rows)
    expect = [r[i] / np.sqrt(np.mean(np.delete(r, i) ** 2)) for i in rows]
    np.testing.assert_allclose(z, expect, rtol=1e-4)


def test_a_corrupt_reading_hidden_by_a_source_that_peaks_at_it_is_found():
    """Masking: a source that is large at one row only (a bump) lets the fit on every row raise
    the variance there, so the corrupt row's ordinary standardised residual falls under the bound;
    refitted without the row, the source has nothing to explain and the row stands out. The
    screen sets aside exactly that row. Fails if suspects were judged by the fit on every row."""
    r, Phi, _ = _hetero(0)
    bump = np.zeros(len(r))
    bump[40] = 1.0
    Phi2 = np.hstack([Phi, bump[:, None]])
    r = r.copy()
    r[40] += 5.0  # >= 6 standard deviations of that row (its std is at most sqrt(0.01 + 0.04 * 16) = 0.81)
    _, c = fit_variance_with(r**2, Phi2, None, None)
    v = variance_design(Phi2, None, None) @ c
    bound = bonferroni_bound(len(r))
    assert abs(r[40]) / np.sqrt(v[40]) < bound  # masked under the fit that includes it
    found = screen_rows(r, Phi2)
    assert found.rows == (40,) and abs(found.z[0]) > bound and not found.withheld
    # its neighbours (in the step) are as quiet as the model says, so the local check keeps it
    step = np.sqrt(Phi[:, 0])
    assert screen_rows(r, Phi2, local_inputs=step[:, None]).rows == (40,)


def test_suspects_are_the_largest_standardised_and_the_largest_residuals():
    """Step 1: a row whose variance the fit raised to its residual (masked: ordinary r^2 / v) is
    still a suspect by |r|; a quiet row with a small residual that is large against its small
    variance is one by r^2 / v. Hand-made residuals, variances and the expected set."""
    r = np.array([0.1, -0.2, 5.0, 0.05, 0.3, -0.1])
    v = np.array([1.0, 1.0, 25.0, 1e-4, 1.0, 1.0])  # row 2 masked (z = 1), row 3 z = 5
    assert suspect_rows(r, v, top=1).tolist() == [2, 3]
    assert suspect_rows(r, v, top=2).tolist() == [2, 3, 4]  # r^2/v: rows 3, 2; |r|: rows 2, 4


def test_scatter_the_sources_miss_is_judged_against_the_neighbouring_moves():
    """Misspecified sources: the data have a region (position > 0.8) where the std is 8x the
    floor, and the variance model has the floor only. A legitimate residual of 3 stds of that
    region (2.4 µm) is far beyond the Gaussian bound (4.7) under the floor fitted without it
    (v ~ 0.14 µm², z ~ 6.3); judged against its 20 nearest moves (all in the region), which carry
    the same scatter, z falls to 3.8 (the median of 20 neighbours estimates the region's
    variance ratio at 0.6 of the truth on this seed). The screen's bound follows the tails the
    rows show under the floor (a mixture of two scales: much heavier than a Gaussian), so it sets
    nothing aside. The local check never lowers a variance, so on data the model describes every
    deletion residual keeps its size or shrinks (checked at the 10 largest rows)."""
    rng = np.random.default_rng(2)
    pos = rng.uniform(0.0, 1.0, 400)
    sd = np.where(pos > 0.8, 0.8, 0.1)
    r = sd * rng.standard_normal(400)
    i = int(np.argmax(pos))
    r[i] = 3.0 * 0.8
    none = np.zeros((400, 0))
    gauss = bonferroni_bound(400)
    assert abs(deletion_residuals(r, none, [i])[0]) > gauss
    assert abs(deletion_residuals(r, none, [i], local_inputs=pos[:, None])[0]) < gauss
    found = screen_rows(r, none, local_inputs=pos[:, None])
    assert found.rows == () and found.bound > 2 * gauss and found.nu == MIN_NU
    r2, Phi, _ = _hetero(4)
    rows = np.argsort(-np.abs(r2))[:10]
    plain = deletion_residuals(r2, Phi, rows)
    local = deletion_residuals(r2, Phi, rows, local_inputs=np.sqrt(Phi))
    assert np.all(np.abs(local) <= np.abs(plain) + 1e-12) and np.any(np.abs(local) < np.abs(plain))


def test_no_row_set_aside_on_data_the_model_describes():
    """100 seeded data sets drawn from the variance model itself (n = 200): each sets a row aside
    with probability at most about SCREEN_ALPHA (1e-3; the tails' bound is never below the
    Gaussian one), so more than 2 of 100 would happen with probability below 2e-4 if the screen
    kept its level."""
    hits = sum(bool(screen_rows(*_hetero(seed)[:2]).rows) for seed in range(100))
    assert hits <= 2, hits
    assert SCREEN_ALPHA == pytest.approx(1e-3)


def test_more_exceedances_than_the_cap_are_scatter_and_no_row_is_set_aside():
    """300 residuals of 0.1 µm std of which 10 are 3 µm off: each of the 10 is beyond the bound
    under the floor fitted without it (the other nine keep the variance near 0.28 µm², so
    z_(-i) ~ 5.7 against a bound of 4.65), more than the cap (2 % of 300 = 6), so the screen
    withholds them all (scatter with heavier tails than the model's, not a few corrupt readings)."""
    r = np.random.default_rng(5).standard_normal(300) * 0.1
    r[::30] = 3.0 * np.sign(r[::30])
    found = screen_rows(r, np.zeros((300, 0)), top=20)
    assert found.withheld and found.rows == () and found.exceeding == 10 > max_screened(300)


@pytest.mark.slow
def test_train_sets_aside_a_corrupt_reading_of_an_independent_stage_and_keeps_its_noise_model(tmp_path):
    """Hidden effect: a stage of the independent generator with stick-slip on PZT 4 (0.05 µm per
    µm moved; the package is not told), 150 random moves, and one reading 5 µm off (row 75, the
    log's line 77) that ``microctl train`` is not told about either. Trained on the corrupt log,
    the model sets aside exactly that row, selects the same noise sources as on the clean log, and
    ``train`` names the line in its output; the log file is unchanged."""
    from microctl.cli import main
    from microctl.measurement.log import read_log
    from microctl.models.afm import AnalyticForwardModel
    from microctl.models.eafm import load_residual_model
    from microctl.models.training import residual_dataset, train_residual_model
    from microctl.stage.config import load_stage_config

    path = CONFIGS / "stage" / "table1.yaml"
    geo = ind.load_geometry(path)
    rng = np.random.default_rng(11)
    truth = ind.random_truth(geo, rng, gauge_um=0.02, physics=ind.load_physics(path))
    truth = replace(truth, friction_per_um=np.array([0.0, 0.0, 0.0, 0.05]))
    run = ind.run(truth, ind.random_moves(geo, 150, rng), rng)
    cfg = load_stage_config(path)
    afm = AnalyticForwardModel(cfg.stage)
    run.write_log(tmp_path / "clean.csv")
    clean = train_residual_model(residual_dataset(read_log(tmp_path / "clean.csv", cfg.stage), afm), afm)
    assert clean.info["noise_selection"]["screened"]["rows"] == [], clean.info["noise_selection"]["screened"]
    run.corrupted([(75, "t", float(run.t[75] + 5.0))]).write_log(tmp_path / "corrupt.csv")
    before = (tmp_path / "corrupt.csv").read_bytes()
    out = tmp_path / "m.npz"
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        assert main(["train", str(tmp_path / "corrupt.csv"), "--config", str(path), "-o", str(out)]) == 0
    sel = load_residual_model(out).info["noise_selection"]
    assert sel["screened"]["rows"] == [75], sel["screened"]
    assert sel["selected"] == clean.info["noise_selection"]["selected"] and sel["selected"], sel["selected"]
    assert "set aside 1 reading(s)" in buf.getvalue() and "line 77 (seq 75," in buf.getvalue(), buf.getvalue()
    assert (tmp_path / "corrupt.csv").read_bytes() == before


def test_train_describes_what_the_screen_did_by_log_line_and_seq():
    """The line ``microctl train`` prints: nothing when no row was set aside or withheld; each row
    by its line in the file (header = line 1, so row i is line i + 2) and its seq; the withheld
    case says none was set aside."""
    from microctl.models.outlier_screen import describe_screen

    seq = np.array([10, 11, 12, 13])
    assert describe_screen(None, seq) == ""
    assert describe_screen({"rows": [], "z": [], "bound": 4.5, "alpha": 1e-3, "withheld": 0}, seq) == ""
    line = describe_screen({"rows": [2], "z": [-7.25], "bound": 4.5, "alpha": 1e-3, "withheld": 0}, seq)
    assert "line 4 (seq 12, z = -7.2)" in line and "|z| = 4.50" in line and "log is unchanged" in line
    line = describe_screen({"rows": [], "z": [], "bound": 4.5, "alpha": 1e-3, "withheld": 9}, seq)
    assert line.startswith("note: 9 readings") and "none was set aside" in line


def _family_log_selection(tmp_path, family: str, seed: int, moves: int) -> dict:
    """The default training's noise selection on an unaltered log of rig ``seed`` of ``family``
    (scripts/rig_families.py): ``moves`` covering moves collected as scripts/bench_screen.py and
    scripts/bench_rigs.py collect them (design seed ``seed``, stage seed ``seed + 10000``)."""
    from script_loader import load_script

    from microctl.backends.collect import run_collect
    from microctl.measurement.design import training_moves
    from microctl.measurement.log import read_log
    from microctl.models.afm import AnalyticForwardModel
    from microctl.models.training import residual_dataset, train_residual_model

    rig = load_script("rig_families").make_family_rig(family, seed)
    afm = AnalyticForwardModel(rig.config.stage)
    with rig.stage(seed + 10_000) as st:
        run_collect(st, training_moves(afm, "covering", moves, seed), tmp_path / "log.csv", quiet=True)
    model = train_residual_model(residual_dataset(read_log(tmp_path / "log.csv", rig.config.stage, min_rows=5), afm), afm)
    return model.info["noise_selection"]


@pytest.mark.slow
def test_a_true_source_that_rests_on_the_largest_readings_keeps_them(tmp_path):
    """Hidden effect: rig 1 of the ``gauge_tilt`` family of scripts/rig_families.py (a reading
    scatter growing with the platform's tilt, the package not told), 200 covering moves collected
    as ``scripts/bench_screen.py`` collects them, nothing corrupted. The tilt's scatter rests on
    the few largest residuals (selected with every row, the true ``rx:sq`` brought 10.5 nats; left
    out all together, no source entered and row 61 was set aside, z 5.6, at 41ef8ec). Judged by
    the sources selected without each suspect alone, no reading is set aside and a tilt source is
    selected (``rx:sq`` or another shape or coordinate of the tilt: its quantity is the pose's
    tilt)."""
    sel = _family_log_selection(tmp_path, "gauge_tilt", 1, 200)
    assert sel["screened"]["rows"] == [], sel["screened"]
    assert any(name.startswith(("rx:", "ry:", "tilt")) for name in sel["selected"]), sel["selected"]


@pytest.mark.slow
@pytest.mark.xfail(strict=True, reason="known defect: a legitimate reading that carries most of a true source's "
                                       "evidence is judged under the sources selected without it (test docstring)")
def test_a_reading_that_carries_a_true_stroke_patch_is_kept(tmp_path):
    """Hidden effect: rig 1 of the ``mix`` family (stick-slip on PZT 1 and a rough patch of PZT 2's
    stroke; the package not told), 125 covering moves, nothing corrupted. Before 41ef8ec the
    selection took both true sources (``dq1:sq``, ``q2:bump@22.4``) and kept every row. Since, each
    suspect is judged by the sources selected without it: without row 81 the patch does not
    enter, row 81's deletion z is -6.24 against a bound of 4.46, it is set aside and the true
    ``q2`` source is lost. Which of "one corrupt reading" and "a source resting on one reading"
    the data support is a comparison of the two models' evidence, which the screen does not make
    yet."""
    sel = _family_log_selection(tmp_path, "mix", 1, 125)
    assert sel["screened"]["rows"] == [], sel["screened"]
    assert any(name.startswith("q2:") for name in sel["selected"]), sel["selected"]
