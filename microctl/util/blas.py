"""One switch for the BLAS thread pool during microctl's numerical work.

On the 2-core machines this package is developed and tested on, with another process on
the other core, a multi-threaded OpenBLAS made the small products of the controller's seeding
(150×8 @ 8×2000), a 250×250 Cholesky in the diagnosis and an n = 2000 VHGPR bound evaluation
many times slower than one thread (``python -m timeit`` of each under
``OPENBLAS_NUM_THREADS=2`` and ``=1`` while another process is busy shows it): the threads
spin waiting for each other. The work here is
either small matrices or already dominated by one O(n³) factorisation, so one thread is
both faster and predictable. :func:`single_thread_blas` limits the BLAS for the duration
of a ``with`` block and restores it afterwards (threadpoolctl).
"""

from __future__ import annotations

from contextlib import AbstractContextManager

from threadpoolctl import ThreadpoolController

_CONTROLLER: list[ThreadpoolController] = []
#: How many single_thread_blas blocks are open (the BLAS's limit is process-wide, so is this).
_DEPTH = [0]


class _OneThread(AbstractContextManager):
    """A block with the BLAS on one thread: the outermost open block sets the limit on entry and
    restores it on exit; a block inside it has nothing to set or restore."""

    def __enter__(self):
        self._limit = None
        if _DEPTH[0] == 0:
            if not _CONTROLLER:  # inspecting the loaded libraries once is the slow part
                _CONTROLLER.append(ThreadpoolController())
            self._limit = _CONTROLLER[0].limit(limits=1, user_api="blas")
        _DEPTH[0] += 1
        return self

    def __exit__(self, *exc):
        _DEPTH[0] -= 1
        if self._limit is not None:
            self._limit.__exit__(*exc)
        return False


def single_thread_blas() -> AbstractContextManager:
    """Context manager: the BLAS runs on one thread inside the block (entering is cheap next to
    the work it wraps; a block opened inside another costs nothing: the outermost one restores the BLAS)."""
    return _OneThread()
