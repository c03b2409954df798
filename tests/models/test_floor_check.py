"""microctl.models.floor_check: a noise floor that the mean correction passes through is flagged.

The degenerate fit is taken from a rig the package was not shaped on: scripts/rig_families.py's
``stick_slip`` rig 1 (stick-slip on actuators 1 and 2) with the covering design's 125 moves and
the sources the selection chose there until 2026-12-02, when the smaller p-value ranked the
significant candidates (``dq1:sat@1, dq2:down, dq1:sq, dq2:sq``; found by the rig bench's audit,
scripts/rig_audit.py: the trained floor std is below 1e-4 µm while that rig's gauge scatters by
tens of nm). They are named to the trainer (``noise_sources``), so the fit is that one; the
default selection now takes the two true sources there, and that model's floor is not flagged.
Whether f passes through a flagged reading is checked directly, not through the hat value: its
residual y - f is below a thousandth of the rig's gauge noise.
The clean rig 0 (gauge noise only, 200 moves), where every move is floor-only, is not flagged.
"""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path

import numpy as np
import pytest

from microctl.backends.collect import run_collect
from microctl.measurement.design import training_moves
from microctl.measurement.log import read_log
from microctl.models.afm import AnalyticForwardModel
from microctl.models.floor_check import HAT_LIMIT, FloorCheck, finding_of, interpolated_floor
from microctl.models.training import ResidualModelSettings, residual_dataset, train_residual_model

ROOT = Path(__file__).resolve().parents[2]


def _families():
    if str(ROOT / "scripts") not in sys.path:
        sys.path.insert(0, str(ROOT / "scripts"))
    import rig_families

    return rig_families


#: The sources the selection chose on stick_slip rig 1 at 125 moves before the exact gain ranked
#: the significant candidates (module docstring).
DEGENERATE_SOURCES = ("dq1:sat@1", "dq2:down", "dq1:sq", "dq2:sq")


def _trained(family: str, seed: int, n: int, sources: tuple[str, ...] | None = None):
    rig = _families().make_family_rig(family, seed)
    afm = AnalyticForwardModel(rig.config.stage)
    with tempfile.TemporaryDirectory() as tmp:
        log = Path(tmp) / "train.csv"
        with rig.stage(seed + 10_000) as stage:
            run_collect(stage, training_moves(afm, "covering", n, seed), log, quiet=True)
        data = residual_dataset(read_log(log, rig.config.stage, min_rows=5), afm)
    model = train_residual_model(data, afm, ResidualModelSettings(noise_sources=sources))
    return rig, model, data.inputs_for(model), data.y


def test_a_floor_the_mean_passes_through_is_flagged():
    rig, model, X, y = _trained("stick_slip", 1, 125, DEGENERATE_SOURCES)
    check = interpolated_floor(model, X)
    gauge = rig.config.backend.simulated.gauge_noise_std_um
    assert check.degenerate and check.floor_std_um < 0.01 * gauge, check
    assert all(h > HAT_LIMIT for h in check.hat)
    # f passes through each flagged reading: the residual is far below the gauge's scatter
    f = model.predict(X[list(check.rows)]).f_mean
    assert np.all(np.abs(y[list(check.rows)] - f) < 1e-3 * gauge), (y[list(check.rows)] - f, gauge)
    assert "not an estimate" in check.describe()


def test_the_default_selection_takes_the_true_sources_there_and_its_floor_is_sound():
    """On the same rig the default selection takes stick-slip on actuators 1 and 2 in the true
    shape (dq^2) and nothing else, and its floor is the gauge's (within the chi-square spread of
    the few floor rows and f's share: a factor 2)."""
    rig, model, X, y = _trained("stick_slip", 1, 125)
    assert sorted(model.info["noise_selection"]["selected"]) == ["dq1:sq", "dq2:sq"]
    check = interpolated_floor(model, X)
    gauge = rig.config.backend.simulated.gauge_noise_std_um
    assert not check.degenerate and 0.5 * gauge < check.floor_std_um < 2.0 * gauge, check


def test_a_sound_floor_is_not_flagged():
    rig, model, X, y = _trained("clean", 0, 200)
    check = interpolated_floor(model, X)
    gauge = rig.config.backend.simulated.gauge_noise_std_um
    assert not check.degenerate and check.floor_rows == len(y)
    # the floor is the gauge's, within the chi-square spread of 200 readings (and f's share)
    assert check.floor_std_um == pytest.approx(gauge, rel=0.25)


def test_train_warns_and_keeps_the_check_with_the_model(tmp_path, capsys, monkeypatch, planted_log, table1_path):
    """``microctl train`` prints the warning with its result and stores the flagged rows in the
    model's info (a degenerate check stands in for the fit's)."""
    import microctl.models.floor_check as floor_check
    from microctl.cli import main
    from microctl.gp.fitted import FittedVHGPR

    monkeypatch.setattr(floor_check, "interpolated_floor", lambda model, X: FloorCheck((3, 7), (0.99, 1.0), 1e-5, 4))
    out = tmp_path / "m.npz"
    rc = main(["train", str(planted_log), "--config", str(table1_path), "-o", str(out), "--restarts", "1", "--quiet"])
    cap = capsys.readouterr()
    assert rc == 0 and "train: warning: the mean correction passes through 2 of the 4" in cap.out, cap.out
    assert FittedVHGPR.load(out).info["floor_check"]["rows"] == [3, 7]


def test_api_train_warns_and_keeps_the_check(monkeypatch, planted_log, table1_path):
    """``api.train`` issues the same warning as a RuntimeWarning and keeps the rows in the info."""
    import microctl.models.floor_check as floor_check
    from microctl import api

    monkeypatch.setattr(floor_check, "interpolated_floor", lambda model, X: FloorCheck((5,), (0.95,), 2e-5, 3))
    with pytest.warns(RuntimeWarning, match="passes through 1 of the 3"):
        model = api.train(planted_log, api.load_stage(table1_path), restarts=1)
    assert model.info["floor_check"]["rows"] == [5]


def test_a_floor_no_reading_bounds_is_flagged():
    """On a hinge that slips with every tilt (``hinge_slip`` rig 1307, 125 covering moves, the default
    selection: ``drx:sq`` and ``dry:sq``) every training move tilts the platform, so no reading is
    floor-only; the fit drives c_0 to mu0's lower bound, and the floor std is far below the rig's gauge
    noise (the scatter the model then predicts at a pure lift). Found by the rig bench (seed 1300):
    a predicted noise of 0.004 µm at a pure lift where the rig scatters by 0.057 µm. No reading is
    interpolated here, so the hat test alone passed this floor."""
    rig, model, X, y = _trained("hinge_slip", 1307, 125)
    assert sorted(model.info["noise_selection"]["selected"]) == ["drx:sq", "dry:sq"]
    check = interpolated_floor(model, X)
    gauge = rig.config.backend.simulated.gauge_noise_std_um
    assert check.rows == () and check.floor_rows == 0 and check.at_bound, check
    assert check.unsupported and check.degenerate and check.floor_std_um < 0.01 * gauge, check
    assert "no training reading is floor-only" in check.describe() and "not an estimate" in check.describe()


def test_what_the_check_reports():
    """:class:`FloorCheck`'s verdict and wording for each finding (hand-made checks)."""
    sound = FloorCheck((), (), 0.05, 40)
    assert not sound.degenerate and not sound.unsupported
    interpolated = FloorCheck((3, 7), (0.97, 0.91), 1e-5, 4)
    assert interpolated.degenerate and not interpolated.unsupported
    assert interpolated.finding().startswith("the mean correction passes through 2 of the 4")
    none_floor_only = FloorCheck((), (), 1e-5, 0)
    assert none_floor_only.degenerate and none_floor_only.finding().startswith("no training reading is floor-only")
    bounded = FloorCheck((), (), 1e-5, 3, at_bound=True)
    assert bounded.degenerate and "sits at its lower bound (the 3 floor-only" in bounded.finding()
    info = bounded.as_info()
    assert info == {"rows": [], "hat": [], "floor_std_um": 1e-5, "floor_rows": 3, "at_bound": True,
                    "finding": bounded.finding()}


def test_finding_of_kept_json_reads_old_and_new_checks():
    """:func:`finding_of` gives a kept check's own finding, and for JSON written before
    ``as_info`` kept one (only ``rows``: readings the mean correction passes through) the same
    kind of sentence, so the report and the rig bench word an old results file alike."""
    for check in (FloorCheck((3, 7), (0.97, 0.91), 1e-5, 4), FloorCheck((), (), 1e-5, 0, at_bound=True)):
        assert finding_of(check.as_info()) == check.finding()
    old = {"rows": [16, 67], "hat": [1.0, 1.0], "floor_std_um": 5.7e-5}
    assert finding_of(old) == ("the mean correction passes through 2 training reading(s) that the noise model "
                               "gives only its floor")
