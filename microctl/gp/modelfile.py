"""The VHGPR model file: writing, reading and validating a fitted model (``.npz``).

The file is a NumPy ``.npz`` archive readable with ``np.load(allow_pickle=False)``: the
fields of :class:`~microctl.gp.fitted.FittedVHGPR` by their storage role (declared once on
the dataclass, :meth:`~microctl.gp.fitted.FittedVHGPR.stored`): arrays and floats as
float64 arrays, optional floats as arrays of length 0 (None) or 1, optional arrays only
when present, and the text fields (hashes, names, fit diagnostics, the noise model's name)
in one JSON array ``meta_json``. Reading refuses, naming the file, anything that is not such
an archive, an unknown format version, missing or malformed arrays, and numbers no fit can
produce (:func:`_check_model_values`).
"""

from __future__ import annotations

import json
import math
import re
import zipfile
from dataclasses import MISSING, fields
from pathlib import Path
from typing import Any

import numpy as np

from microctl.errors import DataError
from microctl.gp.arrays import freeze, jsonable
from microctl.gp.noise_models import FEATURE_ARRAYS, noise_model_class

__all__ = ["FORMAT_VERSION", "READABLE_VERSIONS", "write_model", "read_model"]

#: Version of the ``.npz`` model file written by :func:`write_model` (2: optional linear
#: kernel part of f and parametric prior mean of g; version 1 files read unchanged). The
#: noise model's name (``meta_json["noise_model"]``) is optional: files without it read
#: with the name derived from their arrays. Version 3 adds the optional
#: ``meta_json["posterior_form"]`` (``"sparse"``: :mod:`microctl.gp.sparse`; absent: exact), so
#: that a microctl reading version 2 refuses a sparse model instead of misreading it. Version 4
#: allows inputs the kernels do not read (fewer lengthscales than inputs: a move's context that
#: only g's prior mean reads) and the optional gates of gated noise features
#: (``g_feature_gate``, ``g_feature_gate_offset``), so that an older microctl refuses such a model.
#: Version 5 adds f's optional feature trend (``f_trend_*``, :mod:`microctl.gp.trend`), which an
#: older microctl would silently drop from the mean. Version 6 adds g's optional input map
#: (``g_input_map``, ``meta_json["g_input_names"]``; :mod:`microctl.gp.kernels`), which an older
#: microctl would silently drop from g's kernel.
FORMAT_VERSION = 6
READABLE_VERSIONS = (1, 2, 3, 4, 5, 6)
#: The arrays of f's feature trend (all or none).
TREND_ARRAYS = ("f_trend_matrix", "f_trend_offset", "f_trend_params", "f_trend_scale")
#: The posterior forms (:class:`~microctl.gp.fitted.FittedVHGPR` ``posterior_form``).
POSTERIOR_FORMS = ("exact", "sparse")

# --------------------------------------------------------------------------- writing


def write_model(model: Any, path: str | Path) -> None:
    """Write a :class:`~microctl.gp.fitted.FittedVHGPR` to ``path`` (see the module docstring).

    Raises
    ------
    DataError
        If the file cannot be written.
    """
    cls = type(model)
    arrays: dict[str, np.ndarray] = {"format_version": np.array(FORMAT_VERSION, dtype=np.int64)}
    for name in cls.stored("array"):
        arrays[name] = np.asarray(getattr(model, name), dtype=np.float64)
    for name in cls.stored("float"):
        arrays[name] = np.array(float(getattr(model, name)), dtype=np.float64)
    for name in cls.stored("optional_float"):
        v = getattr(model, name)
        arrays[name] = np.array([] if v is None else [float(v)], dtype=np.float64)
    meta = {name: _META_WRITE.get(name, _same)(getattr(model, name)) for name in cls.stored("meta")
            if name not in ("noise_model_name", "posterior_form")
            and not (name in _WRITTEN_WHEN_SET and not getattr(model, name))}
    if model.posterior_form != "exact":
        meta["posterior_form"] = model.posterior_form
    if model.noise_model != _derived_noise_model(model):  # the first two models' files stay as they were
        meta["noise_model"] = model.noise_model
    arrays["meta_json"] = np.array(json.dumps(meta))
    for name in cls.stored("optional_array"):
        v = getattr(model, name)
        if v is not None:
            arrays[name] = np.asarray(v, dtype=np.float64)
    path = Path(path)
    try:
        from microctl.util.atomic import atomic_write

        with atomic_write(path, "wb") as fh:
            np.savez(fh, **arrays)
    except OSError as exc:
        raise DataError(f"{path}: cannot write the model file: {exc.strerror or exc}") from None


def _same(v: Any) -> Any:
    return v


def _derived_noise_model(model: Any) -> str:
    """The name a file without ``noise_model`` is read with: ``physical`` with features, else ``hgp``."""
    return "physical" if model.g_feature_matrix is not None else "hgp"


def _optional_str(v: Any) -> str | None:
    return None if v is None else str(v)


def _str_tuple(v: Any) -> tuple[str, ...]:
    return tuple(str(s) for s in v)


#: Meta fields written only when set (older models' files stay as they were).
_WRITTEN_WHEN_SET = ("g_feature_shapes", "g_feature_params", "f_trend_names", "f_trend_shapes", "g_input_names")
#: How the meta fields are written to JSON (default: as they are) ...
_META_WRITE = {"x_names": list, "g_feature_names": list, "info": jsonable, "g_feature_shapes": list,
               "f_trend_names": list, "f_trend_shapes": list, "g_input_names": list,
               "g_feature_params": lambda v: [[float(a), float(b)] for a, b in v]}
#: ... and read back: (converter, default when absent; no default: required).
_META_READ: dict[str, tuple] = {
    "training_hash": (str,),
    "geometry_hash": (_optional_str, None),
    "x_names": (_str_tuple, []),
    "y_name": (str, ""),
    "info": (dict, {}),
    "g_feature_names": (_str_tuple, []),
    "g_feature_shapes": (_str_tuple, []),
    "f_trend_names": (_str_tuple, []),
    "f_trend_shapes": (_str_tuple, []),
    "g_input_names": (_str_tuple, []),
    "g_feature_params": (lambda v: tuple((float(a), float(b)) for a, b in v), []),
}


# --------------------------------------------------------------------------- reading


def read_model(cls: type, path: str | Path) -> Any:
    """Read a model file written by :func:`write_model` into ``cls`` (a FittedVHGPR).

    Raises
    ------
    DataError
        Naming the file: unreadable, not an ``.npz``, unknown format version, missing or
        malformed arrays, unknown noise model, numbers no fit can produce.
    """
    path = Path(path)
    data = _read_arrays(path)
    _check_version(path, data)
    added_later = _defaults(cls)  # optional floats a file written before they existed lacks
    needed = (cls.stored("array") + cls.stored("float")
              + tuple(n for n in cls.stored("optional_float") if n not in added_later) + ("meta_json",))
    missing = [k for k in needed if k not in data]
    if missing:
        raise DataError(f"{path}: model file is missing array(s) {', '.join(repr(m) for m in missing)}")
    try:
        kw = _fields_from(cls, data, added_later)
    except (TypeError, ValueError, KeyError) as exc:
        raise DataError(f"{path}: malformed model file: {exc}") from None
    _check_shapes(path, kw, cls.shapes())
    _check_noise_model(path, kw)
    if kw["posterior_form"] not in POSTERIOR_FORMS:
        raise DataError(f"{path}: malformed model file: posterior_form {kw['posterior_form']!r} is not one of "
                        f"{', '.join(POSTERIOR_FORMS)}")
    for name in cls.stored("array") + cls.stored("optional_array"):
        if kw.get(name) is not None:
            freeze(kw[name])
    model = cls(**kw)
    _check_model_values(path, kw, model)
    return model


def _read_arrays(path: Path) -> dict[str, np.ndarray]:
    """Every array of the archive at ``path``; DataError when it is not a readable ``.npz``."""
    try:
        npz = _open_model_file(path)
    except FileNotFoundError:
        raise DataError(f"{path}: no such model file") from None
    except (OSError, ValueError, zipfile.BadZipFile, EOFError) as exc:
        raise DataError(f"{path}: not a VHGPR model file (.npz): {exc}") from None
    if not isinstance(npz, np.lib.npyio.NpzFile):
        raise DataError(f"{path}: not a VHGPR model file (.npz archive expected, found a single array)")
    with npz:
        try:
            return {k: npz[k] for k in npz.files}
        except (ValueError, OSError, zipfile.BadZipFile) as exc:
            raise DataError(f"{path}: not a VHGPR model file (.npz): {exc}") from None


def _check_version(path: Path, data: dict) -> None:
    """A readable ``format_version``, and no array of the retired microctl 0.1 prior mean."""
    if "format_version" not in data:
        raise DataError(f"{path}: not a VHGPR model file (no 'format_version' array)")
    try:
        version = int(data["format_version"])
    except (TypeError, ValueError):
        raise DataError(f"{path}: malformed 'format_version'") from None
    if version not in READABLE_VERSIONS:
        raise DataError(f"{path}: model format version {version} is not supported (this microctl reads "
                        f"versions {', '.join(map(str, READABLE_VERSIONS))})")
    if "mean_coef" in data:
        raise DataError(f"{path}: the model uses the plug-in linear prior mean of microctl 0.1, which is no "
                        f"longer supported (the linear trend is now part of f's kernel); retrain it")


def _defaults(cls: type) -> dict[str, Any]:
    """The fields of ``cls`` with a default (added to the file format after its first version)."""
    return {f.name: f.default for f in fields(cls) if f.default is not MISSING}


def _fields_from(cls: type, data: dict, added_later: dict[str, Any]) -> dict[str, Any]:
    """The constructor arguments of ``cls`` from the arrays (ValueError/KeyError/TypeError if malformed);
    an optional float of ``added_later`` (:func:`_defaults`) that the file lacks gets its default."""
    kw: dict[str, Any] = {}
    for name in cls.stored("array"):
        kw[name] = np.asarray(data[name], dtype=np.float64)
    for name in cls.stored("float"):
        kw[name] = float(data[name])
    for name in cls.stored("optional_float"):
        if name not in data and name in added_later:  # a field added after the file was written
            kw[name] = added_later[name]
            continue
        v = np.asarray(data[name], dtype=np.float64).ravel()
        if v.size > 1:
            raise ValueError(f"'{name}' has {v.size} values")
        kw[name] = float(v[0]) if v.size else None
    meta = json.loads(str(data["meta_json"]))
    for name, (convert, *default) in _META_READ.items():
        kw[name] = convert(meta[name] if not default else meta.get(name, default[0]))
    name = meta.get("noise_model")
    kw["noise_model_name"] = None if name is None else str(name)
    kw["posterior_form"] = str(meta.get("posterior_form", "exact"))
    for name in cls.stored("optional_array"):
        if name in data:
            kw[name] = np.asarray(data[name], dtype=np.float64)
    return kw


def _check_shapes(path: Path, kw: dict, dims: dict[str, tuple[str, ...]]) -> None:
    """Every array of the shape (``dims``: in n, d, k, p, p+1) n training points in d inputs, k of
    them read by the kernels, and p noise features need."""
    X = kw["X"]
    if X.ndim != 2 or X.shape[0] < 1:
        raise DataError(f"{path}: malformed model file: 'X' has shape {X.shape}")
    n, d = X.shape
    p = kw["g_feature_matrix"].shape[0] if kw.get("g_feature_matrix") is not None and kw["g_feature_matrix"].ndim == 2 else 0
    k = int(np.size(kw["f_log_lengthscales"])) if kw.get("f_log_lengthscales") is not None else d
    if not 1 <= k <= d:
        raise DataError(f"{path}: malformed model file: {k} lengthscales for {d} inputs (expected 1 to {d})")
    trend = kw.get("f_trend_matrix")
    t = trend.shape[0] if trend is not None and trend.ndim == 2 else 0
    gmap = kw.get("g_input_map")
    kg = gmap.shape[0] if gmap is not None and gmap.ndim == 2 else k  # g's lengthscales: k, or the map's rows
    if gmap is not None and len(kw.get("g_input_names", ())) not in (0, kg):
        raise DataError(f"{path}: malformed model file: {len(kw['g_input_names'])} g_input_names for a "
                        f"{kg}-row g_input_map")
    size = {"n": n, "d": d, "k": k, "kg": kg, "p": p, "p+1": p + 1, "t": t, "2": 2}
    shapes = {k: tuple(size[s] for s in spec) for k, spec in dims.items() if kw.get(k) is not None}
    features = [k for k in FEATURE_ARRAYS if kw.get(k) is not None]
    if features and len(features) != 3:
        raise DataError(f"{path}: malformed model file: g's prior-mean features need g_feature_matrix, "
                        f"g_feature_offset and g_log_feature_coef together (found {', '.join(features)})")
    trend = [k for k in TREND_ARRAYS if kw.get(k) is not None]
    if trend and (len(trend) != len(TREND_ARRAYS) or kw.get("f_trend_log_var") is None
                  or not len(kw.get("f_trend_names", ())) == len(kw.get("f_trend_shapes", ())) == t):
        raise DataError(f"{path}: malformed model file: f's feature trend needs {', '.join(TREND_ARRAYS)}, "
                        f"f_trend_log_var and one name and shape per feature together (found {', '.join(trend)})")
    for name, shape in shapes.items():
        if kw[name].shape != shape:
            raise DataError(f"{path}: malformed model file: '{name}' has shape {kw[name].shape}, expected {shape}")


def _check_noise_model(path: Path, kw: dict) -> None:
    """A registered noise model whose arrays are the ones the file holds."""
    name = kw["noise_model_name"]
    if name is None:
        return  # a file written before the name was stored: derived from the arrays
    try:
        noise = noise_model_class(name)
    except KeyError as exc:
        raise DataError(f"{path}: {exc.args[0]} (a model file of another microctl?)") from None
    have = tuple(k for k in FEATURE_ARRAYS if kw.get(k) is not None)
    if set(have) != set(noise.stored_arrays) and not (noise.features_optional and not have):
        raise DataError(f"{path}: malformed model file: noise model {name!r} stores "
                        f"{', '.join(noise.stored_arrays) or 'no feature arrays'}, the file has "
                        f"{', '.join(have) or 'none'}")


# --------------------------------------------------------------------------- model-file checks (load)

#: Largest predictive variance (units of y²) a loaded model may produce, far from the data or
#: at its training inputs. Beyond it the controller's arithmetic overflows (OverflowError in
#: ``solve``); no fitted model comes near it.
_MAX_MODEL_VARIANCE = 1e100

#: Largest |value| of a log-parameter (log variances, log lengthscales, mu0, log Lambda) in a
#: model file; the fit keeps them within ±20 and exp(300) is still a finite float.
_MAX_LOG_PARAMETER = 300.0

#: Training rows at which a loaded model's factors and predictions are checked (evenly spaced).
_N_CHECK_ROWS = 16

#: Relative tolerance of the factor checks (rounding of a Cholesky factor of size n ≤ 1e5).
_FACTOR_RTOL = 1e-8

#: Tolerance of the standardisation checks (column mean 0, standard deviation 1 or 0).
_STANDARD_TOL = 1e-5


def _open_model_file(path: Path) -> Any:
    """``np.load`` of a model file, once it is known to be a file holding a zip (.npz) archive.

    A ValueError here becomes ``"<path>: not a VHGPR model file (.npz): <message>"`` in
    :meth:`FittedVHGPR.load`, so its message is the reason only.
    """
    if path.is_dir():
        raise ValueError("it is a directory; give the .npz file written by `microctl train` or `microctl gp fit`")
    if path.exists() and not path.is_file():  # a FIFO or device: reading would wait forever
        raise ValueError("it is not a regular file (a FIFO, socket or device); give the .npz file")
    with path.open("rb") as fh:  # FileNotFoundError: load says "no such model file"
        head = fh.read(64)
    if not head:
        raise ValueError("the file is empty")
    if not head.startswith((b"PK\x03\x04", b"PK\x05\x06")):
        try:
            first = head.decode("utf-8").splitlines()[0]
            what = f"it is a text file starting with {first[:40]!r} (a CSV or YAML file?)"
        except (UnicodeDecodeError, IndexError):
            what = f"it starts with the bytes {head[:8]!r}, not a zip archive"
        raise ValueError(f"{what}; a model file is the .npz archive written by `microctl train` or `microctl gp fit`")
    npz = np.load(path, allow_pickle=False)
    if isinstance(npz, np.lib.npyio.NpzFile):
        try:
            for name in npz.files:  # read once here, so that a wrong dtype is refused, not cast with a warning
                try:
                    a = npz[name]
                except ValueError as exc:
                    if "pickle" in str(exc):
                        raise ValueError(f"array '{name}' holds Python objects (pickled data), which a model "
                                         "file never does") from None
                    raise
                if name != "meta_json" and a.dtype.kind not in "biuf":
                    raise ValueError(f"array '{name}' has dtype {a.dtype}; a model file holds real numbers")
        except BaseException:
            npz.close()
            raise
    return npz


def _check_model_values(path: Path, kw: dict, model: Any) -> None:
    """Refuse a loaded model (``model``, built from the arrays ``kw``) whose numbers cannot come
    from a fit (called at the end of load).

    Checked, each failure one :class:`DataError` naming the file and the array:

    - every array and parameter finite (``bound`` excepted: a record of the fit, NaN for a
      model not fitted by optimisation); ``x_scale`` and ``y_scale`` > 0; every
      log-parameter within ±:data:`_MAX_LOG_PARAMETER`;
    - ``training_hash`` a SHA-256 hex digest;
    - the stored arrays belong together: ``X`` standardised (column mean 0, standard
      deviation 1, or 0 for a constant column); the outputs ``f_chol f_cholᵀ f_alpha``
      standardised likewise (mean 0 only, with a linear prior mean); ``f_chol f_cholᵀ`` equal to K_f(X, X) off the
      diagonal and above it on the diagonal; ``g_chol g_cholᵀ`` equal to K_g(X, X) + Λ⁻¹
      (checked on :data:`_N_CHECK_ROWS` rows). The training hash itself cannot be recomputed
      (the original y is not stored), but arrays edited or taken from two files fail here;
    - the predictive variance far from the data and at the checked training inputs finite
      and at most :data:`_MAX_MODEL_VARIANCE` (a huge variance overflows later, in solve).
    """
    def fail(message: str) -> DataError:
        return DataError(f"{path}: {message}")

    # inf/nan from absurd values fail the checks; no RuntimeWarning
    with np.errstate(over="ignore", invalid="ignore", divide="ignore", under="ignore"):
        _check_ranges(kw, type(model), fail)
        rows = _check_belong_together(kw, model, fail)
        _check_variances(kw, model, rows, fail)


def _check_ranges(kw: dict, cls: type, fail: Any) -> None:
    """Every array and parameter finite, scales > 0, log-parameters bounded, a SHA-256 training hash."""
    for name in cls.stored("array") + cls.stored("optional_array"):
        a = kw.get(name)
        if a is None:
            continue
        bad = ~np.isfinite(a)
        if bad.any():
            idx = [int(i) for i in np.argwhere(bad)[0]]
            raise fail(f"array '{name}' has a non-finite value ({a[tuple(idx)]}) at index {idx}; the model file is "
                       "corrupt, retrain it")
    for name in cls.stored("float") + cls.stored("optional_float"):
        v = kw[name]
        if name != "bound" and v is not None and not math.isfinite(v):
            raise fail(f"'{name}' = {v} is not finite; the model file is corrupt, retrain it")
    if not kw["y_scale"] > 0:
        raise fail(f"'y_scale' = {kw['y_scale']:g} must be > 0 (the standard deviation of the training outputs)")
    if not np.all(kw["x_scale"] > 0):
        raise fail(f"'x_scale' = {kw['x_scale'].tolist()} must be > 0 in every column")
    logs = {n: np.atleast_1d(kw[n]) for n in cls.log_parameters() if kw.get(n) is not None}
    for name, v in logs.items():
        if v.size and np.max(np.abs(v)) > _MAX_LOG_PARAMETER:
            raise fail(f"log-parameter '{name}' = {float(v[np.argmax(np.abs(v))]):g} is beyond "
                       f"±{_MAX_LOG_PARAMETER:g}; the model file is corrupt, retrain it")
    if not re.fullmatch(r"[0-9a-f]{64}", kw["training_hash"]):
        raise fail(f"training_hash {kw['training_hash'][:24]!r} is not a SHA-256 hex digest (64 hex digits)")


def _check_belong_together(kw: dict, model: Any, fail: Any) -> np.ndarray:
    """X and the encoded outputs standardised, the factors those of the stored kernels; the checked rows.

    A sparse model (``posterior_form == "sparse"``) stores inducing inputs, not the data, and
    factors of K(Z, Z) + R with R a full pseudo-noise covariance: there, R must be symmetric
    positive semi-definite (checked on every eigenvalue) instead.
    """
    if kw["posterior_form"] == "sparse":
        return _check_sparse_factors(kw, model, fail)
    X = kw["X"]
    n, d = X.shape
    col_mean, col_std = X.mean(axis=0), X.std(axis=0)
    for j in range(d):
        const_tol = _STANDARD_TOL * max(1.0, abs(float(kw["x_mean"][j])))
        if abs(col_mean[j]) > _STANDARD_TOL or not (abs(col_std[j] - 1.0) <= _STANDARD_TOL or col_std[j] <= const_tol):
            raise fail(f"the stored arrays do not belong together: column {j} of 'X' has mean {col_mean[j]:.3g} and "
                       f"standard deviation {col_std[j]:.3g}, not the standardised 0 and 1 of a fit; the file was "
                       "edited or assembled from two models, retrain it")
    Lf, Lg = kw["f_chol"], kw["g_chol"]
    if n > 1:
        ys = Lf @ (Lf.T @ kw["f_alpha"])
        if abs(float(ys.mean())) > _STANDARD_TOL or abs(float(ys.std()) - 1.0) > _STANDARD_TOL:
            raise fail(f"the stored arrays do not belong together: the training outputs they encode "
                       f"(f_chol f_cholᵀ f_alpha) have mean {ys.mean():.3g} and standard deviation {ys.std():.3g}, "
                       "not the standardised 0 and 1 of a fit; the file was edited or assembled from two models, "
                       "retrain it")
    rows = _check_rows(n)
    kernels = {"f": model.f_kernel, "g": model.g_kernel}
    for label, L in (("f", Lf), ("g", Lg)):
        G = L[rows] @ L.T  # rows of L Lᵀ
        Kr = kernels[label].matrix(X[rows], X)
        diag_all = np.einsum("ij,ij->i", L, L)
        tol = _FACTOR_RTOL * np.sqrt(np.outer(diag_all[rows], diag_all)) + 1e-300
        off = np.ones_like(G, dtype=bool)
        off[np.arange(len(rows)), rows] = False
        diff = np.where(off, np.abs(G - Kr), 0.0)
        excess = G[np.arange(len(rows)), rows] - Kr[np.arange(len(rows)), rows]
        if label == "g":
            want = np.exp(-kw["log_lambda"][rows])
            diag_bad = np.abs(excess - want) > _FACTOR_RTOL * np.maximum(diag_all[rows], 1.0) * 1e2
        else:
            diag_bad = excess < -tol[np.arange(len(rows)), rows]
        if (diff > tol).any() or diag_bad.any():
            raise fail(f"the stored arrays do not belong together: {label}_chol is not the factor of the kernel of "
                       f"'X' with the stored {label} hyperparameters (K_{label}(X, X)"
                       f"{' + Λ⁻¹' if label == 'g' else ' + noise'}); the file was edited or assembled from two "
                       "models, retrain it")
    return rows


def _check_sparse_factors(kw: dict, model: Any, fail: Any) -> np.ndarray:
    """A sparse model's ``L Lᵀ − K(Z, Z)`` positive semi-definite for f and g; all rows checked."""
    Z = kw["X"]
    for label, L, k in (("f", kw["f_chol"], model.f_kernel), ("g", kw["g_chol"], model.g_kernel)):
        if np.any(np.triu(L, 1) != 0):
            raise fail(f"the stored arrays do not belong together: {label}_chol is not lower triangular; the file "
                       "was edited, retrain it")
        R = L @ L.T - k.matrix(Z, Z)
        scale = float(np.max(np.abs(np.diag(L @ L.T)))) or 1.0
        if not np.all(np.isfinite(R)) or float(np.linalg.eigvalsh(0.5 * (R + R.T)).min()) < -1e-6 * scale:
            raise fail(f"the stored arrays do not belong together: {label}_chol {label}_cholᵀ − K_{label}(Z, Z) is not "
                       f"positive semi-definite (a sparse model's pseudo-noise covariance); the file was edited or "
                       "assembled from two models, retrain it")
    return _check_rows(Z.shape[0])


def _check_rows(n: int) -> np.ndarray:
    """At most ``_N_CHECK_ROWS`` evenly spaced distinct row indices of n, ascending (without
    ``np.unique``, whose first call imports ``numpy.ma``, a noticeable part of a one-shot solve:
    ``python -X importtime -c 'import numpy.ma'``)."""
    r = np.linspace(0, n - 1, min(n, _N_CHECK_ROWS)).astype(int)
    return r[np.concatenate([[True], r[1:] != r[:-1]])] if r.size else r


def _check_variances(kw: dict, model: Any, rows: np.ndarray, fail: Any) -> None:
    """Predictive variances far from the data and at the checked rows at most :data:`_MAX_MODEL_VARIANCE`."""
    two_log_ys = 2.0 * math.log(kw["y_scale"])
    log_kff = np.logaddexp(kw["f_log_signal_var"], kw["f_log_bias_var"] if kw["f_log_bias_var"] is not None else -np.inf)
    kgg = math.exp(kw["g_log_signal_var"]) + (math.exp(kw["g_log_bias_var"]) if kw["g_log_bias_var"] is not None else 0.0)
    log_max = math.log(_MAX_MODEL_VARIANCE)
    for what, log_var in (("epistemic", two_log_ys + float(log_kff)),
                          ("noise", kw["g_mu0"] + two_log_ys + 0.5 * kgg)):
        if log_var > log_max:
            raise fail(f"the model's {what} variance far from the data is e^{log_var:.4g} (units of y²), beyond "
                       f"{_MAX_MODEL_VARIANCE:g} (y_scale = {kw['y_scale']:g}); later arithmetic would overflow: the "
                       "file is corrupt or the fit diverged, retrain it")
    X_orig = kw["X"][rows] * kw["x_scale"] + kw["x_mean"]
    try:
        with np.errstate(over="raise", invalid="raise"):
            pred = model.predict(X_orig)
    except (OverflowError, FloatingPointError, DataError) as exc:
        raise fail(f"predicting at the training inputs overflows ({exc}); the file is corrupt or the fit "
                   "diverged, retrain it") from None
    worst = float(np.max(pred.y_var))
    if not (np.all(np.isfinite(pred.y_mean)) and np.isfinite(worst)) or worst > _MAX_MODEL_VARIANCE:
        raise fail(f"the model's predictive variance at its training inputs reaches {worst:.3g} (units of y²), beyond "
                   f"{_MAX_MODEL_VARIANCE:g}; later arithmetic would overflow: the file is corrupt or the fit "
                   "diverged, retrain it")
