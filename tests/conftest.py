"""Shared fixtures: paths to the shipped configs and small helpers."""

from __future__ import annotations

import os
import sys
from pathlib import Path

from microctl.cli import BLAS_THREAD_VARIABLES, one_blas_thread

#: Set where this file chose the BLAS thread count, so that pytest-xdist's workers, which inherit
#: the environment, tell its choice from the user's.
SUITE_CHOSE_BLAS = "MICROCTL_TESTS_CHOSE_BLAS_THREADS"
#: Whether whoever started pytest chose a BLAS thread count (then it is kept).
USER_CHOSE_BLAS_THREADS = (os.environ.get(SUITE_CHOSE_BLAS) != "1"
                           and any(v in os.environ for v in BLAS_THREAD_VARIABLES))
# Before any test imports NumPy: each test process's BLAS on one thread, as the command line runs
# it (microctl.cli.one_blas_thread). With pytest-xdist's two workers on two cores, two BLAS threads
# each oversubscribed the machine and the threads spun waiting for each other.
if one_blas_thread(os.environ, sys.modules):
    os.environ[SUITE_CHOSE_BLAS] = "1"

import pytest  # noqa: E402


def pytest_collection_modifyitems(config, items):
    """Files that hold slow tests run first, each file's tests in their own order (a stable sort,
    so both pytest-xdist workers collect the same order). The suite's wall time on two workers is
    set by its end: a long run started last leaves the other worker idle while it finishes."""
    slow_files = {item.path for item in items if item.get_closest_marker("slow") is not None}
    items.sort(key=lambda item: item.path not in slow_files)


# The tests mirror the packages (tests/stage/, tests/gp/, ...); the shared helpers beside this file
# (independent_stage.py, serial_rig.py, CONFIGS here) are importable from every folder.
sys.path.insert(0, str(Path(__file__).resolve().parent))

ROOT = Path(__file__).resolve().parents[1]
CONFIGS = ROOT / "configs"
DATA = ROOT / "tests" / "data"  # shipped test data (tests/data/README.md); nothing outside the repository is read


@pytest.fixture
def table1_path() -> Path:
    return CONFIGS / "stage" / "table1.yaml"


@pytest.fixture
def table1(table1_path):
    from microctl.stage.config import load_stage_config

    return load_stage_config(table1_path)


@pytest.fixture(scope="session")
def planted_log(tmp_path_factory) -> Path:
    """A hand-written 40-row log of the Table I stage: the AFM's reading plus a planted smooth
    residual (0.3 sin(z/8) + 0.2 rx) and 0.05 µm noise, seed 0 (for train/solve and model-file tests)."""
    import numpy as np

    from microctl.models.afm import AnalyticForwardModel
    from microctl.stage.config import load_stage_config

    afm = AnalyticForwardModel(load_stage_config(CONFIGS / "stage" / "table1.yaml").stage)
    rng = np.random.default_rng(0)
    U = afm.workspace.sample(40, rng)
    Q = U @ afm.K.T
    t = afm.t_of(U) + 0.3 * np.sin(U[:, 0] / 8) + 0.2 * U[:, 1] + 0.05 * rng.standard_normal(40)
    lines = ["seq,u_z,u_rx,u_ry,q1,q2,q3,q4,t"]
    lines += [",".join([str(k)] + [f"{v:.9g}" for v in (*U[k], *Q[k], t[k])]) for k in range(40)]
    log = tmp_path_factory.mktemp("planted_log") / "log.csv"
    log.write_text("\n".join(lines) + "\n")
    return log


@pytest.fixture
def nlpsol_calls(monkeypatch) -> list:
    """The names of the CasADi NLP solvers built while the test runs (``casadi.nlpsol`` spied on)."""
    import casadi

    calls: list = []
    real = casadi.nlpsol

    def counting(*args, **kwargs):
        calls.append(args[0])
        return real(*args, **kwargs)

    monkeypatch.setattr(casadi, "nlpsol", counting)
    return calls
