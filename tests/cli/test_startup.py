"""The command line's start-up: one BLAS thread unless the user chose, and only at the entry point."""

from __future__ import annotations

import subprocess
import sys

from microctl.cli import BLAS_THREAD_VARIABLES, one_blas_thread


def test_one_blas_thread_only_when_nobody_chose():
    env: dict = {}
    assert one_blas_thread(env, {}) and env == {"OPENBLAS_NUM_THREADS": "1"}
    for var in BLAS_THREAD_VARIABLES:  # a user's count wins, whichever variable carries it
        env = {var: "4"}
        assert not one_blas_thread(env, {}) and env == {var: "4"}
    env = {}
    assert not one_blas_thread(env, {"numpy": object()}) and env == {}  # too late: the pool is sized


def test_entry_point_sets_it_and_a_library_call_does_not():
    code = ("import os, sys\nfrom microctl.cli import main\n"
            "try:\n    main(['--version'])\nexcept SystemExit:\n    pass\n"
            "print('LIB', os.environ.get('OPENBLAS_NUM_THREADS'))\n"
            "sys.argv = ['microctl', '--version']\n"
            "try:\n    main()\nexcept SystemExit:\n    pass\n"
            "print('ENTRY', os.environ.get('OPENBLAS_NUM_THREADS'))\n")
    env = {k: v for k, v in __import__("os").environ.items() if k not in BLAS_THREAD_VARIABLES}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=60,
                         check=True).stdout
    assert "LIB None" in out and "ENTRY 1" in out, out
