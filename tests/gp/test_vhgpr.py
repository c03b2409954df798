"""Tests of the VHGPR trainer (microctl.gp.vhgpr) and the ``gp`` commands.

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

import microctl.gp.bound as bound
import microctl.gp.homoscedastic as homoscedastic
import microctl.gp.trainer as trainer
from microctl.cli import main
from microctl.errors import ConfigError, DataError, MicroctlError
from microctl.gp.kernels import KernelSpec
from microctl.gp.noise_prior import NoiseFeatures
from microctl.gp.vhgpr import (
    FORMAT_VERSION,
    VHGPR,
    FittedVHGPR,
    VHGPRPrediction,
    ard_se,
)

# the motorcycle benchmark data, shipped with the tests (tests/data/README.md)
MCYCLE = Path(__file__).resolve().parents[1] / "data" / "mcycle.csv"


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


def _layout(n: int, d: int, bias: bool, linear: bool = False, p: int = 0) -> "bound.Layout":
    return bound.Layout(n=n, f=KernelSpec(d, bias=bias, linear=linear), g=KernelSpec(d, bias=bias), p=p)


def _theta(rng: np.random.Generator, layout: "bound.Layout") -> np.ndarray:
    return np.concatenate([
        rng.normal(-0.5, 0.8, layout.n),  # log lambda, spread over ~ [0.1, 3]
        rng.normal(0.0, 0.3, layout.f.size),  # f kernel
        rng.normal(0.0, 0.3, layout.g.size),  # g kernel
        [-1.0],  # mu0 = log c_0
        rng.normal(-1.0, 0.3, layout.p),  # log c_j of g's parametric prior mean
    ])


def _naive_bound(theta: np.ndarray, X: np.ndarray, y: np.ndarray, layout: "bound.Layout",
                 Phi: np.ndarray | None = None) -> float:
    """The MV bound from the textbook formulas (direct inverses, scipy's Gaussian density),
    kernels written out here by hand, g's prior mean m = log(c_0 + Phi c) (noise_prior eq. 1)."""
    n, d = X.shape
    lam = np.exp(theta[:n])

    def kernel(block, spec):
        ls, sf2 = block[:d], math.exp(block[d])
        D2 = (((X[:, None, :] - X[None, :, :]) / np.exp(ls)) ** 2).sum(-1)
        K = sf2 * np.exp(-0.5 * D2)
        i = d + 1
        if spec.bias:
            K += math.exp(block[i])
            i += 1
        if spec.linear:
            K += (X * np.exp(block[i:i + d])) @ X.T
        return K

    Kf = kernel(theta[layout.f_slice], layout.f)
    Kg = kernel(theta[layout.g_slice], layout.g)
    c = np.exp(theta[layout.mean_slice])
    m = np.log(c[0] + (Phi @ c[1:] if Phi is not None else 0.0)) * np.ones(n)
    Sigma = np.linalg.inv(np.linalg.inv(Kg) + np.diag(lam))
    mu = Kg @ (lam - 0.5) + m
    R = np.diag(np.exp(mu - np.diag(Sigma) / 2))
    loglik = multivariate_normal(mean=np.zeros(n), cov=Kf + R).logpdf(y)
    Kg_inv = np.linalg.inv(Kg)
    dm = mu - m
    kl = 0.5 * (np.trace(Kg_inv @ Sigma) + dm @ Kg_inv @ dm - n
                + np.linalg.slogdet(Kg)[1] - np.linalg.slogdet(Sigma)[1])
    return float(loglik - kl - np.trace(Sigma) / 4)


CASES = [(False, False, 0), (True, False, 0), (False, True, 2), (True, True, 3)]


@pytest.mark.parametrize("bias,linear,p", CASES)
def test_bound_matches_textbook_formulas(bias: bool, linear: bool, p: int) -> None:
    rng = np.random.default_rng(1)
    n, d = 12, 2
    X, y = rng.standard_normal((n, d)), rng.standard_normal(n)
    Phi = (X @ rng.standard_normal((d, p)) + 0.2) ** 2 if p else None
    layout = _layout(n, d, bias, linear, p)
    for _ in range(3):
        theta = _theta(rng, layout)
        F, _, _ = bound.mv_bound(theta, X, y, layout, want_grad=False, Phi=Phi)
        assert F == pytest.approx(_naive_bound(theta, X, y, layout, Phi), rel=1e-8, abs=1e-8)


@pytest.mark.parametrize("bias,linear,p", CASES)
def test_gradient_matches_central_differences_per_block(bias: bool, linear: bool, p: int) -> None:
    rng = np.random.default_rng(2)
    n, d = 15, 2
    X, y = rng.standard_normal((n, d)), rng.standard_normal(n)
    Phi = (X @ rng.standard_normal((d, p)) + 0.2) ** 2 if p else None
    layout = _layout(n, d, bias, linear, p)
    theta = _theta(rng, layout)
    _, grad, _ = bound.mv_bound(theta, X, y, layout, Phi=Phi)
    h = 1e-5
    fd = np.empty_like(theta)
    for i in range(theta.size):
        e = np.zeros_like(theta)
        e[i] = h
        fd[i] = (bound.mv_bound(theta + e, X, y, layout, want_grad=False, Phi=Phi)[0]
                 - bound.mv_bound(theta - e, X, y, layout, want_grad=False, Phi=Phi)[0]) / (2 * h)
    blocks = {
        "log lambda": slice(0, n),
        "f hyperparameters": layout.f_slice,
        "g hyperparameters": layout.g_slice,
        "g prior mean (mu0, log c)": layout.mean_slice,
    }
    for name, sl in blocks.items():
        # central differences with h = 1e-5 are accurate to ~h^2 * F''' + eps * F / h ~ 1e-9
        np.testing.assert_allclose(grad[sl], fd[sl], rtol=1e-6, atol=1e-7, err_msg=name)
        assert np.any(np.abs(grad[sl]) > 1e-3), f"{name}: gradient unexpectedly ~0, test would be vacuous"


def test_gradient_of_homoscedastic_likelihood() -> None:
    rng = np.random.default_rng(4)
    n, d = 10, 2
    X, y = rng.standard_normal((n, d)), rng.standard_normal(n)
    spec = KernelSpec(d, bias=True, linear=True)
    theta = np.array([0.2, -0.3, 0.1, -1.5, -0.7, 0.4, -2.0])  # ls (2), signal, bias, linear (2), noise
    _, g = homoscedastic.gp_loglik(theta, X, y, spec)
    fd = np.array([(homoscedastic.gp_loglik(theta + e, X, y, spec)[0] - homoscedastic.gp_loglik(theta - e, X, y, spec)[0]) / 2e-5
                   for e in np.eye(theta.size) * 1e-5])
    np.testing.assert_allclose(g, fd, rtol=1e-6, atol=1e-8)


def test_noise_parameter_covariance_is_the_fisher_information_inverse() -> None:
    """For a diagonal covariance A = R (f absent) the Fisher information of c is
    1/2 sum_i J_i J_i^T with J_i = [1, phi_i] / (c_0 + phi_i c): derived by hand from
    log N(y_i | 0, V_i), V_i = c_0 + phi_i c; plus the prior (mean(phi_j))^2 on the diagonal."""
    rng = np.random.default_rng(8)
    n, p = 50, 2
    Phi = rng.uniform(0, 3, (n, p))
    log_c = np.array([-1.0, -0.5, -2.0])
    V = np.exp(log_c[0]) + Phi @ np.exp(log_c[1:])
    state = {"r": V, "A_inv": np.diag(1.0 / V)}
    D = np.hstack([np.ones((n, 1)), Phi])
    J = D / V[:, None]
    info = 0.5 * J.T @ J + np.diag(np.mean(D, axis=0) ** 2)
    np.testing.assert_allclose(bound.mean_coef_covariance(state, log_c, Phi), np.linalg.inv(info), rtol=1e-10)


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
    # two restarts plus the run from unit lengthscales of g (g_start="both", the default)
    assert a.info["restarts_tried"] == 3 and a.info["restarts_failed"] == 0
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
    too_many = tmp_path / "too_many_lengthscales.npz"
    d = small_model.n_inputs
    _rewrite_npz(good, too_many, f_log_lengthscales=np.zeros(d + 1), g_log_lengthscales=np.zeros(d + 1))
    with pytest.raises(DataError, match=rf"too_many_lengthscales\.npz.*{d + 1} lengthscales for {d} inputs"):
        FittedVHGPR.load(too_many)
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


@pytest.mark.slow
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


@pytest.mark.slow
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

    monkeypatch.setattr(trainer, "mv_bound", broken)
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
    assert main(["gp", "predict", str(model_path), str(query), "--out", str(out)]) == 0
    with out.open() as fh:
        rows = list(csv.reader(fh))
    assert rows[0] == ["mean", "var"] and len(rows) == 1 + Xq.size
    got = np.array(rows[1:], dtype=float)
    p = model.predict(Xq[:, None])
    np.testing.assert_array_equal(got[:, 0], p.y_mean)
    np.testing.assert_array_equal(got[:, 1], p.y_var)
    # -o/--out as every other command; --output still accepted (hidden alias), the same file
    alias = tmp_path / "pred_alias.csv"
    assert main(["gp", "predict", str(model_path), str(query), "--output", str(alias)]) == 0
    assert alias.read_text() == out.read_text()


def test_cli_gp_out_is_required_once(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """``gp fit`` without -o/--out, or with both --out and the --output alias: one line, exit 2."""
    data = tmp_path / "d.csv"
    _write_csv(data, ["a", "b"], [[0, 1], [1, 2], [2, 2]])
    for extra, needle in (([], "one of the arguments -o/--out is required"),
                          (["--out", "a.npz", "--output", "b.npz"], "not allowed with argument -o/--out")):
        with pytest.raises(SystemExit) as exc:
            main(["gp", "fit", str(data), "--x", "a", "--y", "b", *extra])
        err = capsys.readouterr().err.strip().splitlines()
        assert exc.value.code == 2 and len(err) == 1 and needle in err[0]


def test_cli_input_errors(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    data = tmp_path / "d.csv"
    _write_csv(data, ["a", "b"], [[1, 5], [2, 5], [3, 5], [4, 5], [5, 5], [6, 5]])  # gp fit needs >= 5 rows
    out = tmp_path / "gp.npz"
    assert main(["gp", "fit", str(data), "--x", "a", "--y", "c", "-o", str(out)]) == 2
    err = capsys.readouterr().err
    assert "d.csv" in err and "'c'" in err and len(err.strip().splitlines()) == 1
    assert main(["gp", "fit", str(data), "--x", "a", "--y", "b", "-o", str(out)]) == 2
    err = capsys.readouterr().err
    assert "d.csv" in err and "y is constant" in err
    bad = tmp_path / "bad.csv"
    _write_csv(bad, ["a", "b"], [[1, 5], ["x", 6], [3, 7], [4, 8], [5, 9], [6, 1]])
    assert main(["gp", "fit", str(bad), "--x", "a", "--y", "b", "-o", str(out)]) == 2
    err = capsys.readouterr().err
    assert "bad.csv" in err and "row 3" in err and "'a'" in err
    assert main(["gp", "predict", str(tmp_path / "none.npz"), str(data), "-o", str(tmp_path / "p.csv")]) == 2
    assert "none.npz" in capsys.readouterr().err


# --------------------------------------------------------------------------- linear trend, SE selection, noise features


def test_affine_trend_extrapolates_along_the_weighted_trend() -> None:
    """y = 2 + 0.8 x1 - 0.5 x2 on [0, 1]^2 with noise std 0.02, except 30 % of the points
    that follow another trend (+1.5 x1) with std 1.0. The affine part of f is generalised
    least squares with the model's own noise weights: far outside the data the prediction
    follows the quiet trend (|error| < 0.15 at x = (4, -3) and (-3, 4)), whereas ordinary
    least squares on all points is pulled > 0.6 away by the noisy ones there. The noise
    levels come from a planted 0/1 column ``noisy`` used as a noise feature."""
    rng = np.random.default_rng(11)
    n = 150
    X = rng.uniform(0, 1, (n, 2))
    noisy = rng.random(n) < 0.3
    trend = lambda Z: 2 + 0.8 * Z[:, 0] - 0.5 * Z[:, 1]  # noqa: E731
    y = trend(X) + np.where(noisy, 1.5 * X[:, 0] + 1.0 * rng.standard_normal(n), 0.02 * rng.standard_normal(n))
    Xa = np.column_stack([X, noisy.astype(float)])
    nf = NoiseFeatures(np.array([[0.0, 0.0, 1.0]]), np.zeros(1), ("noisy",))
    m = VHGPR(linear=(0, 1), linear_prior_var=10.0, se="off", noise_features=nf, n_restarts=1).fit(Xa, y)
    far = np.array([[4.0, -3.0, 0.0], [-3.0, 4.0, 0.0]])
    assert np.all(np.abs(m.predict(far).f_mean - trend(far[:, :2])) < 0.15)
    ols = np.linalg.lstsq(np.column_stack([np.ones(n), X]), y, rcond=None)[0]
    assert np.all(np.abs(np.column_stack([np.ones(2), far[:, :2]]) @ ols - trend(far[:, :2])) > 0.6)


def test_se_part_is_kept_only_when_it_pays() -> None:
    """se="auto" (BIC on the bound): an affine truth drops f's SE part, a bump of height 1
    on an affine trend keeps it (both n = 120, noise std 0.05)."""
    rng = np.random.default_rng(12)
    X = rng.uniform(0, 1, (120, 2))
    noise = 0.05 * rng.standard_normal(120)
    affine = 1 + 0.5 * X[:, 0] - X[:, 1]
    bump = np.exp(-((X[:, 0] - 0.5) ** 2 + (X[:, 1] - 0.5) ** 2) / (2 * 0.15**2))
    a = VHGPR(linear=True, linear_prior_var=10.0, se="auto", n_restarts=1).fit(X, affine + noise)
    b = VHGPR(linear=True, linear_prior_var=10.0, se="auto", n_restarts=1).fit(X, affine + bump + noise)
    assert a.info["se_selection"]["kept_se"] is False
    assert b.info["se_selection"]["kept_se"] is True
    sel = b.info["se_selection"]
    # measured gain 30 nats against the penalty 1.5 log 120 = 7.2: kept with a margin
    assert sel["bound_with_se"] - sel["bound_affine"] > 2 * sel["penalty"]


@pytest.mark.slow
def test_noise_features_recover_planted_floor_and_friction() -> None:
    """Noise variance 0.03^2 + (0.05 dq)^2 with dq = x1 - x2 (x uniform in [0, 30]^2, a third
    of the rows with dq = 0 so the floor is identifiable): the fitted prior mean's c_0 and c_1
    (original units) within 30 % of the planted values (n = 300; ~3 standard errors, the
    reported c_std at this size)."""
    rng = np.random.default_rng(13)
    n = 300
    X = rng.uniform(0, 30, (n, 2))
    X[: n // 3, 1] = X[: n // 3, 0]
    dq = X[:, 0] - X[:, 1]
    y = 0.02 * X[:, 0] + np.sqrt(0.03**2 + (0.05 * dq) ** 2) * rng.standard_normal(n)
    nf = NoiseFeatures(np.array([[1.0, -1.0]]), np.zeros(1), ("dq",))
    m = VHGPR(linear=True, linear_prior_var=10.0, se="off", noise_features=nf, n_restarts=1).fit(X, y)
    c0 = math.exp(m.g_mu0) * m.y_scale**2
    c1 = math.exp(m.g_log_feature_coef[0])
    assert c0 == pytest.approx(0.03**2, rel=0.3)
    assert c1 == pytest.approx(0.05**2, rel=0.3)
    assert m.noise_model == "physical" and m.g_feature_names == ("dq",)


def test_bad_trend_and_se_settings() -> None:
    with pytest.raises(ConfigError, match="se must be 'on', 'off' or 'auto', got 'maybe'"):
        VHGPR(se="maybe")
    with pytest.raises(ConfigError, match="needs a linear trend"):
        VHGPR(se="off")
    with pytest.raises(ConfigError, match="linear_prior_var must be a positive number"):
        VHGPR(linear=True, linear_prior_var=-1.0)
    with pytest.raises(DataError, match="linear trend on input column 5; X has 2 columns"):
        VHGPR(linear=(5,)).fit(np.random.default_rng(0).random((10, 2)), np.arange(10.0))


def test_physical_model_round_trips_through_the_file(tmp_path: Path) -> None:
    rng = np.random.default_rng(14)
    X = rng.uniform(0, 30, (60, 2))
    y = 0.01 * X[:, 0] + np.sqrt(0.01 + (0.05 * (X[:, 0] - X[:, 1])) ** 2) * rng.standard_normal(60)
    nf = NoiseFeatures(np.array([[1.0, -1.0]]), np.zeros(1), ("dq",))
    m = VHGPR(linear=True, linear_prior_var=10.0, se="auto", noise_features=nf, n_restarts=1,
              propagate_noise_parameter_uncertainty=True).fit(X, y)
    m.save(tmp_path / "m.npz")
    back = FittedVHGPR.load(tmp_path / "m.npz")
    Z = rng.uniform(0, 30, (7, 2))
    for k in ("f_mean", "f_var", "g_mean", "g_var"):
        np.testing.assert_array_equal(getattr(back.predict(Z), k), getattr(m.predict(Z), k))
    assert back.g_feature_names == ("dq",) and back.g_mean_coef_cov.shape == (2, 2)


def _two_source_data(seed: int = 21, n: int = 90) -> tuple[np.ndarray, np.ndarray, NoiseFeatures]:
    """Noise 0.03^2 + (0.05 dq)^2 with dq = x1 - x2; candidate sources dq (real) and x1 (none)."""
    rng = np.random.default_rng(seed)
    X = rng.uniform(0, 30, (n, 2))
    y = 0.02 * X[:, 0] + np.sqrt(0.03**2 + (0.05 * (X[:, 0] - X[:, 1])) ** 2) * rng.standard_normal(n)
    nf = NoiseFeatures(np.array([[1.0, -1.0], [1.0, 0.0]]), np.zeros(2), ("dq", "x1"))
    return X, y, nf


def test_warm_start_starts_exactly_at_the_start_models_bound() -> None:
    """The initial point a warm start builds (kernels packed, coefficients matched by name,
    Lambda reused on the same points) is the start model's own optimum: the MV bound evaluated
    there equals the bound the start model recorded, and the refit's bound is never lower."""
    X, y, nf = _two_source_data()
    kw = {"linear": True, "linear_prior_var": 10.0, "se": "off", "n_restarts": 1}
    start = VHGPR(noise_features=nf, **kw).fit(X, y)
    warm = VHGPR(noise_features=nf, warm_start=start, **kw)
    data = trainer._standardise(X, y)
    As, bs = nf.standardised(data["x_mean"], data["x_scale"], data["y_scale"])
    noise = warm.noise.for_features(nf, data["y_scale"])
    Phi = noise.design(data["Xs"], As, bs)
    f_spec = KernelSpec(d=2, bias=True, linear=True)
    x0 = warm._warm_point(len(y), f_spec, KernelSpec(d=2), nf.names, data["training_hash"])
    layout = bound.Layout(n=len(y), f=f_spec, g=KernelSpec(d=2), p=2, se_off=True,
                          linear_bounds=warm._linear_bounds(2))
    F0, _, _ = bound.mv_bound(x0, data["Xs"], data["ys"], layout, want_grad=False, Phi=Phi)
    assert F0 == pytest.approx(start.bound, abs=1e-8)
    refit = warm.fit(X, y)
    assert refit.bound >= start.bound - 1e-9
    assert refit.info["warm_start"] is True and refit.info["restarts_tried"] == 1
    assert refit.info["homoscedastic_init"] is None


def test_warm_start_after_dropping_a_source_matches_a_cold_fit_with_fewer_evaluations() -> None:
    """Refit with the unsupported source (x1) dropped, from the two-source fit: the bound within
    0.01 nats of a cold fit (restarts 2) of the one-source model (both reach the same optimum
    of a smooth bound; the difference is L-BFGS-B's stopping slack, measured <= 3e-5 nats on
    seeds 21-23), with fewer bound evaluations than the cold fit (measured 2, 28, 1 vs 54-60)."""
    X, y, nf = _two_source_data()
    kw = {"linear": True, "linear_prior_var": 10.0, "se": "off"}
    both = VHGPR(noise_features=nf, n_restarts=1, **kw).fit(X, y)
    one = NoiseFeatures(np.array([[1.0, -1.0]]), np.zeros(1), ("dq",))
    cold = VHGPR(noise_features=one, n_restarts=2, **kw).fit(X, y)
    warm = VHGPR(noise_features=one, warm_start=both, **kw).fit(X, y)
    assert warm.bound == pytest.approx(cold.bound, abs=0.01)
    assert warm.info["evaluations"] < cold.info["evaluations"]
    assert warm.g_feature_names == ("dq",)


def test_warm_start_refuses_what_it_cannot_start_from() -> None:
    X, y, nf = _two_source_data(n=40)
    kw = {"linear": True, "linear_prior_var": 10.0, "se": "off", "n_restarts": 1}
    one = NoiseFeatures(np.array([[1.0, -1.0]]), np.zeros(1), ("dq",))
    start = VHGPR(noise_features=one, **kw).fit(X, y)
    with pytest.raises(ConfigError, match="warm start needs se 'on' or 'off'"):
        VHGPR(linear=True, se="auto", warm_start=start)
    with pytest.raises(ConfigError, match=r"no coefficient for the noise feature\(s\) \['x1'\]; it has \['dq'\]"):
        VHGPR(noise_features=nf, warm_start=start, **kw).fit(X, y)
    with pytest.raises(ConfigError, match="warm start's kernels .* are not of this fit's form"):
        VHGPR(noise_features=one, warm_start=start, se="on", n_restarts=1).fit(X, y)


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_default_finds_a_noise_driven_by_an_input_the_mean_ignores(seed: int) -> None:
    """Hidden effect: the noise std grows with x3 (0.05 + 0.4 x3^2) while the mean depends on x1
    and x2 only. The default (g_start="both") must find it: the learned mean log noise variance
    correlates with the true one at > 0.9 on 1000 hold-out points (measured 0.997-1.000 on these
    seeds), and g's lengthscale of x3 is the shortest. From f's lengthscales alone (g_start="f")
    the correlation was -0.06 to -0.02 on the same seeds: x3's lengthscale starts at the upper
    bound, where its gradient vanishes."""
    def gen(n: int, s: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        r = np.random.default_rng(s)
        X = r.uniform(0, 1, (n, 3))
        g = 2 * np.log(0.05 + 0.4 * X[:, 2] ** 2)
        return X, np.sin(2 * np.pi * X[:, 0]) + 0.5 * X[:, 1] + np.exp(g / 2) * r.standard_normal(n), g

    X, y, _ = gen(250, seed)
    Xt, _, gt = gen(1000, 100 + seed)
    m = VHGPR().fit(X, y)
    assert float(np.corrcoef(m.predict(Xt).g_mean, gt)[0, 1]) > 0.9
    assert int(np.argmin(m.g_log_lengthscales)) == 2


def test_homoscedastic_init_records_its_cost_without_changing_the_fit(monkeypatch) -> None:
    """The init's record (``info["homoscedastic_init"]``: starts, evaluations, time_s) counts what
    ran, here every call of the likelihood counted independently, and asking for it changes
    nothing: the initial point is bit for bit the one without the record."""
    rng = np.random.default_rng(7)
    X = rng.uniform(-1.0, 1.0, (60, 2))
    y = np.sin(2.0 * X[:, 0]) + 0.1 * rng.standard_normal(60)
    spec = KernelSpec(d=2)
    plain = homoscedastic.fit_homoscedastic(X, y, spec, np.random.default_rng(0))
    calls = {"n": 0}
    loglik = homoscedastic.gp_loglik

    def counted(*args, **kwargs):
        calls["n"] += 1
        return loglik(*args, **kwargs)

    monkeypatch.setattr(homoscedastic, "gp_loglik", counted)
    record: dict = {}
    recorded = homoscedastic.fit_homoscedastic(X, y, spec, np.random.default_rng(0), record=record)
    for a, b in zip(plain, recorded):
        np.testing.assert_array_equal(a, b)
    assert record["starts"] == len(homoscedastic.INIT_STARTS) == 2
    assert record["evaluations"] == calls["n"] > 2
    assert record["time_s"] > 0.0
    calls["n"] = 0  # the trainer's init (on the standardised data) is counted the same way
    info = VHGPR(n_restarts=1, g_start="f", max_iter=5).fit(X, y).info["homoscedastic_init"]
    assert info["starts"] == 2 and info["evaluations"] == calls["n"] > 2 and info["time_s"] > 0.0
