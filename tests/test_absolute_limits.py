"""scripts/absolute_limits.py: the pieces that do not train a model.

The comparison with the AFM is checked on numbers worked out by hand; the truth's readings on a
stand-in stage whose mean is a known formula, with the noise drawn again from the same seed; the
errors on a folder that is not a run and on a config.yaml without its experiment section.
"""

from __future__ import annotations

import numpy as np
import pytest
from script_loader import load_script

from microctl.errors import ConfigError


def _lim():
    return load_script("absolute_limits")


def test_nearer_than_afm_counts_strictly_nearer_points_and_the_error_sizes():
    truth = np.array([1.0, 2.0, 3.0, 4.0])
    afm = np.array([1.5, 2.0, 2.0, 4.1])      # errors 0.5, 0.0, 1.0, 0.1
    pred = np.array([1.2, 2.3, 3.0, 4.1])     # errors 0.2, 0.3, 0.0, 0.1 (a tie is not nearer)
    out = _lim().nearer_than_afm(pred, truth, afm)
    assert out["nearer"] == 2 and out["points"] == 4
    assert out["median_um"] == pytest.approx(0.15)
    assert out["max_um"] == pytest.approx(0.3)


def test_nearer_than_afm_averages_each_points_error_over_the_trials_first():
    """Two trials: at point 0 the model's errors 0.5 and 0.0 (mean 0.25) against the AFM's 0.3
    and 0.1 (mean 0.2), though the model is nearer in one trial; at point 1, 0.1 and 0.1
    against 0.5 and 0.3."""
    truth = np.array([[1.0, 2.0], [1.2, 2.2]])
    afm = np.array([1.3, 2.5])                 # errors: point 0 0.3, 0.1; point 1 0.5, 0.3
    pred = np.array([[1.5, 2.1], [1.2, 2.1]])  # errors: point 0 0.5, 0.0; point 1 0.1, 0.1
    out = _lim().nearer_than_afm(pred, truth, afm)
    assert out["nearer"] == 1 and out["points"] == 2
    assert out["median_um"] == pytest.approx(0.175)
    assert out["max_um"] == pytest.approx(0.25)


class _Stage:
    """The next reading's true mean is 2 u_0 - u_1 + t_prev / 10."""

    @staticmethod
    def true_mean(s, u):
        return 2.0 * u[0] - u[1] + s[0] / 10.0


def test_truth_readings_are_the_true_mean_of_each_move_from_its_state_plus_the_seeded_noise():
    rng = np.random.default_rng(3)
    s_prev = rng.normal(size=(6, 5))
    moves = rng.normal(size=(6, 3))
    lim = _lim()
    got = lim.truth_readings(lim.true_means(_Stage(), s_prev, moves), 0.25, np.random.default_rng(11))
    mean = 2.0 * moves[:, 0] - moves[:, 1] + s_prev[:, 0] / 10.0
    assert np.allclose(got, mean + 0.25 * np.random.default_rng(11).standard_normal(6), rtol=0, atol=1e-12)


def test_a_folder_without_results_and_a_config_without_its_experiment_section_are_named(tmp_path, capsys):
    lim = _lim()
    with pytest.raises(SystemExit) as e:
        lim.main([str(tmp_path)])
    assert e.value.code == 2
    assert f"{tmp_path}: no results.json" in capsys.readouterr().err
    cfg = tmp_path / "config.yaml"
    cfg.write_text("stage_config: {}\n")
    with pytest.raises(ConfigError, match=r"config\.yaml: no 'experiment' section"):
        lim._run_config(cfg)


def test_with_noise_variances_gives_the_posterior_a_model_built_with_those_variances_has():
    """The re-weighted model's f equals the fixture built directly with the new noise (its own
    Cholesky and solve from the kernel formula), while the old fit's noise differed by 10x."""
    from microctl.testing import fixed_hyperparameter_model
    rng = np.random.default_rng(7)
    X = rng.uniform(-1, 1, size=(25, 2))
    y = np.sin(3 * X[:, 0]) + 0.5 * X[:, 1] + 0.1 * rng.standard_normal(25)
    old = np.log(0.05 * np.ones(25))
    new_var = 0.002 + 0.02 * X[:, 0] ** 2  # y's units
    kw = dict(f_log_lengthscales=np.array([-0.3, 0.2]), f_log_signal_var=0.4)
    fitted = fixed_hyperparameter_model(X, y, old, **kw)
    want = fixed_hyperparameter_model(X, y, np.log(new_var), **kw)
    got = _lim().with_noise_variances(fitted, new_var)
    assert np.allclose(got.f_chol, want.f_chol, rtol=0, atol=1e-10)
    assert np.allclose(got.f_alpha, want.f_alpha, rtol=1e-8, atol=1e-8)
    assert not np.allclose(fitted.f_alpha, want.f_alpha, rtol=1e-3, atol=1e-3)
