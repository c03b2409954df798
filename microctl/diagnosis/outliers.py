"""Outlying rows: reported by row number and left out of the fits, never explained as physics.

A corrupt cell in a log (a command typed as 50 µm, a reading off by tens of µm) is one row
that disagrees with every model; a least-squares fit would bend a cause to it. Two tests,
both at the per-run level α/4 with a Bonferroni correction over the n rows (critical
|z| = Φ⁻¹(1 − α/(8n)), 4.9 for n = 300). Outliers are rare by nature: when more than
:data:`MAX_OUTLIER_FRACTION` of the rows are beyond the critical value, they are a region the
model gets wrong (structure), and none is set aside.

1. :func:`screen` — before any cause is fitted: the residual of the configured model is fitted
   *robustly* (Tukey bisquare, iteratively reweighted least squares from a Huber start) by the
   generic basis B of :func:`~microctl.diagnosis.residuals.generic_basis`, which follows the
   smooth structure of any cause; rows whose robust residual exceeds the critical multiple of
   the robust scale (1.4826 × MAD) are set aside.
2. :func:`row_test` — after the causes are named on the other rows: the residual of the named
   model at *every* row, less the flexible term F where structure is left
   (:class:`~microctl.diagnosis.flexible.Flexible`, a row's prediction from the other rows),
   standardised by the fitted noise model (friction included) plus F's own uncertainty, and by
   the scale of the fitted rows (:func:`tail_scale`: bulk and tail). Rows beyond the critical
   value are the outliers — where structure is left, only those also extreme against the spread
   of the residual itself (:func:`extreme_rows`: F extrapolates poorly at the corners of the
   workspace, while a gross error stands out from any structure). Rows set aside by the screen
   that the named model fits are taken back; the pipeline repeats naming and test until the set
   no longer changes.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import stats

from microctl.diagnosis.data import DiagnosisData
from microctl.diagnosis.residuals import generic_basis

#: Tukey bisquare tuning constant (95 % efficiency at the normal) and Huber's start.
BISQUARE_C = 4.685
HUBER_C = 1.345

#: Most IRLS iterations per stage.
MAX_IRLS = 50

#: Largest share of the rows that can be outliers: more rows beyond the critical value are a
#: region the model gets wrong (structure, e.g. a ball lifting off over part of the workspace),
#: not corrupt cells, and none of them is set aside.
MAX_OUTLIER_FRACTION = 0.05


def critical_z(n: int, alpha: float) -> float:
    """Two-sided Bonferroni critical value over n rows at level ``alpha``."""
    return float(stats.norm.isf(alpha / (2.0 * max(n, 1))))


def robust_scale(r: np.ndarray) -> float:
    """1.4826 × median absolute deviation from the median (the normal's σ for clean data)."""
    return float(1.4826 * np.median(np.abs(r - np.median(r))))


#: Quantile of |z| that :func:`tail_scale` matches to the normal's.
TAIL_QUANTILE = 0.95


def tail_scale(z: np.ndarray) -> float:
    """Scale of standardised residuals from their bulk *and* their tail: the larger of
    1.4826 × MAD and the 95 % quantile of |z| over the normal's (1.96). Both are 1 for Gaussian
    residuals of the right scale; the tail estimate grows when the flexible term's approximation
    error makes the tails heavier than the bulk says (a few outliers move neither)."""
    q = float(np.quantile(np.abs(z), TAIL_QUANTILE)) / float(stats.norm.isf((1 - TAIL_QUANTILE) / 2))
    return max(robust_scale(z), q)


def robust_residual(X: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, float]:
    """Residual of a robust regression of y on X (Huber, then Tukey bisquare IRLS) and its scale.

    Returns
    -------
    r : ndarray, shape (n,)
    scale : float
        1.4826 × MAD of r.
    """
    coef, *_ = np.linalg.lstsq(X, y, rcond=None)
    for c, kind in ((HUBER_C, "huber"), (BISQUARE_C, "bisquare")):
        for _ in range(MAX_IRLS):
            r = y - X @ coef
            s = robust_scale(r)
            if s <= 0:
                return r, 0.0
            a = np.abs(r) / (c * s)
            w = np.minimum(1.0, 1.0 / np.maximum(a, 1e-12)) if kind == "huber" else np.where(a < 1, (1 - a * a) ** 2, 0.0)
            sw = np.sqrt(w)
            new, *_ = np.linalg.lstsq(X * sw[:, None], y * sw, rcond=None)
            if np.allclose(new, coef, rtol=1e-10, atol=1e-12 * (1 + np.abs(coef).max())):
                coef = new
                break
            coef = new
    r = y - X @ coef
    return r, robust_scale(r)


def screen(resid: np.ndarray, data: DiagnosisData, alpha: float) -> np.ndarray:
    """Rows set aside before naming (see the module docstring), boolean mask shape (n,).

    Parameters
    ----------
    resid : ndarray, shape (n,)
        Residual of the configured model.
    data : DiagnosisData
    alpha : float
        Per-run level (Bonferroni over rows).
    """
    r, s = robust_residual(generic_basis(data), resid)
    if s <= 0:
        return np.zeros(data.n, dtype=bool)
    return _rare(np.abs(r) > critical_z(data.n, alpha) * s)


def _rare(flags: np.ndarray) -> np.ndarray:
    """``flags`` if at most :data:`MAX_OUTLIER_FRACTION` of the rows, else none (structure, not outliers)."""
    return flags if flags.sum() <= MAX_OUTLIER_FRACTION * flags.size else np.zeros_like(flags)


def extreme_rows(reference: np.ndarray, values: np.ndarray, alpha: float) -> np.ndarray:
    """Rows of ``values`` beyond the critical multiple of the robust spread of ``reference``
    (|v − median| > z_c · 1.4826 MAD), boolean mask shape of ``values``."""
    med = float(np.median(reference))
    s = robust_scale(reference)
    return np.abs(values - med) > critical_z(values.size, alpha) * max(s, 1e-12)


@dataclass(frozen=True)
class RowTest:
    """The outlier test on every row.

    Attributes
    ----------
    outlier : ndarray of bool, shape (n,)
    z : ndarray, shape (n,)
        Standardised residuals.
    critical : float
    scale : float
        Robust scale of the standardised residual on the fitted rows (1 when the noise model is right).
    """

    outlier: np.ndarray
    z: np.ndarray
    critical: float
    scale: float


def row_test(resid: np.ndarray, std: np.ndarray, fitted: np.ndarray, alpha: float) -> RowTest:
    """Outliers among all rows of a named model (see the module docstring).

    Parameters
    ----------
    resid : ndarray, shape (n,)
        Residual of the named model at every row, less the flexible term where it is used, µm.
    std : ndarray, shape (n,)
        Noise model's std per row, µm.
    fitted : ndarray of bool, shape (n,)
        Rows the model was fitted on (they set the robust scale).
    alpha : float
    """
    z = resid / std
    s = tail_scale(z[fitted]) if fitted.sum() > 2 else 1.0
    s = max(s, 1e-12)
    zc = critical_z(resid.size, alpha)
    return RowTest(_rare(np.abs(z) > zc * s), z / s, zc, s)


def suspect_cells(data: DiagnosisData, K: np.ndarray, rows: np.ndarray, names: tuple[str, ...],
                  tool: str) -> list[dict]:
    """Which cell of each outlying row looks wrong: an actuator column whose command disagrees with
    its pose (q ≠ K u, eq. 12; a log written by this package has q = K u to round-off), else the reading.

    Returns
    -------
    list of dict
        ``{"index", "columns", "values"}`` per row (0-based index into the run).
    """
    out = []
    for k in np.flatnonzero(rows):
        qk = K @ data.u[k]
        bad = np.abs(data.q[k] - qk) > 1e-6 * (1.0 + np.abs(qk))
        cols = [names[i] for i in np.flatnonzero(bad)] or [tool]
        vals = {names[i]: {"logged": float(data.q[k, i]), "from_pose": float(qk[i])} for i in np.flatnonzero(bad)}
        if not vals:
            vals = {tool: {"logged": float(data.t[k])}}
        out.append({"index": int(k), "columns": cols, "values": vals})
    return out
