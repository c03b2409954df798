"""Noise sources named by the user (``noise_sources``): which candidate each name gives, the
settings' checks, and the train command end to end."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml

from microctl.cli import main
from microctl.errors import ConfigError
from microctl.experiments.config import Training, parse_experiment_config
from microctl.gp.vhgpr import FittedVHGPR
from microctl.models.afm import AnalyticForwardModel
from microctl.models.declared_sources import declared_selection
from microctl.models.noise_dictionary import _fit_variance, candidate_features, quantity
from microctl.models.training import ResidualModelSettings
from microctl.stage.config import load_stage_config

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def afm():
    return AnalyticForwardModel(load_stage_config(ROOT / "configs/stage/sim_paper.yaml").stage)


def _planted(afm, n=300, seed=11):
    """Inputs [t_prev, q_prev, u] with steps from 0 to the workspace's size, and residuals whose
    variance is a 0.05 µm floor plus creep on actuator 1 that saturates with a 1 µm knee,
    0.2^2 dq^2 / (dq^2 + 1) (written here from the steps, not through the dictionary)."""
    rng = np.random.default_rng(seed)
    U0, U = afm.workspace.sample(n, rng), afm.workspace.sample(n, rng)
    Up = U + rng.uniform(0, 1, (n, 1)) ** 2 * (U0 - U)
    X = np.hstack([np.zeros((n, 1)), Up @ afm.K.T, U])
    dq = (U - Up) @ afm.K.T
    r = np.sqrt(0.05**2 + 0.2**2 * dq[:, 0] ** 2 / (dq[:, 0] ** 2 + 1.0)) * rng.standard_normal(n)
    cands = candidate_features(afm).rescaled(X)
    return r, cands.values(X), list(cands.names)


def test_a_named_quantity_takes_the_shape_that_fits_best_and_recovers_the_planted_one(afm):
    """Naming ``dq1`` gives actuator 1's step shape with the highest likelihood over every dq1 shape
    (checked here against each shape fitted alone); on residuals of a creep with a 1 µm knee that is
    ``dq1:sat@1``, the planted shape. The gains add up to the fit's rise over the floor alone."""
    r, Phi, names = _planted(afm)
    sel = declared_selection(r, Phi, names, ["dq1"])
    r2 = r**2
    lls = {nm: _fit_variance(r2, Phi[:, [j]])[0] for j, nm in enumerate(names) if quantity(nm) == "dq1"}
    assert sel.names == (max(lls, key=lls.get),) == ("dq1:sat@1",)
    floor_only = _fit_variance(r2, Phi[:, :0])[0]
    assert sel.loglik == pytest.approx(lls["dq1:sat@1"]) and sum(sel.gains) == pytest.approx(sel.loglik - floor_only)
    assert sel.p_values == () and sel.thresholds == (pytest.approx(0.5 * np.log(len(r))),)


def test_candidate_names_enter_as_named_in_order_even_where_the_data_do_not_support_them(afm):
    """Exact names are not tested or replaced: a source the residuals do not carry (actuator 3's
    stick-slip, drx) is kept, in the order given, beside a quantity resolved to its best shape."""
    r, Phi, names = _planted(afm)
    sel = declared_selection(r, Phi, names, ["dq3:sq", "dq1", "drx:sq"])
    assert sel.names[0] == "dq3:sq" and sel.names[2] == "drx:sq" and sel.names[1].startswith("dq1:")
    assert [names[j] for j in sel.indices] == list(sel.names)
    # each gain is over the sources named before it: dq3 first takes the share of actuator 1's creep
    # that its steps correlate with (a few nats), the creep's own shape then adds tens of nats and
    # drx nothing; with actuator 1 first, dq3 adds nothing either
    assert sel.gains[2] < 0.5 and sel.gains[1] > 10 * sel.gains[0]
    first = declared_selection(r, Phi, names, ["dq1", "dq3:sq"])
    assert first.gains[1] < 0.5 and first.loglik == pytest.approx(sel.loglik, abs=1e-6)


@pytest.mark.parametrize("declared,needle", [
    (["dq9"], "valid quantities: dq1, q1, f1, dq2"),
    (["tilt"], "neither a noise-source candidate nor a quantity"),
    (["dq1", "dq1:sat@1"], "already named (dq1:sat@1)"),
])
def test_names_that_are_no_source_of_the_stage_or_name_one_twice_are_refused(afm, declared, needle):
    r, Phi, names = _planted(afm)  # actuator 1 resolves to its planted shape, sat@1
    with pytest.raises(ConfigError, match="noise source") as exc:
        declared_selection(r, Phi, names, declared)
    assert needle in str(exc.value)
    assert "drx" in str(exc.value) or "valid quantities" not in needle  # every quantity is listed


def test_the_setting_is_a_list_of_distinct_names_for_the_dictionary_model_only():
    assert ResidualModelSettings().noise_sources is None  # the default: the data select
    assert ResidualModelSettings(noise_sources=["dq4", "drx"]).noise_sources == ("dq4", "drx")
    assert ResidualModelSettings(noise_sources=[]).noise_sources == ()
    for bad in ("dq4", ["dq4", "dq4"], ["dq 4"], [""], [4]):
        with pytest.raises(ConfigError, match="noise_sources: must be a list of distinct names or null"):
            ResidualModelSettings(noise_sources=bad)
    with pytest.raises(ConfigError, match="not of 'hgp'"):
        ResidualModelSettings(noise_model="hgp", noise_sources=["dq4"])


def test_an_experiment_file_names_sources_under_training_and_writes_them_back(tmp_path):
    raw = yaml.safe_load((ROOT / "configs/experiments/paper.yaml").read_text())
    raw["training"]["noise_sources"] = ["dq4", "drx:sq"]
    cfg = parse_experiment_config(raw, "exp.yaml", ROOT / "configs/experiments")
    assert cfg.training.model_settings(1).noise_sources == ("dq4", "drx:sq")
    assert cfg.to_dict()["training"]["noise_sources"] == ["dq4", "drx:sq"]
    yaml.safe_dump(cfg.to_dict())  # plain data (a tuple would not dump)
    raw["training"]["noise_sources"] = "dq4"
    with pytest.raises(ConfigError, match="exp.yaml.*training.noise_sources.*list of distinct names"):
        parse_experiment_config(raw, "exp.yaml", ROOT / "configs/experiments")
    with pytest.raises(ConfigError, match="not of 'physical'"):
        Training(noise_model="physical", noise_sources=("dq4",))


def test_train_with_named_sources_keeps_them_and_weighs_no_alternative(tmp_path, capsys):
    """``microctl train --noise-source``: on sim_paper's log (its stick-slip is on PZT 4) the named
    quantity and a named source the data do not carry are both kept (no test, no pruning), the model
    stores no alternatives for the least-motion rule, and the command says the sources were named;
    ``none`` names no source; ``none`` beside a name is refused."""
    cfg = ROOT / "configs/stage/sim_paper.yaml"
    log = tmp_path / "log.csv"
    assert main(["collect", "--config", str(cfg), "-n", "60", "--seed", "2", "-o", str(log), "--quiet"]) == 0
    out = tmp_path / "m.npz"
    rc = main(["train", str(log), "--config", str(cfg), "-o", str(out), "--restarts", "1",
               "--noise-source", "dq4", "--noise-source", "dq2:sq"])
    text = capsys.readouterr().out
    assert rc == 0 and "sources named (dq4, dq2:sq), not selected by the data" in text
    sel = FittedVHGPR.load(out).info["noise_selection"]
    assert sel["declared"] == ["dq4", "dq2:sq"] and "alternatives" not in sel
    assert sel["selected"][0].startswith("dq4:") and sel["selected"][1] == "dq2:sq" and len(sel["selected"]) == 2
    rc = main(["train", str(log), "--config", str(cfg), "-o", str(tmp_path / "n.npz"), "--restarts", "1",
               "--noise-source", "none"])
    assert rc == 0 and "sources named (none)" in capsys.readouterr().out
    assert FittedVHGPR.load(tmp_path / "n.npz").info["noise_selection"]["selected"] == []
    rc = main(["train", str(log), "--config", str(cfg), "-o", str(tmp_path / "x.npz"),
               "--noise-source", "none", "--noise-source", "dq4"])
    assert rc == 2 and "'none' names no source" in capsys.readouterr().err
    rc = main(["train", str(log), "--config", str(cfg), "-o", str(tmp_path / "x.npz"), "--noise-source", "dq7"])
    assert rc == 2 and "valid quantities" in capsys.readouterr().err and not (tmp_path / "x.npz").exists()
