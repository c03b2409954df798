"""Tests of the VHGPR trainer (microctl.vhgpr) and the ``gp`` commands.

Each test checks against an answer computed independently of the code under test:
loops instead of vectorised kernels, direct matrix inverses and textbook Gaussian
formulas instead of the stable B-forms, central finite differences instead of the
analytic gradient, a planted noise function, published benchmark numbers.
"""

from __future__ import annotations

import csv
import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest
from scipy.stats import multivariate_normal

import microctl.vhgpr as vh
from microctl.cli import main
from microctl.errors import ConfigError, DataError, MicroctlError
from microctl.vhgpr import FORMAT_VERSION, VHGPR, FittedVHGPR, VHGPRPrediction, ard_se

# shared/ sits beside the repository (here and in CI): the motorcycle benchmark data
MCYCLE = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "mcycle.csv"


def _mcycle() -> tuple[np.ndarray, np.ndarray]:
    data = np.loadtxt(MCYCLE, delimiter=",", skiprows=1)
    return data[:, :1], data[:, 1]


def _planted(n: int, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Data with a known mean f and a known log noise variance g (a bump of noise at x = 0.7)."""
    rng = np.random.default_rng(seed)
    x = rng.uniform(0.0, 1.0, n)
    f = np.sin(2 * np.pi * x) + 0.5 * x
    sd = 0.1 + 0.5 * np.exp(-0.5 * ((x - 0.7) / 0.15) ** 2)
    return x[:, None], f + sd * rng.standard_normal(n), f, 2 * np.log(sd)


@pytest.fixture(scope="module")
def mcycle_model() -> FittedVHGPR:
    X, y = _mcycle()
    return VHGPR().fit(X, y)


@pytest.fixture(scope="module")
def small_model() -> FittedVHGPR:
    X, y, _, _ = _planted(40, seed=3)
    return VHGPR(n_restarts=1, max_iter=60).fit(X, y)


# --------------------------------------------------------------------------- kernel


def test_ard_se_matches_double_loop() -> None:
    rng = np.random.default_rng(0)
    Xa, Xb = rng.standard_normal((4, 3)), rng.standard_normal((5, 3))
    ls, lsf, lb = np.array([0.1, -0.3, 0.7]), 0.4, -1.2
    ref = np.empty((4, 5))
    for i in range(4):
        for j in range(5):
            r2 = sum(((Xa[i, k] - Xb[j, k]) / math.exp(ls[k])) ** 2 for k in range(3))
            ref[i, j] = math.exp(lsf) * math.exp(-0.5 * r2) + math.exp(lb)
    np.testing.assert_allclose(ard_se(Xa, Xb, ls, lsf, lb), ref, rtol=1e-12)
    np.testing.assert_allclose(ard_se(Xa, Xb, ls, lsf, None), ref - math.exp(lb), rtol=1e-12)


# --------------------------------------------------------------------------- the bound and its gradient


def _theta(rng: np.random.Generator, layout: "vh._Layout") -> np.ndarray:
    k = layout.n_kernel
    return np.concatenate([
        rng.normal(-0.5, 0.8, layout.n),  # log lambda, spread over ~ [0.1, 3]
        rng.normal(0.0, 0.3, k),  # f kernel
        rng.normal(0.0, 0.3, k),  # g kernel
        [-1.0],  # mu0
    ])


def _naive_bound(theta: np.ndarray, X: np.ndarray, y: np.ndarray, layout: "vh._Layout") -> float:
    """The MV bound from the textbook formulas (direct inverses, scipy's Gaussian density)."""
    n = layout.n
    lam = np.exp(theta[:n])
    Kf = ard_se(X, X, *layout.kernel(theta[layout.f_slice]))
    Kg = ard_se(X, X, *layout.kernel(theta[layout.g_slice]))
    mu0 = theta[-1]
    Sigma = np.linalg.inv(np.linalg.inv(Kg) + np.diag(lam))
    mu = Kg @ (lam - 0.5) + mu0
    R = np.diag(np.exp(mu - np.diag(Sigma) / 2))
    loglik = multivariate_normal(mean=np.zeros(n), cov=Kf + R).logpdf(y)
    Kg_inv = np.linalg.inv(Kg)
    dm = mu - mu0
    kl = 0.5 * (np.trace(Kg_inv @ Sigma) + dm @ Kg_inv @ dm - n
                + np.linalg.slogdet(Kg)[1] - np.linalg.slogdet(Sigma)[1])
    return float(loglik - kl - np.trace(Sigma) / 4)


@pytest.mark.parametrize("bias", [False, True])
def test_bound_matches_textbook_formulas(bias: bool) -> None:
    rng = np.random.default_rng(1)
    n, d = 12, 2
    X, y = rng.standard_normal((n, d)), rng.standard_normal(n)
    layout = vh._Layout(n=n, d=d, bias=bias)
    for _ in range(3):
        theta = _theta(rng, layout)
        F, _, _ = vh._mv_bound(theta, X, y, layout, want_grad=False)
        assert F == pytest.approx(_naive_bound(theta, X, y, layout), rel=1e-8, abs=1e-8)


@pytest.mark.parametrize("bias", [False, True])
def test_gradient_matches_central_differences_per_block(bias: bool) -> None:
    rng = np.random.default_rng(2)
    n, d = 15, 2
    X, y = rng.standard_normal((n, d)), rng.standard_normal(n)
    layout = vh._Layout(n=n, d=d, bias=bias)
    theta = _theta(rng, layout)
    _, grad, _ = vh._mv_bound(theta, X, y, layout)
    h = 1e-5
    fd = np.empty_like(theta)
    for i in range(theta.size):
        e = np.zeros_like(theta)
        e[i] = h
        fd[i] = (vh._mv_bound(theta + e, X, y, layout, want_grad=False)[0]
                 - vh._mv_bound(theta - e, X, y, layout, want_grad=False)[0]) / (2 * h)
    blocks = {
        "log lambda": slice(0, n),
        "f hyperparameters": layout.f_slice,
        "g hyperparameters": layout.g_slice,
        "mu0": slice(layout.size - 1, layout.size),
    }
    for name, sl in blocks.items():
        # central differences with h = 1e-5 are accurate to ~h^2 * F''' + eps * F / h ~ 1e-9
        np.testing.assert_allclose(grad[sl], fd[sl], rtol=1e-6, atol=1e-7, err_msg=name)
        assert np.any(np.abs(grad[sl]) > 1e-3), f"{name}: gradient unexpectedly ~0, test would be vacuous"


def test_gradient_of_homoscedastic_likelihood() -> None:
    rng = np.random.default_rng(4)
    n, d = 10, 2
    X, y = rng.standard_normal((n, d)), rng.standard_normal(n)
    theta = np.array([0.2, -0.3, 0.1, -1.5, -2.0])  # ls (2), signal, bias, noise
    _, g = vh._gp_loglik(theta, X, y, d, True)
    fd = np.array([(vh._gp_loglik(theta + e, X, y, d, True)[0] - vh._gp_loglik(theta - e, X, y, d, True)[0]) / 2e-5
                   for e in np.eye(theta.size) * 1e-5])
    np.testing.assert_allclose(g, fd, rtol=1e-6, atol=1e-8)


# --------------------------------------------------------------------------- the fitted model


def test_prediction_at_training_inputs_matches_variational_posterior(small_model: FittedVHGPR) -> None:
    m = small_model
    lam = np.exp(m.log_lambda)
    Kf = ard_se(m.X, m.X, m.f_log_lengthscales, m.f_log_signal_var, m.f_log_bias_var)
    Kg = ard_se(m.X, m.X, m.g_log_lengthscales, m.g_log_signal_var, m.g_log_bias_var)
    # notes: mu = K_g (Lambda - I/2) 1 + mu0,  Sigma = (K_g^-1 + Lambda)^-1
    mu = Kg @ (lam - 0.5) + m.g_mu0
    # (K_g^-1 + Lambda)^-1 by the matrix inversion lemma: K_g is too ill-conditioned at the
    # fitted lengthscale to be inverted directly.
    Sigma = Kg - Kg @ np.linalg.solve(Kg + np.diag(1 / lam), Kg)
    X_orig = m.X * m.x_scale + m.x_mean
    p = m.predict(X_orig)
    np.testing.assert_allclose(p.g_mean - 2 * math.log(m.y_scale), mu, rtol=1e-8, atol=1e-8)
    np.testing.assert_allclose(p.g_var, np.diag(Sigma), rtol=1e-6, atol=1e-8)
    # f at the training inputs: K_f (K_f + R)^-1 ys with R = diag(exp(mu - Sigma_ii/2))
    R = np.diag(np.exp(mu - np.diag(Sigma) / 2))
    _, y, _, _ = _planted(40, seed=3)  # the data small_model was fitted to
    ys = (y - y.mean()) / y.std()
    np.testing.assert_allclose((p.f_mean - m.y_mean) / m.y_scale, Kf @ np.linalg.solve(Kf + R, ys),
                               rtol=1e-7, atol=1e-8)
    cov_f = Kf - Kf @ np.linalg.solve(Kf + R, Kf)
    np.testing.assert_allclose(p.f_var / m.y_scale**2, np.diag(cov_f), rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose(p.y_var, p.f_var + np.exp(p.g_mean + p.g_var / 2), rtol=1e-12)
    np.testing.assert_array_equal(p.y_mean, p.f_mean)
    # the stored bound is the bound at the stored parameters (same lemma for the KL terms:
    # tr(K^-1 Sigma) = n - tr(Lambda Sigma), log|K| - log|Sigma| = log|I + K Lambda|)
    n = lam.size
    beta = lam - 0.5
    kl = 0.5 * (n - np.sum(lam * np.diag(Sigma)) + beta @ Kg @ beta - n
                + np.linalg.slogdet(np.eye(n) + Kg * lam[None, :])[1])
    loglik = multivariate_normal(mean=np.zeros(n), cov=Kf + R).logpdf(ys)
    assert m.bound == pytest.approx(loglik - kl - np.trace(Sigma) / 4, rel=1e-7)


def test_fitted_model_is_frozen(small_model: FittedVHGPR) -> None:
    with pytest.raises(dataclasses.FrozenInstanceError):
        small_model.g_mu0 = 0.0  # type: ignore[misc]
    with pytest.raises(ValueError):
        small_model.f_alpha[0] = 1.0
    assert isinstance(small_model.predict(np.zeros((2, 1))), VHGPRPrediction)


def test_fit_is_reproducible_with_seed() -> None:
    X, y, _, _ = _planted(30, seed=5)
    a = VHGPR(n_restarts=2, max_iter=30, random_state=7).fit(X, y)
    b = VHGPR(n_restarts=2, max_iter=30, random_state=7).fit(X, y)
    np.testing.assert_array_equal(a.log_lambda, b.log_lambda)
    assert a.bound == b.bound
    assert a.info["restarts_tried"] == 2 and a.info["restarts_failed"] == 0
    assert a.training_hash == b.training_hash and len(a.training_hash) == 64


def test_save_load_round_trip(tmp_path: Path, small_model: FittedVHGPR) -> None:
    model = dataclasses.replace(small_model, x_names=("x",), y_name="y", geometry_hash="abc")
    path = tmp_path / "m.npz"
    model.save(path)
    with np.load(path, allow_pickle=False) as raw:  # no pickled objects inside
        assert int(raw["format_version"]) == FORMAT_VERSION
    loaded = FittedVHGPR.load(path)
    Xt = np.linspace(-0.2, 1.2, 17)[:, None]
    p, q = model.predict(Xt), loaded.predict(Xt)
    for name in ("f_mean", "f_var", "g_mean", "g_var", "y_mean", "y_var"):
        np.testing.assert_array_equal(getattr(p, name), getattr(q, name), err_msg=name)
    assert loaded.x_names == ("x",) and loaded.y_name == "y" and loaded.geometry_hash == "abc"
    assert loaded.f_log_bias_var is None and loaded.bound == model.bound
    assert loaded.training_hash == model.training_hash
    assert loaded.info["restarts_tried"] == model.info["restarts_tried"]


def _rewrite_npz(src: Path, dst: Path, *, drop: str | None = None, **replace: np.ndarray) -> None:
    with np.load(src, allow_pickle=False) as raw:
        arrays = {k: raw[k] for k in raw.files if k != drop}
    arrays.update(replace)
    np.savez(dst, **arrays)


def test_load_errors_name_the_file(tmp_path: Path, small_model: FittedVHGPR) -> None:
    good = tmp_path / "good.npz"
    small_model.save(good)
    wrong = tmp_path / "wrong_version.npz"
    _rewrite_npz(good, wrong, format_version=np.array(99))
    with pytest.raises(DataError, match=r"wrong_version\.npz.*version 99"):
        FittedVHGPR.load(wrong)
    missing = tmp_path / "missing.npz"
    _rewrite_npz(good, missing, drop="f_chol")
    with pytest.raises(DataError, match=r"missing\.npz.*missing array.*'f_chol'"):
        FittedVHGPR.load(missing)
    bad_shape = tmp_path / "bad_shape.npz"
    _rewrite_npz(good, bad_shape, g_beta=np.zeros(3))
    with pytest.raises(DataError, match=r"bad_shape\.npz.*'g_beta' has shape"):
        FittedVHGPR.load(bad_shape)
    text = tmp_path / "text.npz"
    text.write_text("not a model\n")
    with pytest.raises(DataError, match=r"text\.npz.*not a VHGPR model file"):
        FittedVHGPR.load(text)
    single = tmp_path / "single.npy"
    np.save(single, np.zeros(3))
    with pytest.raises(DataError, match=r"single\.npy.*not a VHGPR model file"):
        FittedVHGPR.load(single)
    with pytest.raises(DataError, match=r"nowhere\.npz.*no such model file"):
        FittedVHGPR.load(tmp_path / "nowhere.npz")


def test_save_to_missing_directory_is_data_error(tmp_path: Path, small_model: FittedVHGPR) -> None:
    with pytest.raises(DataError, match=r"nodir.*cannot write"):
        small_model.save(tmp_path / "nodir" / "m.npz")


# --------------------------------------------------------------------------- accuracy


def test_recovers_planted_heteroscedastic_noise() -> None:
    X, y, _, _ = _planted(300, seed=11)
    Xt, yt, ft, gt = _planted(2000, seed=12)
    model = VHGPR(n_restarts=1).fit(X, y)
    p = model.predict(Xt)
    # The true log noise variance spans 3.6 nats (sd 0.1 .. 0.6); with 300 points the learned
    # mean log-noise tracks its shape closely (measured r ~ 0.99 for several seeds), so 0.95
    # leaves margin for seed-to-seed variation while still failing for a homoscedastic fit (r ~ 0).
    assert np.corrcoef(p.g_mean, gt)[0, 1] >= 0.95
    sd = np.exp(gt / 2)
    oracle = np.mean(0.5 * np.log(2 * np.pi * sd**2) + 0.5 * (yt - ft) ** 2 / sd**2)
    # The oracle knows f and g exactly; estimation error in f and g from 300 points costs
    # ~0.02 nats here (measured), the issue allows 0.05.
    assert model.nlpd(Xt, yt) - oracle <= 0.05


def test_mcycle_nlpd(mcycle_model: FittedVHGPR) -> None:
    X, y = _mcycle()
    # Authors' MATLAB VHGPR on the same protocol: 4.07 nats; homoscedastic GP 4.51 (data/README.md).
    nlpd = mcycle_model.nlpd(X, y)
    assert nlpd <= 4.09
    assert mcycle_model.info["restarts_failed"] == 0


def test_duplicate_inputs_fit() -> None:
    X, y, _, _ = _planted(25, seed=8)
    Xd = np.vstack([X, X, X[:5]])
    yd = np.concatenate([y, y + 0.05, y[:5] - 0.05])
    model = VHGPR(n_restarts=1, max_iter=50).fit(Xd, yd)
    p = model.predict(Xd)
    assert np.all(np.isfinite(p.y_mean)) and np.all(p.y_var > 0)
    assert np.isfinite(model.bound)


def test_all_restarts_failing_raises(monkeypatch: pytest.MonkeyPatch) -> None:
    def broken(*args: object, **kwargs: object) -> None:
        raise np.linalg.LinAlgError("forced failure")

    monkeypatch.setattr(vh, "_mv_bound", broken)
    X, y, _, _ = _planted(20, seed=1)
    with pytest.raises(MicroctlError, match="every optimisation run failed.*no finite bound"):
        VHGPR(n_restarts=2, max_iter=10).fit(X, y)


# --------------------------------------------------------------------------- input validation


@pytest.mark.parametrize(
    ("X", "y", "match"),
    [
        ([[0.0], [np.nan], [2.0]], [1.0, 2.0, 3.0], r"X has a non-finite value.*row 1"),
        ([[0.0], [1.0], [2.0]], [1.0, np.inf, 3.0], r"y has a non-finite value.*row 1"),
        (np.zeros((3, 1, 1)), [1.0, 2.0, 3.0], r"X has 3 dimensions"),
        ([[0.0], [1.0], [2.0]], [[1.0], [2.0], [3.0]], r"y has shape \(3, 1\); expected a 1-D"),
        ([[0.0], [1.0], [2.0]], [1.0, 2.0], r"X has 3 rows but y has 2 values"),
        ([[0.0]], [1.0], r"1 training point\(s\); at least 2"),
        ([[0.0], [1.0], [2.0]], [4.0, 4.0, 4.0], r"y is constant"),
        (np.zeros((3, 0)), [1.0, 2.0, 3.0], r"at least one input column"),
        ([["a"], ["b"]], [1.0, 2.0], r"X is not numeric"),
    ],
)
def test_fit_input_errors(X: object, y: object, match: str) -> None:
    with pytest.raises(DataError, match=match):
        VHGPR().fit(X, y)


def test_predict_input_errors(small_model: FittedVHGPR) -> None:
    with pytest.raises(DataError, match=r"expects shape \(m, 1\)"):
        small_model.predict(np.zeros((3, 2)))
    with pytest.raises(DataError, match="non-finite"):
        small_model.predict(np.array([[np.nan]]))
    with pytest.raises(DataError, match=r"y has shape \(2,\); expected \(3,\)"):
        small_model.nlpd(np.zeros((3, 1)), np.zeros(2))


@pytest.mark.parametrize("kwargs", [{"n_restarts": 0}, {"max_iter": 0}, {"tol": -1.0}, {"max_time": 0}])
def test_bad_settings(kwargs: dict) -> None:
    with pytest.raises(ConfigError):
        VHGPR(**kwargs)


# --------------------------------------------------------------------------- command line


def _write_csv(path: Path, header: list[str], rows: list[list[object]]) -> None:
    with path.open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(header)
        w.writerows(rows)


def test_cli_fit_predict_round_trip(tmp_path: Path) -> None:
    X, y, _, _ = _planted(40, seed=21)
    data = tmp_path / "train.csv"
    _write_csv(data, ["u", "noise_free_junk", "resp"], [[x, 0, v] for x, v in zip(X[:, 0], y)])
    model_path = tmp_path / "gp.npz"
    assert main(["gp", "fit", str(data), "--x", "u", "--y", "resp", "-o", str(model_path),
                 "--restarts", "1", "--seed", "3", "--quiet"]) == 0
    model = FittedVHGPR.load(model_path)
    assert model.x_names == ("u",) and model.y_name == "resp"
    query = tmp_path / "query.csv"
    Xq = np.linspace(0, 1, 9)
    _write_csv(query, ["other", "u"], [[1, x] for x in Xq])
    out = tmp_path / "pred.csv"
    assert main(["gp", "predict", str(model_path), str(query), "-o", str(out)]) == 0
    with out.open() as fh:
        rows = list(csv.reader(fh))
    assert rows[0] == ["mean", "var"] and len(rows) == 1 + Xq.size
    got = np.array(rows[1:], dtype=float)
    p = model.predict(Xq[:, None])
    np.testing.assert_array_equal(got[:, 0], p.y_mean)
    np.testing.assert_array_equal(got[:, 1], p.y_var)


def test_cli_input_errors(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    data = tmp_path / "d.csv"
    _write_csv(data, ["a", "b"], [[1, 5], [2, 5], [3, 5]])
    out = tmp_path / "gp.npz"
    assert main(["gp", "fit", str(data), "--x", "a", "--y", "c", "-o", str(out)]) == 2
    err = capsys.readouterr().err
    assert "d.csv" in err and "'c'" in err and len(err.strip().splitlines()) == 1
    assert main(["gp", "fit", str(data), "--x", "a", "--y", "b", "-o", str(out)]) == 2
    err = capsys.readouterr().err
    assert "d.csv" in err and "y is constant" in err
    bad = tmp_path / "bad.csv"
    _write_csv(bad, ["a", "b"], [[1, 5], ["x", 6], [3, 7]])
    assert main(["gp", "fit", str(bad), "--x", "a", "--y", "b", "-o", str(out)]) == 2
    err = capsys.readouterr().err
    assert "bad.csv" in err and "row 3" in err and "'a'" in err
    assert main(["gp", "predict", str(tmp_path / "none.npz"), str(data), "-o", str(tmp_path / "p.csv")]) == 2
    assert "none.npz" in capsys.readouterr().err


# --------------------------------------------------------------------------- linear prior mean


def test_linear_mean_recovers_a_planted_trend_and_extrapolates(tmp_path: Path) -> None:
    """y = 2 + 0.8 x1 − 0.5 x2 + 0.3 sin(3 x1) + noise on [0, 1]²; the linear prior mean's
    coefficients (original units) must match ordinary least squares computed here directly;
    far outside the data the GP part reverts to its prior, so the prediction *is* the OLS
    plane (to rounding), while a constant-mean GP reverts to the output mean, > 1.5 off the
    trend there (measured 4.4 and 4.7; seeded)."""
    rng = np.random.default_rng(11)
    X = rng.uniform(0, 1, (120, 2))
    trend = lambda Z: 2 + 0.8 * Z[:, 0] - 0.5 * Z[:, 1]  # noqa: E731
    y = trend(X) + 0.3 * np.sin(3 * X[:, 0]) + 0.1 * rng.standard_normal(120)
    lin = VHGPR(mean="linear", n_restarts=1, random_state=0).fit(X, y)
    const = VHGPR(mean="constant", n_restarts=1, random_state=0).fit(X, y)
    A = np.column_stack([np.ones(120), X])
    ols = np.linalg.lstsq(A, y, rcond=None)[0]
    coef_orig = lin.mean_coef * lin.y_scale / lin.x_scale
    np.testing.assert_allclose(coef_orig, ols[1:], rtol=1e-10)
    far = np.array([[4.0, -3.0], [-3.0, 4.0]])
    plane = np.column_stack([np.ones(2), far]) @ ols
    np.testing.assert_allclose(lin.predict(far).f_mean, plane, atol=1e-9)
    assert np.all(np.abs(const.predict(far).f_mean - trend(far)) > 1.5)
    # persisted
    lin.save(tmp_path / "lin.npz")
    back = FittedVHGPR.load(tmp_path / "lin.npz")
    np.testing.assert_array_equal(back.mean_coef, lin.mean_coef)
    np.testing.assert_array_equal(back.predict(far).f_mean, lin.predict(far).f_mean)
    assert const.mean_coef is None and FittedVHGPR.load(_saved(const, tmp_path)).mean_coef is None


def _saved(model: FittedVHGPR, tmp_path: Path) -> Path:
    path = tmp_path / "const.npz"
    model.save(path)
    return path


def test_linear_mean_bad_setting() -> None:
    with pytest.raises(ConfigError, match="mean must be 'constant' or 'linear', got 'quadratic'"):
        VHGPR(mean="quadratic")
