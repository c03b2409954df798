"""The backends form a registry by ``backend.kind``, covering every kind the stage config accepts."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import pytest

from microctl.backends import BACKENDS, StageBackend, make_backend, register_backend
from microctl.backends.serial import SerialStage
from microctl.backends.simulated import SimulatedStage
from microctl.errors import ConfigError
from microctl.stage.config import BACKEND_KINDS, load_stage_config

ROOT = Path(__file__).resolve().parents[2]


def test_every_config_kind_has_a_backend():
    assert tuple(BACKENDS) == BACKEND_KINDS
    assert BACKENDS["simulated"] is SimulatedStage and BACKENDS["serial"] is SerialStage
    assert all(issubclass(cls, StageBackend) for cls in BACKENDS.values())


def test_make_backend_reads_the_registry():
    cfg = load_stage_config(ROOT / "configs/stage/sim_paper.yaml")
    with make_backend(cfg, seed=3) as b:
        assert type(b) is SimulatedStage
    bad = replace(cfg, backend=replace(cfg.backend, kind="usb"))
    with pytest.raises(ConfigError, match="backend.kind: 'usb' is not a backend; valid: simulated, serial"):
        make_backend(bad)


def test_a_kind_registers_once():
    with pytest.raises(ValueError, match="registered already"):
        register_backend("simulated")(SimulatedStage)
