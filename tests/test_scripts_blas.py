"""The benchmark scripts that run the package's numerics in worker processes, and the test suite
(tests/conftest.py), start their BLAS on one thread, as the command line does
(microctl.cli.one_blas_thread), unless the user chose a count.

Two BLAS threads in each of two workers on two cores oversubscribe the machine (a worker was
seen above 100 % CPU with much of the time in the kernel), and the rounding then differs from
the command line's.
"""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from microctl.cli import BLAS_THREAD_VARIABLES
from script_loader import ROOT

#: The scripts with a process pool of workers running the package's numerics.
POOLED_SCRIPTS = ("bench_rigs", "bench_learn", "bench_screen", "bench_sequence")

#: Loads a script as a module (its main() does not run), then prints the largest BLAS thread count
#: in this process and in a worker process of the kind the scripts start.
PROBE = """
import importlib.util, sys
from concurrent.futures import ProcessPoolExecutor
sys.path.insert(0, {scripts!r})
spec = importlib.util.spec_from_file_location("probe_script", {path!r})
mod = sys.modules[spec.name] = importlib.util.module_from_spec(spec)
spec.loader.exec_module(mod)

def blas_threads():
    from threadpoolctl import threadpool_info
    return max(i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas")

with ProcessPoolExecutor(1) as ex:
    worker = ex.submit(blas_threads).result()
print("THREADS", blas_threads(), worker)
"""


def _threads(script: str, extra_env: dict) -> tuple[int, int]:
    env = {k: v for k, v in os.environ.items() if k not in BLAS_THREAD_VARIABLES}
    env.update(extra_env)
    code = PROBE.format(scripts=str(ROOT / "scripts"), path=str(ROOT / "scripts" / f"{script}.py"))
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, cwd=ROOT,
                         timeout=120, check=True).stdout
    line = next(ln for ln in out.splitlines() if ln.startswith("THREADS"))
    main, worker = (int(v) for v in line.split()[1:])
    return main, worker


@pytest.mark.skipif((os.cpu_count() or 1) < 2, reason="one core: a BLAS pool has one thread whatever the script does")
@pytest.mark.parametrize("script", POOLED_SCRIPTS)
def test_pooled_script_runs_one_blas_thread_unless_the_user_chose(script):
    assert _threads(script, {}) == (1, 1)
    # a user's count wins (2: more than one, and no more than this machine's cores)
    assert _threads(script, {"OPENBLAS_NUM_THREADS": "2"}) == (2, 2)


@pytest.mark.skipif((os.cpu_count() or 1) < 2, reason="one core: a BLAS pool has one thread whatever the suite does")
def test_the_suite_runs_one_blas_thread_unless_the_user_chose():
    import conftest
    from threadpoolctl import threadpool_info

    if conftest.USER_CHOSE_BLAS_THREADS:
        pytest.skip("pytest was started with a BLAS thread count of the user's")
    import numpy  # noqa: F401  (the BLAS libraries are loaded)

    threads = [i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas"]
    assert threads and max(threads) == 1, threads
