"""single_thread_blas (microctl.util.blas): the limit holds inside nested blocks and is restored
by the outermost one. Independent answer: threadpoolctl's own report of the BLAS pools."""

from __future__ import annotations

import numpy as np
import pytest
from threadpoolctl import threadpool_info, threadpool_limits

from microctl.util.blas import single_thread_blas


def _blas_threads() -> list[int]:
    np.ones((2, 2)) @ np.ones((2, 2))  # the BLAS NumPy loaded is the pool checked
    return [p["num_threads"] for p in threadpool_info() if p["user_api"] == "blas"]


def test_nested_blocks_keep_one_thread_until_the_outermost_exits():
    if not _blas_threads():
        pytest.skip("no BLAS pool reported by threadpoolctl")
    with threadpool_limits(limits=2, user_api="blas"):  # a known starting point, above 1
        before = _blas_threads()
        with single_thread_blas():
            assert set(_blas_threads()) == {1}
            with single_thread_blas():
                assert set(_blas_threads()) == {1}
            assert set(_blas_threads()) == {1}  # the inner block restored nothing
        assert _blas_threads() == before
        # an error inside still restores
        with pytest.raises(RuntimeError):
            with single_thread_blas():
                with single_thread_blas():
                    raise RuntimeError("inside")
        assert _blas_threads() == before
        with single_thread_blas():  # and the next block limits again
            assert set(_blas_threads()) == {1}
        assert _blas_threads() == before
