"""The experiments' controller registry: one registration adds a controller to the config
validation, the runner, results.json, report.md and the figures."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from microctl.control.controller import AFMController
from microctl.errors import ConfigError
from microctl.experiments import controllers as registry
from microctl.experiments.config import load_experiment_config
from microctl.experiments.runner import run_experiment

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture
def toy_controller():
    """The AFM controller registered under another name (removed after the test)."""
    e = registry.register(registry.ControllerEntry(
        "toy_afm", "toy AFM", lambda run, eafm: AFMController(run.afm, run.cfg.controller, reporter=eafm),
        registry.PlotStyle("tab:cyan", "P", True, 0.2)))
    yield e
    del registry.REGISTRY[e.name]


def _config(tmp_path: Path, controllers: list[str], stage: str = "configs/stage/sim_paper.yaml") -> Path:
    doc = {"stage": str(ROOT / stage), "controllers": controllers,
           "training": {"moves": 20, "restarts": 1, "max_iter": 60}, "absolute": {"enabled": False},
           "incremental": {"targets_um": [7], "trials": 2}, "figures": False}
    p = tmp_path / "exp.yaml"
    p.write_text(yaml.safe_dump(doc))
    return p


def test_the_builtin_entries():
    assert registry.names() == ("afm", "eafm", "oracle", "eafm_sequence", "oracle_sequence")
    assert registry.default_names() == ("afm", "eafm", "oracle")
    assert registry.required_names() == ("afm", "eafm")
    assert [n for n in registry.names() if registry.entry(n).needs_truth] == ["oracle", "oracle_sequence"]
    assert registry.sequence_pairs() == (("eafm", "eafm_sequence"), ("oracle", "oracle_sequence"))
    assert registry.label("eafm_sequence") == "EAFM sequence" and registry.label("unknown") == "unknown"
    with pytest.raises(ValueError, match="registered already"):
        registry.register(registry.entry("afm"))


def test_unregistered_controller_is_rejected(tmp_path):
    with pytest.raises(ConfigError, match="toy_afm"):
        load_experiment_config(_config(tmp_path, ["afm", "eafm", "toy_afm"]))


def test_a_registered_controller_runs_through_the_experiment(tmp_path, toy_controller):
    cfg = load_experiment_config(_config(tmp_path, ["afm", "eafm", "toy_afm"]))
    assert cfg.controllers == ("afm", "eafm", "toy_afm")
    res = run_experiment(cfg, tmp_path / "out", quiet=True)
    inc = res["incremental"]["controllers"]
    assert set(inc) == {"afm", "eafm", "toy_afm"}
    # the AFM controller under another name: the same commands, so the same predictions
    assert inc["toy_afm"]["predicted_um"] == inc["afm"]["predicted_um"]
    assert inc["toy_afm"]["fallbacks_to_afm"] == 0
    assert "| MSSE | toy AFM |" in (tmp_path / "out" / "report.md").read_text()


def test_a_truth_controller_needs_a_simulated_stage(tmp_path, toy_controller):
    registry.register(registry.ControllerEntry("toy_afm", "toy AFM", toy_controller.build, needs_truth=True),
                      replace=True)
    with pytest.raises(ConfigError, match="'toy_afm' needs the simulator's true mean"):
        load_experiment_config(_config(tmp_path, ["afm", "eafm", "toy_afm"], "configs/stage/emulated.yaml"))
