"""Dense linear algebra of the VHGPR: Cholesky factors with fallback jitter and inverses from them.

Used by the bound (:mod:`microctl.gp.bound`) and the homoscedastic initialisation
(:mod:`microctl.gp.homoscedastic`); ``notes/vhgpr.md`` [N stable forms]. LAPACK comes from
SciPy, imported on first use: importing ``scipy.linalg`` costs more CPU than NumPy and CasADi
together (``python -X importtime -c 'import scipy.linalg'``), and a one-shot ``microctl solve``
(prediction only) never needs it
(:func:`tril_inverse` is NumPy only).
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["LOG_2PI", "chol", "chol_inverse", "tril_inverse"]

#: log(2 pi), of the Gaussian log densities.
LOG_2PI = math.log(2.0 * math.pi)

def chol(A: np.ndarray, *, what: str) -> tuple[np.ndarray, float]:
    """Lower Cholesky factor of symmetric ``A``; diagonal jitter only if plain Cholesky fails.

    Returns the factor and the jitter added (0.0 when none).  Jitter grows from 1e-10 to
    1e-4 times the mean diagonal; beyond that a :class:`numpy.linalg.LinAlgError` is raised.
    """
    from scipy.linalg import lapack

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
    from scipy.linalg import lapack

    Ainv, info = lapack.dpotri(L, lower=1)
    if info != 0:
        raise np.linalg.LinAlgError("potri failed")
    Ainv += Ainv.T
    Ainv[np.diag_indices(Ainv.shape[0])] *= 0.5
    return Ainv



#: Below this order :func:`tril_inverse` inverts a diagonal block by forward substitution.
_TRIL_BLOCK = 32


def tril_inverse(L: np.ndarray) -> np.ndarray:
    """Inverse of a nonsingular lower-triangular ``L`` (shape (n, n)), lower triangular, NumPy only.

    Recursive block inversion: with ``L = [[A, 0], [B, C]]``, ``L^-1 = [[A^-1, 0],
    [-C^-1 B A^-1, C^-1]]``; blocks of order <= 32 by column-wise forward substitution, the
    rest matrix products (the flops of LAPACK's ``trtri``, n^3 / 3). Checked against
    ``scipy.linalg.solve_triangular(L, I)`` in ``tests/gp/test_linalg.py``.
    """
    L = np.asarray(L, dtype=float)
    n = L.shape[0]
    if L.ndim != 2 or L.shape[1] != n:
        raise ValueError(f"tril_inverse needs a square matrix, got shape {L.shape}")
    if n <= _TRIL_BLOCK:
        X = np.zeros((n, n))
        d = np.diag(L)
        for i in range(n):  # row i of L X = I: X[i] = (e_i - L[i, :i] X[:i]) / L[i, i]
            X[i] = -(L[i, :i] @ X[:i])
            X[i, i] += 1.0
            X[i] /= d[i]
        return X
    h = n // 2
    Ai = tril_inverse(L[:h, :h])
    Ci = tril_inverse(L[h:, h:])
    X = np.zeros((n, n))
    X[:h, :h] = Ai
    X[h:, h:] = Ci
    X[h:, :h] = -(Ci @ (L[h:, :h] @ Ai))
    return X
