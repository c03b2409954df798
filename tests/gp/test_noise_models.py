"""Noise models are a registry of classes (microctl.gp.noise_models): a new one is one class.

The toy model here, ``quartic``, makes g's prior mean ``log(c_0 + c_1 z^4)`` with ``z = a . x + b``;
it registers, trains on a small set and round-trips through a model file, and the model file
stores its name (files without a name still read, the name derived from their arrays).
"""

from __future__ import annotations

import json
from pathlib import Path

import casadi as ca
import numpy as np
import pytest

import microctl.gp.noise_models as noise_models
from microctl.errors import ConfigError, DataError
from microctl.gp.noise_models import NoiseModel, noise_model_class, register_noise_model
from microctl.gp.noise_prior import NoiseFeatures
from microctl.gp.vhgpr import VHGPR, FittedVHGPR


def quartic(z):  # NumPy array or CasADi expression alike
    return (z * z) * (z * z)


class QuarticNoise(NoiseModel):
    """Toy noise model: phi = z^4."""

    name = "quartic"
    transform = staticmethod(quartic)


@pytest.fixture
def registry(monkeypatch: pytest.MonkeyPatch) -> None:
    """Register the toy model in a copy of the registry (restored after the test)."""
    monkeypatch.setattr(noise_models, "_REGISTRY", dict(noise_models._REGISTRY))
    register_noise_model(QuarticNoise)


def _data(n: int = 40, seed: int = 3) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    X = rng.uniform(-1.5, 1.5, (n, 1))
    y = np.sin(2 * X[:, 0]) + (0.05 + 0.3 * X[:, 0] ** 2) * rng.standard_normal(n)
    return X, y


def _features() -> NoiseFeatures:
    return NoiseFeatures(np.array([[1.0]]), np.zeros(1), ("x",))


def _rewrite_meta(src: Path, dst: Path, edit) -> None:
    z = dict(np.load(src, allow_pickle=False))
    meta = json.loads(str(z["meta_json"]))
    edit(meta)
    z["meta_json"] = np.array(json.dumps(meta))
    np.savez(dst, **z)


def test_registry_has_the_two_package_models() -> None:
    assert noise_models.noise_model_names()[:3] == ("physical", "hgp", "dictionary")
    assert noise_model_class("hgp").uses_features is False
    with pytest.raises(KeyError, match="unknown noise model 'nope'"):
        noise_model_class("nope")


def test_a_name_registers_once(registry: None) -> None:
    class Other(NoiseModel):
        name = "quartic"

    with pytest.raises(ValueError, match="already registered"):
        register_noise_model(Other)
    register_noise_model(QuarticNoise)  # the same class again is harmless


def test_toy_noise_model_trains_and_round_trips(registry: None, tmp_path: Path) -> None:
    X, y = _data()
    model = VHGPR(noise_features=_features(), noise_model="quartic", n_restarts=1, max_iter=40).fit(X, y)
    assert model.noise_model == "quartic" and model.noise_model_name == "quartic"
    gm = model.g_prior_mean
    assert gm.transform is quartic
    # g's prior mean is the toy's: log(c_0 + c_1 z^4), z the standardised feature
    xs = np.linspace(-1.0, 1.0, 7)[:, None]
    z = xs @ model.g_feature_matrix.T + model.g_feature_offset
    want = np.log(np.exp(model.g_mu0) + np.exp(model.g_log_feature_coef[0]) * z[:, 0] ** 4)
    np.testing.assert_allclose(gm.value(xs), want, rtol=1e-12)
    # the CasADi form of the posterior agrees with the NumPy one
    sym = ca.MX.sym("x", 1)
    out = model.posterior.casadi(sym, ("g_mean", "g_var"))
    fn = ca.Function("g", [sym], [out["g_mean"], out["g_var"]])
    p = model.predict(X[:5])
    for i in range(5):
        gmean, gvar = (float(v) for v in fn((X[i, 0] - model.x_mean[0]) / model.x_scale[0]))
        assert gmean == pytest.approx(p.g_mean[i], rel=1e-10, abs=1e-10)
        assert gvar == pytest.approx(p.g_var[i], rel=1e-8, abs=1e-10)

    path = tmp_path / "quartic.npz"
    model.save(path)
    assert json.loads(str(np.load(path)["meta_json"]))["noise_model"] == "quartic"
    back = FittedVHGPR.load(path)
    assert back.noise_model == "quartic" and back.g_prior_mean.transform is quartic
    Xt = np.linspace(-2.0, 2.0, 11)[:, None]
    a, b = model.predict(Xt), back.predict(Xt)
    for name in ("f_mean", "f_var", "g_mean", "g_var", "y_var"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))


def test_unknown_or_mismatched_noise_model_in_a_file(registry: None, tmp_path: Path) -> None:
    X, y = _data(25)
    good = tmp_path / "good.npz"
    VHGPR(noise_features=_features(), noise_model="quartic", n_restarts=1, max_iter=20).fit(X, y).save(good)
    bad = tmp_path / "bad.npz"
    _rewrite_meta(good, bad, lambda m: m.update(noise_model="cubic"))
    with pytest.raises(DataError, match=r"bad\.npz: unknown noise model 'cubic'"):
        FittedVHGPR.load(bad)
    _rewrite_meta(good, bad, lambda m: m.update(noise_model="hgp"))
    with pytest.raises(DataError, match=r"noise model 'hgp' stores no feature arrays"):
        FittedVHGPR.load(bad)


def test_files_without_a_name_read_with_the_derived_one(tmp_path: Path) -> None:
    X, y = _data(25)
    for features, want in ((None, "hgp"), (_features(), "physical")):
        path = tmp_path / f"{want}.npz"
        VHGPR(noise_features=features, n_restarts=1, max_iter=20).fit(X, y).save(path)
        # the two models whose name the arrays give are written as format 1 and 2 files were (no name)
        assert "noise_model" not in json.loads(str(np.load(path)["meta_json"]))
        back = FittedVHGPR.load(path)
        assert back.noise_model_name is None and back.noise_model == want


def test_trainer_refuses_a_noise_model_without_its_features(registry: None) -> None:
    with pytest.raises(ConfigError, match="noise model 'quartic' needs noise_features"):
        VHGPR(noise_model="quartic")
    with pytest.raises(ConfigError, match="noise model 'hgp' takes no noise_features"):
        VHGPR(noise_features=_features(), noise_model="hgp")
    with pytest.raises(ConfigError, match="unknown noise model 'nope'"):
        VHGPR(noise_model="nope")
