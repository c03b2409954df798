"""Whether g's GP pays for itself: the ``dictionary`` noise model's last step with ``g_gp: auto``.

The dictionary model writes g, the log noise variance, as a parametric prior mean (the noise
sources the data selected, :mod:`microctl.models.noise_dictionary`) plus a GP on x = [s; u]
for what the sources leave (:mod:`microctl.gp.noise_prior`). The GP's k_g + 1 hyperparameters
(an ARD lengthscale per input and a signal variance) are fitted by the variational bound, and on
a few hundred moves they can follow the scatter of the squared residuals: a lengthscale a small
fraction of an input's spread, a log variance that rises and dips along it. The controller seeks
the lowest predicted noise, so it finds those dips, and the truth is not lower there.

So the GP, like f's SE part (``se: auto``, :class:`~microctl.gp.trainer.VHGPR`), must pay for
its hyperparameters: the model is refitted with g's GP switched off (g is then its prior mean;
started where the full fit ended) and the GP is kept only if the bound with it is higher by more
than the BIC's (k_g + 1)/2 log n. A noise structure the dictionary does not have, and that the
data show, pays for the GP many times over; a prior mean that already explains the scatter does
not. Both bounds and the decision are in the model's ``info["noise_selection"]["g_gp"]``.
"""

from __future__ import annotations

from typing import Callable

from microctl.gp.fitted import FittedVHGPR
from microctl.util.bic import bic_penalty

__all__ = ["g_gp_penalty", "select_g_gp"]


def g_gp_penalty(model: FittedVHGPR, n: int) -> float:
    """The BIC's price of g's GP on n rows: half log n per hyperparameter (lengthscales, signal
    variance, and the bias variance when g's kernel has one)."""
    k = len(model.g_log_lengthscales) + 1 + (model.g_log_bias_var is not None)
    return bic_penalty(k, n)


def select_g_gp(model: FittedVHGPR, without_gp: Callable[[], FittedVHGPR], n: int) -> tuple[FittedVHGPR, dict]:
    """``model`` if its g's GP pays for itself on n rows, else the refit ``without_gp()`` returns.

    Parameters
    ----------
    model : FittedVHGPR
        The fit with g's GP.
    without_gp : callable
        Fits the same model with g's GP switched off.
    n : int
        Rows the models were fitted on.

    Returns
    -------
    model : FittedVHGPR
    record : dict
        ``bound_with_gp``, ``bound_without_gp``, ``penalty`` (nats) and ``kept_gp``.
    """
    off = without_gp()
    penalty = g_gp_penalty(model, n)
    kept = bool(float(model.bound) - float(off.bound) > penalty)
    record = {"bound_with_gp": float(model.bound), "bound_without_gp": float(off.bound), "penalty": float(penalty),
              "kept_gp": kept}
    return (model if kept else off), record
