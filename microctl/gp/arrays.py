"""Checks and conversions of the arrays the VHGPR takes and stores (training data, model-file JSON).

Every failure is a :class:`~microctl.errors.DataError` whose message names the array and
the offending row.
"""

from __future__ import annotations

import hashlib
import math
from typing import Any

import numpy as np

from microctl.errors import DataError

__all__ = ["as_float_array", "check_finite", "validate_training", "training_hash", "freeze", "jsonable"]


def as_float_array(a: Any, name: str) -> np.ndarray:
    """``a`` as a float64 array; DataError naming ``name`` when it is not numeric."""
    try:
        arr = np.asarray(a, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise DataError(f"{name} is not numeric: {exc}") from None
    return arr


def check_finite(a: np.ndarray, name: str) -> None:
    """DataError naming ``name`` and the first row (and column) holding NaN or inf."""
    bad = ~np.isfinite(a)
    if bad.any():
        idx = tuple(int(i) for i in np.argwhere(bad)[0])
        where = f"row {idx[0]}" + (f", column {idx[1]}" if len(idx) > 1 else "")
        raise DataError(f"{name} has a non-finite value ({a[idx]}) at {where} (0-based); NaN and inf are not allowed")


#: Largest magnitude of a training value: beyond it the standardisation's squares overflow.
MAX_ABS_VALUE = 1e150


def check_magnitude(a: np.ndarray, name: str) -> None:
    """DataError naming ``name`` and the first row (and column) with a value beyond :data:`MAX_ABS_VALUE`."""
    big = np.abs(a) > MAX_ABS_VALUE
    if big.any():
        idx = tuple(int(i) for i in np.argwhere(big)[0])
        where = f"row {idx[0]}" + (f", column {idx[1]}" if len(idx) > 1 else "")
        raise DataError(f"{name} has the value {a[idx]:.6g} at {where} (0-based); values beyond ±{MAX_ABS_VALUE:g} "
                        "cannot be standardised (their squares overflow): rescale the column")


def validate_training(X: Any, y: Any) -> tuple[np.ndarray, np.ndarray]:
    """Check and convert training data; DataError with a clear message otherwise."""
    X = as_float_array(X, "X")
    y = as_float_array(y, "y")
    if X.ndim == 1:
        X = X[:, None]
    if X.ndim != 2:
        raise DataError(f"X has {X.ndim} dimensions (shape {X.shape}); expected a 2-D array of shape (n, d)")
    if X.shape[1] < 1:
        raise DataError(f"X has shape {X.shape}; it needs at least one input column")
    if y.ndim != 1:
        raise DataError(f"y has shape {y.shape}; expected a 1-D array of shape (n,)")
    if X.shape[0] != y.shape[0]:
        raise DataError(f"X has {X.shape[0]} rows but y has {y.shape[0]} values; they must match")
    if X.shape[0] < 2:
        raise DataError(f"{X.shape[0]} training point(s); at least 2 are needed")
    check_finite(X, "X")
    check_finite(y, "y")
    check_magnitude(X, "X")
    check_magnitude(y, "y")
    if not float(np.std(y)) > 1e-12 * max(1.0, float(np.max(np.abs(y)))):
        raise DataError(f"y is constant (every value is {y[0]:g}); there is nothing to regress")
    return np.array(X, dtype=np.float64), np.array(y, dtype=np.float64)


def training_hash(X: np.ndarray, y: np.ndarray) -> str:
    """SHA-256 of the training data's float64 bytes (X then y): which data a model was fitted on."""
    return hashlib.sha256(
        np.ascontiguousarray(X, dtype=np.float64).tobytes() + np.ascontiguousarray(y, dtype=np.float64).tobytes()
    ).hexdigest()


def freeze(a: np.ndarray) -> None:
    """Make ``a`` read-only (the arrays of a fitted model are shared, never copied)."""
    a.setflags(write=False)


def jsonable(obj: Any) -> Any:
    """``obj`` with NumPy values as Python ones and non-finite floats as None (for JSON)."""
    if isinstance(obj, dict):
        return {str(k): jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return jsonable(obj.tolist())
    if isinstance(obj, np.generic):
        return jsonable(obj.item())
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj
