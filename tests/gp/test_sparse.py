"""The sparse VHGPR (microctl.gp.sparse) against independent answers.

- with the inducing points at the training inputs and the exact fit's hyperparameters, the
  sparse bound's optimum is the exact MV bound and the predictions are the exact ones;
- the closed-form expected log-likelihood (S1) against Monte Carlo at the fitted q;
- the fitted q(u_g) is a stationary point of the bound (central differences);
- known-truth recovery: a planted input-dependent noise on 2-D data, against the truth;
- the streaming update against the batch fit with the same Z and hyperparameters;
- the CasADi graph of a sparse model against its NumPy prediction; the file round trip and
  an edited file refused.
"""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest

from microctl.errors import ConfigError, DataError
from microctl.gp.fitted import FittedVHGPR
from microctl.gp.sparse import SparseVHGPR, _Problem, update
from microctl.gp.trainer import VHGPR


def _planted(n: int, seed: int, d: int = 2) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """x ~ U(-1, 1)^d; f = sin(2 x0) + x1^2 / 2; log noise variance -3 + 1.5 x1 (independent of f's x0)."""
    rng = np.random.default_rng(seed)
    X = rng.uniform(-1.0, 1.0, (n, d))
    f = np.sin(2.0 * X[:, 0]) + 0.5 * X[:, 1] ** 2
    g = -3.0 + 1.5 * X[:, 1]
    return X, f + np.exp(0.5 * g) * rng.standard_normal(n), f, g


def _problem(model: FittedVHGPR, X: np.ndarray, y: np.ndarray, Z: np.ndarray | None = None) -> _Problem:
    Xs = (X - model.x_mean) / model.x_scale
    ys = (y - model.y_mean) / model.y_scale
    Zs = Xs if Z is None else (Z - model.x_mean) / model.x_scale
    return _Problem(Zs, model.f_kernel, model.g_kernel, model.g_prior_mean, Xs, ys)


@pytest.fixture(scope="module")
def small():
    X, y, _, _ = _planted(60, 1)
    exact = VHGPR(random_state=0).fit(X, y)
    return X, y, exact


def test_inducing_at_the_data_gives_the_exact_fit(small):
    """Z = X and the same hyperparameters: the sparse family contains the exact VHGPR's optimum.

    The exact fit stops on L-BFGS-B's relative tolerance over (Lambda, hyperparameters)
    jointly, so its Lambda can sit a little below the optimum for its hyperparameters: the
    sparse bound may exceed it, by at most a few hundredths of a nat (measured 0.007), never
    fall below it by more than round-off.
    """
    X, y, exact = small
    sparse = SparseVHGPR(n_inducing=1000, subset=1000, hyper=VHGPR(random_state=0)).fit(X, y)
    assert sparse.posterior_form == "sparse" and sparse.X.shape == exact.X.shape
    assert exact.bound - 1e-6 <= sparse.bound <= exact.bound + 0.05
    Xt, _, _, _ = _planted(300, 2)
    pe, ps = exact.predict(Xt), sparse.predict(Xt)
    # tolerances: a change of Lambda worth < 0.05 nats of bound moves g by a few hundredths
    assert np.max(np.abs(pe.f_mean - ps.f_mean)) < 0.01 * exact.y_scale
    assert np.max(np.abs(pe.g_mean - ps.g_mean)) < 0.05
    assert np.max(np.abs(pe.g_var - ps.g_var)) < 0.02
    assert np.max(np.abs(np.log(pe.y_var) - np.log(ps.y_var))) < 0.05


def test_expected_log_likelihood_matches_monte_carlo(small):
    """(S1) in closed form against 200 000 samples of independent f_i, g_i from the fitted marginals."""
    X, y, exact = small
    prob = _problem(exact, X, y)
    prob.solve(tol=1e-9, max_iter=200)
    _, _, mu, s2 = prob.q_g()
    w = np.exp(-mu + 0.5 * s2)
    _, _, a, c2 = prob.q_f(w)
    closed = -0.5 * np.log(2 * np.pi) - 0.5 * mu - 0.5 * w * ((prob.ys - a) ** 2 + c2)
    rng = np.random.default_rng(3)
    S = 200_000
    for i in (0, 17, 42):
        f = a[i] + np.sqrt(c2[i]) * rng.standard_normal(S)
        g = mu[i] + np.sqrt(s2[i]) * rng.standard_normal(S)
        ll = -0.5 * np.log(2 * np.pi) - 0.5 * g - 0.5 * (prob.ys[i] - f) ** 2 * np.exp(-g)
        se = ll.std() / np.sqrt(S)
        assert abs(ll.mean() - closed[i]) < 5 * se, (i, ll.mean(), closed[i], se)


def test_fitted_q_g_is_a_stationary_point(small):
    """Central differences of the bound along random directions of q(v_g)'s linear term: ~0."""
    X, y, exact = small
    prob = _problem(exact, X, y)
    bound, _, converged = prob.solve(tol=1e-12, max_iter=500)
    assert converged
    rng = np.random.default_rng(4)
    h0 = prob.hg.copy()
    eps = 1e-4
    for _ in range(3):
        d = rng.standard_normal(h0.size)
        d /= np.linalg.norm(d)
        prob.hg = h0 + eps * d
        up = prob.evaluate()["bound"]
        prob.hg = h0 - eps * d
        down = prob.evaluate()["bound"]
        # the bound's curvature along d is O(1) per unit step: a non-stationary point would show
        # a slope of O(1); stationarity leaves round-off and the tolerance's O(1e-4)
        assert abs(up - down) / (2 * eps) < 1e-2
        assert up <= bound + 1e-8 and down <= bound + 1e-8
    prob.hg = h0


@pytest.mark.slow
def test_planted_noise_is_recovered_with_few_inducing_points():
    """3000 points, 48 inducing points: g follows the planted log variance (which f does not see)."""
    X, y, f, g = _planted(3000, 5)
    model = SparseVHGPR(n_inducing=48, subset=400).fit(X, y)
    assert model.X.shape[0] == 48 and model.info["sparse"]["converged"]
    Xt, yt, ft, gt = _planted(2000, 6)
    p = model.predict(Xt)
    assert np.corrcoef(p.g_mean, gt)[0, 1] > 0.9
    oracle = float(np.mean(0.5 * np.log(2 * np.pi) + 0.5 * gt + 0.5 * (yt - ft) ** 2 / np.exp(gt)))
    # 400 points fix the hyperparameters: the hold-out NLPD within 0.05 nats of the truth's
    assert model.nlpd(Xt, yt) < oracle + 0.05


@pytest.mark.slow
def test_update_matches_the_batch_fit():
    """Fit on 1500 points then add 500 by update() = the batch problem on all 2000 (same Z, kernels).

    f's update is exact given g's weights; g's old points keep the Lambda they had: the
    difference is that approximation's, measured ~1e-3 in f (units of y) and ~0.02 in g.
    """
    X, y, _, _ = _planted(2000, 7)
    base = VHGPR(random_state=0, g_start="both").fit(X[:300], y[:300])
    Z = X[np.random.default_rng(0).choice(2000, 40, replace=False)]
    batch = _problem(base, X, y, Z)
    batch.solve(tol=1e-9, max_iter=500)
    full = batch.fitted(base, bound=0.0, training_hash="0" * 64, info={})
    first = _problem(base, X[:1500], y[:1500], Z)
    first.solve(tol=1e-9, max_iter=500)
    half = first.fitted(base, bound=0.0, training_hash="0" * 64, info={})
    upd = update(half, X[1500:], y[1500:])
    Xt = _planted(500, 8)[0]
    pf, pu, ph = full.predict(Xt), upd.predict(Xt), half.predict(Xt)
    assert np.max(np.abs(pf.f_mean - pu.f_mean)) < 0.01
    assert np.max(np.abs(pf.g_mean - pu.g_mean)) < 0.1
    # and the update moved the model toward the batch answer (the 500 points carry information)
    assert np.mean(np.abs(pf.f_var - pu.f_var)) < np.mean(np.abs(pf.f_var - ph.f_var))
    assert upd.info["sparse"]["updates"] == 500


def test_update_of_an_exact_model_keeps_its_prediction_when_told_nothing(small):
    """An exact model is the sparse form with Z = X (S5 with R diagonal): updating it with one
    point far outside the data (no kernel overlap) leaves its prediction where the data are."""
    X, y, exact = small
    far = np.full((1, X.shape[1]), 1e3)
    upd = update(exact, far, [float(np.mean(y))])
    Xt = _planted(200, 9)[0]
    pe, pu = exact.predict(Xt), upd.predict(Xt)
    assert np.max(np.abs(pe.f_mean - pu.f_mean)) < 1e-5 * exact.y_scale
    assert np.max(np.abs(pe.f_var - pu.f_var)) < 1e-5 * exact.y_scale**2
    assert np.max(np.abs(pe.g_mean - pu.g_mean)) < 1e-4


def test_casadi_graph_of_a_sparse_model_matches_numpy():
    X, y, _, _ = _planted(800, 10)
    model = SparseVHGPR(n_inducing=30, subset=200).fit(X, y)
    xs = ca.MX.sym("xs", 2)
    which = ("f_mean", "f_var", "g_mean", "g_var")
    out = model.posterior.casadi(xs, which)
    fn = ca.Function("p", [xs], [out[k] for k in which])
    Xt = np.random.default_rng(11).uniform(-1.2, 1.2, (20, 2))
    p = model.predict(Xt)
    for i, x in enumerate(Xt):
        vals = [float(v) for v in fn(model.posterior.standardise(x[None, :])[0])]
        ref = [p.f_mean[i], p.f_var[i], p.g_mean[i], p.g_var[i]]
        np.testing.assert_allclose(vals, ref, rtol=1e-8, atol=1e-10)


def test_sparse_model_file_round_trip_and_edit_refused(tmp_path):
    X, y, _, _ = _planted(500, 12)
    model = SparseVHGPR(n_inducing=25, subset=200).fit(X, y)
    path = tmp_path / "sparse.npz"
    model.save(path)
    back = FittedVHGPR.load(path)
    assert back.posterior_form == "sparse"
    Xt = _planted(100, 13)[0]
    np.testing.assert_array_equal(back.predict(Xt).y_var, model.predict(Xt).y_var)
    with np.load(path) as z:
        arrays = {k: z[k] for k in z.files}
    K = model.f_kernel.matrix(model.X, model.X)
    arrays["f_chol"] = np.linalg.cholesky(K + 1e-6 * np.eye(K.shape[0])) * 0.9  # L Lᵀ below K: R not PSD
    bad = tmp_path / "edited.npz"
    np.savez(bad, **arrays)
    with pytest.raises(DataError, match="positive semi-definite"):
        FittedVHGPR.load(bad)


def test_bad_settings_and_inputs_are_refused(small):
    with pytest.raises(ConfigError, match="n_inducing"):
        SparseVHGPR(n_inducing=1)
    with pytest.raises(ConfigError, match="tol"):
        SparseVHGPR(tol=0)
    X, y, exact = small
    with pytest.raises(DataError, match="inducing has shape"):
        SparseVHGPR().fit(X, y, inducing=np.zeros((4, 3)))
    with pytest.raises(DataError, match="X_new has shape"):
        update(exact, np.zeros((3, 5)), np.zeros(3))
    with pytest.raises(DataError, match="y_new has shape"):
        update(exact, np.zeros((3, 2)), np.zeros(4))
    with pytest.raises(DataError, match=r"X_new has shape \(0, 2\); at least one new point"):
        update(exact, np.zeros((0, 2)), np.zeros(0))
    with pytest.raises(DataError, match=r"X_new has a non-finite value \(nan\) at row 0, column 0"):
        update(exact, np.array([[np.nan, 0.0]]), np.zeros(1))
    with pytest.raises(ConfigError, match="hyper must be a VHGPR trainer, got str"):
        SparseVHGPR(hyper="exact")


def test_kmeans_of_the_same_sample_is_computed_once_and_gives_the_same_points(monkeypatch):
    """The residual model fits one data set up to three times (microctl.models.training); the
    k-means inducing points of a repeated sample and seed come from the cache: one kmeans2 call,
    and the points equal bit for bit those of a fresh computation (cache emptied)."""
    import microctl.gp.sparse as sp

    rng0 = np.random.default_rng(3)
    Xs = rng0.standard_normal((600, 3))  # 600 > 50 M: a sample is drawn, as at n = 20 000 with M = 256
    calls = []
    real = sp.kmeans2
    monkeypatch.setattr(sp, "kmeans2", lambda *a, **k: calls.append(1) or real(*a, **k))
    monkeypatch.setattr(sp, "_KMEANS_CACHE", type(sp._KMEANS_CACHE)())
    first = sp._inducing_points(Xs, 10, np.random.default_rng(0))
    again = sp._inducing_points(Xs, 10, np.random.default_rng(0))
    assert len(calls) == 1 and np.array_equal(first, again)
    again[0, 0] += 1.0  # a caller's copy: the cache keeps its own
    assert np.array_equal(sp._inducing_points(Xs, 10, np.random.default_rng(0)), first) and len(calls) == 1
    sp._KMEANS_CACHE.clear()
    fresh = sp._inducing_points(Xs, 10, np.random.default_rng(0))
    assert len(calls) == 2 and np.array_equal(first, fresh)
    other = sp._inducing_points(Xs, 10, np.random.default_rng(1))  # another seed: computed
    assert len(calls) == 3 and not np.array_equal(first, other)
