"""Issue 21 deliverable 3: equivalent causes — which one extended.yaml carries, and the run that
separates them. Data from the independent generator (tests/independent_stage.py)."""

from __future__ import annotations

import independent_stage as ind
import numpy as np
import pytest
from conftest import CONFIGS

from microctl.diagnosis.causes import CauseSpec, fit_mean
from microctl.diagnosis.data import data_from_arrays
from microctl.diagnosis.pipeline import run_diagnosis
from microctl.diagnosis.report import add_identifiability
from microctl.diagnosis.separate import (
    TARGET_NONCENTRALITY,
    plausibility,
    prior_scales,
    separating_design,
)
from microctl.stage.causes import ActuatorGain, ContactLoss, ContactOffset, ToolOffset
from microctl.stage.config import load_stage_config
from microctl.util.io import to_jsonable

TABLE1 = CONFIGS / "stage" / "table1.yaml"


@pytest.fixture(scope="module")
def cfg():
    return load_stage_config(TABLE1)


@pytest.fixture(scope="module")
def geo():
    return ind.load_geometry(TABLE1)


def _run(geo, seed, cause, n=150, extra_gap=None):
    rng = np.random.default_rng(seed)
    truth = ind.random_truth(geo, rng, physics=ind.load_physics(TABLE1))
    if extra_gap is not None:
        cause = ContactLoss(cause.actuator, truth.compression_um + extra_gap)
    truth, _ = ind.plant(truth, cause)
    r = ind.run(truth, ind.random_moves(geo, n, rng), rng)
    return truth, data_from_arrays(r.u, r.q, r.t, q_prev=r.q_prev, t_prev=r.t_prev, time_s=r.time_s)


def test_prior_scales_are_the_vocabulary_magnitudes():
    """rms departure of the registry's planted magnitudes: a gain 3-10 % off (rms ≈ 7 %), a
    contact loss a few µm beyond the preload compression (5 + 2..7 µm: rms ≈ 9.7 µm)."""
    s = prior_scales("actuator_gain", 5.0)["gain"]
    assert 0.06 < s < 0.08
    assert 9.0 < prior_scales("contact_loss", 5.0)["gap_um"] < 10.5


def test_carried_cause_is_the_most_plausible_of_its_class_and_reported(cfg, geo):
    """A tool offset is one class with the four contact offsets (one gauge): the accepted entry,
    and extended.yaml, carry the member of largest plausibility score, the entry says how it was
    chosen, and no collect design separates the class (same readings on every design: it needs a
    second gauge, as the separating measurement says)."""
    _, data = _run(geo, 50, ToolOffset(0.6, -0.4))
    d = run_diagnosis(cfg, data, gain=False)
    rep = to_jsonable(d.report)
    add_identifiability(rep)
    first = rep["mean_causes"][0]
    assert first["accepted"] and {first["cause"], *(q["cause"] for q in first["equivalent"])} == {
        "tool_offset", "contact_offset"}
    ch = first["chosen"]
    key = first["cause"] + (f"[{first['params']['actuator']}]" if "actuator" in first["params"] else "")
    assert ch["scores"][key] == max(ch["scores"].values())
    assert set(ch["scores"]) == {key, *(q["cause"] + (f"[{q['params']['actuator']}]" if "actuator" in q["params"]
                                                       else "") for q in first["equivalent"])}
    (item,) = rep["identifiability"]
    assert item["carried_in_extended_yaml"] == key
    corr = d.extended_config.stage.corrections.to_dict()
    assert list(corr) == [first["cause"]]
    assert item["recommended_runs"] and all(r["design"] is None for r in item["recommended_runs"])
    # exactly equivalent: every design's misfit per move is round-off (< 1e-4 of a noise variance)
    assert max(max(r["noncentrality_per_move"].values()) for r in item["recommended_runs"]) < 1e-4


def test_separating_design_sizes_a_run_that_tells_a_kink_from_a_gain(cfg, geo):
    """A contact loss 1 µm beyond the preload compression against the gain on the same actuator
    fitted to the same data: the recommended design is the one whose moves add the most 2Δℓ per
    move, and its size gives the target 2Δℓ."""
    truth, data = _run(geo, 51, ContactLoss(2, 0.0), extra_gap=1.0)
    stage = cfg.stage
    kink = fit_mean(stage, stage.corrections, [CauseSpec.of(ContactLoss, stage, 2)], data)
    gain = fit_mean(stage, stage.corrections, [CauseSpec.of(ActuatorGain, stage, 2)], data)
    assert kink.rss < gain.rss
    sep = separating_design(stage, kink, gain, 0.05)
    per = sep["noncentrality_per_move"]
    assert sep["design"] == max(per, key=per.get) and per[sep["design"]] > 0
    assert sep["moves"] == max(40, int(np.ceil(TARGET_NONCENTRALITY / per[sep["design"]])))
    assert f"--design {sep['design']} -n {sep['moves']}" in sep["command"]
    # a plausibility score is the log-likelihood less the prior penalty: never above the likelihood
    assert plausibility(kink, stage) <= kink.loglik and plausibility(gain, stage) <= gain.loglik


def test_a_contact_offset_far_beyond_its_typical_size_is_less_plausible(cfg, geo):
    """Same likelihood, larger departure: lower score (the prior's only job)."""
    _, data = _run(geo, 52, ContactOffset(3, 0.5, 0.2))
    stage = cfg.stage
    f = fit_mean(stage, stage.corrections, [CauseSpec.of(ContactOffset, stage, 3)], data)
    far = fit_mean(stage, stage.corrections, [CauseSpec.of(ContactOffset, stage, 2)], data)
    # ball 2's offset must be |c3/c2| ≈ 2.3 × larger for the same readings (docs/diagnosis.md)
    assert np.hypot(*far.theta) > 1.5 * np.hypot(*f.theta)
    assert abs(far.loglik - f.loglik) < 3.0
    assert plausibility(far, stage) < plausibility(f, stage)
