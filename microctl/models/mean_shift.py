"""The mean shift a stage's scatter causes: f's feature trend on the selected noise sources.

Where a move scatters and the stage's response to the scattered quantity is not linear (a ball
that lifts off when its actuator falls short and pushes when it overshoots, a gauge that reads
a quadratic of the displacement), the *mean* reading moves with the scatter's size. To second
order, ``E[h(q + e)] = h(q) + h''(q) Var(e) / 2``: the shift is proportional to the variance,
source by source. The noise model's selected sources (:mod:`microctl.models.noise_dictionary`)
are those variances, each a shaped function of one physical quantity, so the mean correction f
gets them as the features of a trend (:mod:`microctl.gp.trend`), one coefficient each with a
vague Gaussian prior, in f's kernel. Without them the stationary kernel over x = [s; u] treats the
shift as noise: on the paper-scale rig (configs/stage/sim_paper_scale.yaml) the mean correction
was biased low exactly where PZT 4 moves far (docs/generated/paper_scale.md, the absolute
experiment against the true mean).

The trend is on wherever a source is selected (``mean_shift: true``, the default): the physics
says a shift exists wherever the scatter does, and the data say how large it is, with the
coefficients' vague Gaussian prior keeping it near zero where they say little and their
uncertainty in f's variance. The model's bound is not the judge here: inside the training moves
f's SE part takes up a shift that the trend extrapolates beyond them, so the bound can prefer
the model that predicts worse at moves from the zero state (tests/models/test_mean_shift.py
plants the paper-scale physics in the independent stage generator and requires the trend to
lower the mean error there on every seed it runs). The bounds' difference is
recorded (``gain_nats``: the log Bayes factor of the trend, its coefficients integrated out). A
gated source (a reversal, which reads the move's context) is not a feature of the trend; a model
with no selected source has none.
"""

from __future__ import annotations

from typing import Callable, Sequence

import numpy as np

from microctl.gp.shaped_features import GATED, ShapedFeatures
from microctl.gp.vhgpr import FittedVHGPR

__all__ = ["trend_features", "with_mean_shift"]


def trend_features(names: Sequence[str], rows: Sequence[np.ndarray], offsets: Sequence[float],
                   shapes: Sequence[str], params: Sequence[tuple[float, float]], d: int) -> ShapedFeatures | None:
    """The ungated selected sources as features of x = [s; u] (its first d columns), or None.

    Parameters
    ----------
    names, shapes : sequence of str
        One per selected source.
    rows : sequence of ndarray, each shape (>= d,)
        The linear map of each source on x (and the move's context, which an ungated source
        does not read).
    offsets : sequence of float
    params : sequence of (float, float)
    d : int
        Width of x = [s; u].
    """
    keep = [j for j, s in enumerate(shapes) if s not in GATED
            and not np.any(np.asarray(rows[j], dtype=float)[d:])]
    if not keep:
        return None
    A = np.array([np.asarray(rows[j], dtype=float)[:d] for j in keep])
    return ShapedFeatures(A, np.array([float(offsets[j]) for j in keep]), tuple(shapes[j] for j in keep),
                          np.array([params[j] for j in keep], dtype=float).reshape(len(keep), 2), np.ones(len(keep)),
                          tuple(names[j] for j in keep))


def with_mean_shift(model: FittedVHGPR, features: ShapedFeatures | None,
                    refit: Callable[[ShapedFeatures, FittedVHGPR], FittedVHGPR]) -> tuple[FittedVHGPR, dict | None]:
    """``model`` refitted with the features' trend in f (``model`` itself without features).

    Parameters
    ----------
    model : FittedVHGPR
        The residual model without the trend.
    features : ShapedFeatures or None
        :func:`trend_features` (None: ``model`` and no record).
    refit : callable
        ``refit(features, warm_start) -> FittedVHGPR``: the same fit with f's trend, started
        from ``model``.

    Returns
    -------
    model : FittedVHGPR
    record : dict or None
        ``{"features", "gain_nats"}`` (None without features): the features and the log Bayes
        factor of the trend (the bounds' difference, for the record).
    """
    if features is None:
        return model, None
    trial = refit(features, model)
    return trial, {"features": list(features.names), "gain_nats": float(trial.bound - model.bound)}
