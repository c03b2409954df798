"""Equivalent causes: which one ``extended.yaml`` carries, and the moves that would separate them.

When a step of the selection finds causes that predict the data equally well (2Δℓ < 6,
:data:`~microctl.diagnosis.selection.EQUIV_LR`), the data cannot say which one is there.
:func:`choose_plausible` then picks the one the physics makes most plausible: the largest

    score = log L − ½ Σ_p ((θ_p − healthy_p) / s_p)²,

the profile log-likelihood plus a Gaussian log prior on each parameter's departure from a
healthy stage, with s_p the typical size of that defect (the rms departure of the vocabulary's
own magnitudes, :meth:`microctl.stage.causes.Cause.draw`, for this stage's preload: a 3-10 %
gain error, a 0.3-2 mm offset, a gap a few µm beyond the preload compression). A 1 % gain,
well inside any piezo's calibration tolerance, is more plausible than a set screw lowered
beyond the preload; the lowest-BIC cause among equivalents is not more likely to be there.
The choice is reported (``chosen`` in the entry) and said in report.md.

:func:`separating_design` measures, for each design of ``microctl collect``, how well a short
run would tell the chosen cause from its nearest equivalent: the readings the chosen fit predicts
on the design's moves are fitted by the equivalent (best parameters), and the misfit per move
(in noise variances) is the noncentrality a real run adds per move. The report recommends the
design with the largest one and the number of moves for an expected 2Δℓ of
:data:`TARGET_NONCENTRALITY`.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from microctl.diagnosis.causes import MeanFit, fit_mean
from microctl.diagnosis.data import data_from_arrays
from microctl.errors import ConfigError
from microctl.measurement.design import DESIGNS, training_moves
from microctl.models.afm import AnalyticForwardModel
from microctl.stage.cause_base import preload_compression_um
from microctl.stage.causes import REGISTRY

#: Draws of a cause's magnitude used to size its prior.
PRIOR_DRAWS = 400

#: Expected 2Δℓ between the two causes a separating run is sized for (well beyond the
#: equivalence threshold 6: the run then separates them with a probability of about 0.9).
TARGET_NONCENTRALITY = 20.0

#: Moves of the design each candidate design is evaluated on.
DESIGN_MOVES = 60

#: Most equivalents a separating design is computed for (the nearest in likelihood).
MAX_SEPARATED = 2


@lru_cache(maxsize=64)
def prior_scales(cause: str, compression_um: float) -> dict[str, float]:
    """Typical departure from healthy of each parameter of ``cause``: rms over the vocabulary's
    planted magnitudes (:meth:`Cause.draw`, seeded), for a stage of this preload compression."""
    cls = REGISTRY[cause]
    rng = np.random.default_rng(0)
    dev = {p.name: [] for p in cls.params}
    for _ in range(PRIOR_DRAWS):
        c = cls.draw(rng, 1 if cls.per_actuator else None, compression_um=compression_um)
        for p in cls.params:
            dev[p.name].append(float(getattr(c, p.name)) - p.healthy)
    return {k: float(np.sqrt(np.mean(np.square(v)))) or 1.0 for k, v in dev.items()}


def plausibility(fit: MeanFit, stage) -> float:
    """Score of a fit's *last* cause: log-likelihood plus the log prior of its departure from healthy."""
    spec, theta, _ = fit.split()[-1]
    scales = prior_scales(spec.cause, float(preload_compression_um(stage)))
    pen = sum(((float(v) - p.healthy) / scales[p.name]) ** 2 for p, v in zip(spec.cls.params, theta))
    return float(fit.loglik - 0.5 * pen)


def choose_plausible(best_key: str, equivalent: tuple, fits: dict, stage) -> tuple[str, dict]:
    """The most plausible of ``best_key`` and its equivalents (see the module docstring).

    Returns
    -------
    key : str
    info : dict
        ``{"by", "lowest_bic", "scores"}`` (report form).
    """
    keys = (best_key, *equivalent)
    scores = {k: plausibility(fits[k], stage) for k in keys}
    chosen = max(keys, key=lambda k: scores[k])
    return chosen, {"by": "physical plausibility among causes the data cannot separate (log-likelihood + log prior "
                          "of the departure from a healthy stage, typical defect sizes of the vocabulary)",
                    "lowest_bic": best_key, "scores": scores}


def _design_data(stage, design: str, n: int, seed: int):
    afm = AnalyticForwardModel(stage)
    u = training_moves(afm, design, n, seed)
    q = afm.q_of(u)
    return data_from_arrays(u, q, np.zeros(len(u)), time_s=np.arange(1.0, len(u) + 1.0))


def separating_design(stage, chosen: MeanFit, other: MeanFit, sigma_um: float, *, seed: int = 0) -> dict:
    """How each ``collect`` design separates ``chosen`` from ``other``, and the recommended run.

    Parameters
    ----------
    stage : Stage
        The configured stage (its corrections are the base of both fits).
    chosen, other : MeanFit
        The two fitted cause sets (same earlier causes, another last cause).
    sigma_um : float
        Noise std of one reading.
    seed : int

    Returns
    -------
    dict
        ``{"design", "moves", "command", "noncentrality_per_move": {design: value}}``; design
        None when no design separates them (same predictions everywhere).
    """
    per = {}
    split = {s.key: th for s, th, _ in other.split()}
    theta0 = np.concatenate([split[s.key] for s in other.specs]) if other.specs else None
    for design in DESIGNS:
        try:
            d = _design_data(stage, design, DESIGN_MOVES, seed)
        except ConfigError:
            continue
        t = chosen.model().predict_data(d).t
        f = fit_mean(stage, stage.corrections, list(other.specs), d.with_t(t), theta0=theta0,
                     nuisance0=other.nuisance)
        per[design] = float(f.rss / (sigma_um**2 * d.n))
    if not per or max(per.values()) * 600 < TARGET_NONCENTRALITY:
        return {"design": None, "moves": None, "command": None, "noncentrality_per_move": per,
                "note": "no collect design separates them within 600 moves: same readings on every design"}
    best = max(per, key=per.get)
    n = int(min(600, max(40, np.ceil(TARGET_NONCENTRALITY / per[best]))))
    return {"design": best, "moves": n, "noncentrality_per_move": per,
            "command": f"microctl collect --config STAGE.yaml --design {best} -n {n} --seed 1 -o separate.csv",
            "note": (f"expected 2Δℓ ≈ {TARGET_NONCENTRALITY:.0f} between the two causes on {n} moves of the "
                     f"'{best}' design; diagnose that log (or append it to this one) to tell them apart")}
