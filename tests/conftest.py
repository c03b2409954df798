"""Shared fixtures: paths to the shipped configs and small helpers."""

from __future__ import annotations

from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
CONFIGS = ROOT / "configs"
DATA = ROOT / "tests" / "data"  # shipped test data (tests/data/README.md); nothing outside the repository is read


@pytest.fixture
def table1_path() -> Path:
    return CONFIGS / "stage" / "table1.yaml"


@pytest.fixture
def table1(table1_path):
    from microctl.config import load_stage_config

    return load_stage_config(table1_path)
