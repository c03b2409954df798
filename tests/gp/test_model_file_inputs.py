"""Model files that cannot come from a fit are refused at load, one clear line (issue 12)."""

from __future__ import annotations

import json
import warnings
from pathlib import Path

import numpy as np
import pytest

from microctl.cli import main
from microctl.errors import DataError
from microctl.gp.vhgpr import FittedVHGPR
from microctl.models.afm import AnalyticForwardModel
from microctl.stage.config import load_stage_config

ROOT = Path(__file__).resolve().parents[2]
CONFIG = ROOT / "configs/stage/table1.yaml"


@pytest.fixture(scope="module")
def model_path(tmp_path_factory, planted_log) -> Path:
    """A residual model trained by ``microctl train`` on a 40-row log of the Table I stage."""
    out = tmp_path_factory.mktemp("model") / "model.npz"
    assert main(["train", str(planted_log), "--config", str(CONFIG), "-o", str(out), "--restarts", "1",
                 "--quiet"]) == 0
    return out


def _variant(src: Path, dst: Path, **arrays) -> Path:
    with np.load(src) as npz:
        data = {k: npz[k] for k in npz.files}
    for k, v in arrays.items():
        data[k] = v(data) if callable(v) else np.asarray(v)
    np.savez(dst, **data)
    return dst


def _meta(**changes):
    def f(data):
        meta = json.loads(str(data["meta_json"]))
        meta.update(changes)
        return np.array(json.dumps(meta))
    return f


def _set(name, index, value):
    def f(data):
        a = data[name].copy()
        a[index] = value
        return a
    return f


def test_trained_model_loads(model_path):
    assert FittedVHGPR.load(model_path).X.shape == (40, 8)


@pytest.mark.parametrize("arrays, match", [
    ({"X": _set("X", (3, 2), np.nan)}, r"array 'X' has a non-finite value \(nan\) at index \[3, 2\]"),
    ({"f_chol": _set("f_chol", (5, 1), np.inf)}, r"array 'f_chol' has a non-finite value \(inf\)"),
    ({"y_scale": np.inf}, r"'y_scale' = inf is not finite"),
    ({"y_scale": -1.0}, r"'y_scale' = -1 must be > 0"),
    ({"y_scale": 1e200}, r"the model's epistemic variance far from the data is e\^9\d\d.* beyond 1e\+100 \(y_scale = 1e\+200\)"),
    ({"g_mu0": 250.0}, r"the model's noise variance far from the data is e\^2\d\d"),
    ({"f_log_signal_var": 800.0}, r"log-parameter 'f_log_signal_var' = 800 is beyond ±300"),
    ({"g_log_signal_var": 1e5}, r"log-parameter 'g_log_signal_var' = 100000 is beyond ±300"),
    ({"meta_json": _meta(training_hash="abc")}, r"training_hash 'abc' is not a SHA-256 hex digest"),
    ({"X": _set("X", (0, 0), 1.7)}, r"the stored arrays do not belong together: column 0 of 'X'"),
    ({"f_alpha": lambda d: d["f_alpha"] * 2}, r"the stored arrays do not belong together: the training outputs they encode"),
    ({"f_log_bias_var": lambda d: d["f_log_bias_var"] + 0.5},  # in play whether or not f's SE part is
     r"the stored arrays do not belong together: f_chol is not the factor of the kernel of 'X'"),
    ({"log_lambda": _set("log_lambda", 7, 3.0)}, r"the stored arrays do not belong together: g_chol is not the factor .*Λ⁻¹"),
    ({"X": lambda d: d["X"][::-1].copy()}, r"the stored arrays do not belong together: f_chol is not the factor"),
])
def test_bad_model_files_refused(model_path, tmp_path, arrays, match):
    bad = _variant(model_path, tmp_path / "bad.npz", **arrays)
    with pytest.raises(DataError, match=r"bad\.npz: " + match):
        FittedVHGPR.load(bad)


def test_arrays_from_two_models_refused(model_path, tmp_path):
    """Factors of one fit with the inputs of another (same shapes) are caught."""
    other = tmp_path / "other.npz"
    log = tmp_path / "log2.csv"
    afm = AnalyticForwardModel(load_stage_config(CONFIG).stage)
    rng = np.random.default_rng(11)
    U = afm.workspace.sample(40, rng)
    Q = U @ afm.K.T
    t = afm.t_of(U) + 0.1 * rng.standard_normal(40)
    lines = ["seq,u_z,u_rx,u_ry,q1,q2,q3,q4,t"]
    lines += [",".join([str(k)] + [f"{v:.9g}" for v in (*U[k], *Q[k], t[k])]) for k in range(40)]
    log.write_text("\n".join(lines) + "\n")
    assert main(["train", str(log), "--config", str(CONFIG), "-o", str(other), "--restarts", "1", "--quiet"]) == 0
    with np.load(other) as npz:
        X_other = npz["X"].copy()
    bad = _variant(model_path, tmp_path / "mixed.npz", X=X_other)
    with pytest.raises(DataError, match=r"mixed\.npz: the stored arrays do not belong together"):
        FittedVHGPR.load(bad)


def test_csv_and_directory_as_model(tmp_path):
    csv = tmp_path / "log.csv"
    csv.write_text("seq,time_s,u_z\n0,0,1\n")
    with pytest.raises(DataError, match=r"log\.csv: not a VHGPR model file \(\.npz\): it is a text file starting "
                                        r"with 'seq,time_s,u_z' \(a CSV or YAML file\?\)") as info:
        FittedVHGPR.load(csv)
    assert "allow_pickle" not in str(info.value)
    with pytest.raises(DataError, match=r"not a VHGPR model file \(\.npz\): it is a directory"):
        FittedVHGPR.load(tmp_path)
    empty = tmp_path / "empty.npz"
    empty.write_bytes(b"")
    with pytest.raises(DataError, match=r"empty\.npz: not a VHGPR model file \(\.npz\): the file is empty"):
        FittedVHGPR.load(empty)


@pytest.mark.parametrize("arrays", [{"y_scale": 1e200}, {"f_log_signal_var": 800.0}, {"g_mu0": 250.0}])
def test_cli_solve_huge_variance_one_line(model_path, tmp_path, capsys, arrays):
    bad = _variant(model_path, tmp_path / "huge.npz", **arrays)
    rc = main(["solve", "--config", str(CONFIG), "--model", str(bad), "--target", "5"])
    err = capsys.readouterr().err
    assert rc == 2 and err.count("\n") == 1 and err.startswith("microctl: error: ") and "huge.npz" in err, err


def test_cli_solve_csv_model_one_line(model_path, tmp_path, capsys):
    csv = tmp_path / "log.csv"
    csv.write_text("seq,time_s,u_z\n0,0,1\n")
    rc = main(["solve", "--config", str(CONFIG), "--model", str(csv), "--target", "5"])
    err = capsys.readouterr().err
    assert rc == 2 and err.count("\n") == 1 and "a text file" in err and "pickle" not in err


def test_cli_solve_refuses_a_residual_model_of_absurd_size(model_path, tmp_path, capsys):
    """Found by the fuzz test: y_scale × 1e10 passes load (variance < 1e100) but IPOPT then fails (exit 1)."""
    bad = _variant(model_path, tmp_path / "scaled.npz", y_scale=lambda d: d["y_scale"] * 1e10)
    rc = main(["solve", "--config", str(CONFIG), "--model", str(bad), "--target", "5"])
    err = capsys.readouterr().err
    assert rc == 2 and err.count("\n") == 1, err
    assert "the residual model's y_scale = " in err and "beyond what stage 'table1' can produce" in err


@pytest.mark.parametrize("dtype, match", [
    (np.complex128, r"array 'X' has dtype complex128; a model file holds real numbers"),
    ("U8", r"array 'X' has dtype <U8"),
    (object, r"array 'X' holds Python objects \(pickled data\), which a model file never does"),
])
def test_wrong_dtype_refused_not_cast(model_path, tmp_path, dtype, match):
    """Found by the fuzz test: a complex X was cast to real with a ComplexWarning (two more stderr lines)."""
    bad = tmp_path / "dtype.npz"
    with np.load(model_path) as npz:
        data = {k: npz[k] for k in npz.files}
    data["X"] = data["X"].astype(dtype)
    np.savez(bad, **data)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no warning on the way to the error
        with pytest.raises(DataError, match=r"dtype\.npz: not a VHGPR model file \(\.npz\): " + match) as info:
            FittedVHGPR.load(bad)
    assert "allow_pickle" not in str(info.value)


def test_huge_finite_value_refused_without_warnings(model_path, tmp_path):
    """Found by the fuzz test: X[0, 0] = 1e300 made the standardisation check overflow with a RuntimeWarning."""
    bad = _variant(model_path, tmp_path / "huge.npz", X=_set("X", (0, 0), 1e300))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(DataError, match=r"huge\.npz: the stored arrays do not belong together: column 0 of 'X'"):
            FittedVHGPR.load(bad)


def test_nonpositive_x_scale_refused(model_path, tmp_path):
    bad = _variant(model_path, tmp_path / "xs.npz", x_scale=lambda d: -d["x_scale"])
    with pytest.raises(DataError, match=r"xs\.npz: 'x_scale' = \[.*\] must be > 0 in every column"):
        FittedVHGPR.load(bad)


def test_variance_overflowing_at_the_training_inputs_refused(model_path, tmp_path):
    """g_beta is not tied to the factors: huge values pass those checks, the prediction at X overflows."""
    def huge(d):  # mu = K_g g_beta + mu0 of about 1e4 at the training inputs: exp() overflows
        return d["g_beta"] + 1e4 / (np.exp(float(d["g_log_signal_var"])) * d["g_beta"].size)

    bad = _variant(model_path, tmp_path / "beta.npz", g_beta=huge)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(DataError, match=r"beta\.npz: (predicting at the training inputs overflows|the model's "
                                            r"predictive variance at its training inputs reaches)"):
            FittedVHGPR.load(bad)
