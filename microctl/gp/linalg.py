"""Dense linear algebra of the VHGPR: Cholesky factors with fallback jitter and inverses from them.

Used by the bound (:mod:`microctl.gp.bound`) and the homoscedastic initialisation
(:mod:`microctl.gp.homoscedastic`); ``notes/vhgpr.md`` [N stable forms].
"""

from __future__ import annotations

import math

import numpy as np
from scipy.linalg import lapack

__all__ = ["LOG_2PI", "chol", "chol_inverse"]

#: log(2 pi), of the Gaussian log densities.
LOG_2PI = math.log(2.0 * math.pi)

def chol(A: np.ndarray, *, what: str) -> tuple[np.ndarray, float]:
    """Lower Cholesky factor of symmetric ``A``; diagonal jitter only if plain Cholesky fails.

    Returns the factor and the jitter added (0.0 when none).  Jitter grows from 1e-10 to
    1e-4 times the mean diagonal; beyond that a :class:`numpy.linalg.LinAlgError` is raised.
    """
    L, info = lapack.dpotrf(A, lower=1, clean=1, overwrite_a=0)
    if info == 0:
        return L, 0.0
    scale = float(np.mean(np.diag(A)))
    if not np.isfinite(scale) or scale <= 0:
        raise np.linalg.LinAlgError(f"{what}: non-finite or non-positive diagonal")
    for k in range(-10, -3):
        jitter = scale * 10.0**k
        L, info = lapack.dpotrf(A + jitter * np.eye(A.shape[0]), lower=1, clean=1, overwrite_a=0)
        if info == 0:
            return L, jitter
    raise np.linalg.LinAlgError(f"{what}: not positive definite even with jitter {jitter:.3g}")


def chol_inverse(L: np.ndarray) -> np.ndarray:
    """Full symmetric inverse of L L^T from its lower Cholesky factor ``L`` (LAPACK potri).

    ``L`` must have a zero upper triangle (``dpotrf(..., clean=1)``); potri writes the
    lower triangle of the inverse, which is then mirrored.
    """
    Ainv, info = lapack.dpotri(L, lower=1)
    if info != 0:
        raise np.linalg.LinAlgError("potri failed")
    Ainv += Ainv.T
    Ainv[np.diag_indices(Ainv.shape[0])] *= 0.5
    return Ainv

