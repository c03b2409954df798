"""A Ctrl-C while a training design is built (microctl.measurement.design)."""

from __future__ import annotations

from pathlib import Path

import pytest

from microctl.measurement.design import training_moves
from microctl.models.afm import AnalyticForwardModel
from microctl.stage.config import load_stage_config

ROOT = Path(__file__).resolve().parents[2]


def _afm() -> AnalyticForwardModel:
    return AnalyticForwardModel(load_stage_config(ROOT / "configs/stage/sim_paper.yaml").stage)


def test_a_ctrl_c_during_the_sobol_set_up_is_held_until_it_is_done(monkeypatch):
    """A SIGINT that arrives while scipy sets up the Sobol sequence (compiled code that cannot raise:
    a Ctrl-C there was printed as a traceback, tests/cli/test_kill.py) is delivered once the set-up
    is done, through the command line's handler, as KeyboardInterrupt from the design."""
    import os
    import signal

    from scipy.stats import qmc

    from microctl.cli import _on_sigint
    from microctl.util.signals import RECEIVED

    done = []
    real_init = qmc.Sobol.__init__

    def init(self, *args, **kwargs):
        os.kill(os.getpid(), signal.SIGINT)  # arrives inside the set-up
        real_init(self, *args, **kwargs)
        done.append(True)

    monkeypatch.setattr(qmc.Sobol, "__init__", init)
    previous = signal.signal(signal.SIGINT, _on_sigint)
    try:
        with pytest.raises(KeyboardInterrupt):
            training_moves(_afm(), "space_filling", 10, 0)
    finally:
        signal.signal(signal.SIGINT, previous)
        RECEIVED.clear()
    assert done == [True]
