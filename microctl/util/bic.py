"""The Bayesian information criterion's price of parameters (Schwarz 1978).

A model with k more free parameters must raise the maximised log-likelihood (or bound) by more
than ``k log(n) / 2`` on n rows to be preferred. The package compares nested models this way in
several places (f's SE part, g's GP, a noise source entering the dictionary, the alternatives the
controller weighs); they all price parameters with :func:`bic_penalty`.
"""

from __future__ import annotations

import math

__all__ = ["bic_penalty"]


def bic_penalty(k: float, n: int) -> float:
    """``k log(n) / 2``: the log-likelihood k extra parameters must gain on n rows (BIC).

    Parameters
    ----------
    k : float
        Number of extra parameters (> 0).
    n : int
        Number of rows (>= 1).

    Returns
    -------
    float
    """
    return 0.5 * k * math.log(n)
