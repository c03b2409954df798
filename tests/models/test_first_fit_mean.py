"""Known defect, kept as a strict expected failure: a smooth mean that the affine trend cannot
follow, on a small log, is taken for scatter when ``se: auto`` drops f's SE part.

Data: the hand-written planted log (tests/conftest.py ``planted_log``): 40 moves of the Table I
stage, the AFM's reading plus a smooth residual 0.3 sin(z/8) + 0.2 rx the package is not told
about, and uniform 0.05 µm noise, so no noise source should be selected. With the defaults the
first fit (the residual the selection reads) keeps f's SE part only if it raises the bound by
more than its BIC penalty, (d + 1)/2 log n = 16.6 nats here; it raises it by less (the affine
optimum two restarts find is within that of the SE fit), the sin(z/8) stays in the residual, and
it enters as a tilt source with a large gain. Tried and measured against the rig families
(scripts/bench_rigs.py), not landed: confirming a selection on the residual of the first fit
with the SE part on fixed this log, but on a reversal rig (seed 10, 125 moves) nothing entered
on that residual where the affine one found the true source, the final bound fell by 21 nats,
and the family's dev rigs passing at 125 moves fell from 12 to 10 of 12. With ``se: on`` the log selects nothing
(tests/cli/test_train_solve_cli.py). When this passes, remove the mark.
"""

from __future__ import annotations

import pytest
from conftest import CONFIGS

from microctl.measurement.log import read_log
from microctl.models.afm import AnalyticForwardModel
from microctl.models.training import ResidualModelSettings, residual_dataset, train_residual_model
from microctl.stage.config import load_stage_config


@pytest.mark.xfail(strict=True, reason="known defect: se: auto drops f's SE part and a smooth mean residual "
                                       "enters as a tilt noise source (module docstring)")
@pytest.mark.parametrize("restarts", [1, 2])
def test_a_smooth_mean_residual_is_not_selected_as_a_noise_source(planted_log, restarts):
    cfg = load_stage_config(CONFIGS / "stage" / "table1.yaml")
    afm = AnalyticForwardModel(cfg.stage)
    data = residual_dataset(read_log(planted_log, cfg.stage), afm)
    model = train_residual_model(data, afm, ResidualModelSettings(restarts=restarts))
    assert model.info["noise_selection"]["selected"] == []
