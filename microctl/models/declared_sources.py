"""Noise sources named by the user instead of selected by the data.

The default residual model selects the stage's noise sources among the candidates of
:mod:`microctl.models.noise_dictionary` by evidence (:func:`~microctl.models.noise_dictionary.select_features`).
A lab that knows its stage (from its construction, or from ``microctl diagnose`` on an earlier
log) can name them instead (``ResidualModelSettings.noise_sources``, ``microctl train
--noise-source``, ``training.noise_sources`` in an experiment file). A name is either

- a candidate (``dq4:sat@4``, ``drx:sq``, ``q2:bump@16``): that candidate enters as it is; or
- a physical quantity (``dq4``: actuator 4's step, ``drx``: the platform's rotation about x over
  the move, ``q2``: actuator 2's position, ``f1``: ball 1's contact force, ``rx``: the pose's
  rotation; :func:`~microctl.models.noise_dictionary.quantity`): the shape of that quantity whose
  variance model fits the residuals best, with the sources named before it in the model, enters
  (the names are taken in the order given).

Every named source stays in the model: no significance test and no pruning (they are the user's
knowledge, not a finding), and the controller's least-motion rule weighs no other candidate
against them (:mod:`microctl.control.credible`: the model stores no alternatives). An empty list
names no source: the paper's constant prior mean of g.
``scripts/bench_rigs.py`` uses this as the ``told`` reference: the default model told the
quantities that carry each simulated rig's true scatter, which separates what the selection
misses from what the data and the rest of the model cannot resolve.
"""

from __future__ import annotations

import math
from typing import Sequence

import numpy as np

from microctl.errors import ConfigError
from microctl.models.noise_dictionary import Selection, fit_variance_with, quantity

__all__ = ["declared_selection"]


def declared_selection(residual: np.ndarray, candidates: np.ndarray, names: Sequence[str],
                       declared: Sequence[str]) -> Selection:
    """The candidates the user named (module docstring), each with the likelihood it adds.

    Parameters
    ----------
    residual : ndarray, shape (n,)
        Residual of the mean correction at the training inputs.
    candidates : ndarray, shape (n, P)
        Candidate features at the training inputs (non-negative).
    names : sequence of str, length P
        The candidates' names.
    declared : sequence of str
        Candidate names or quantities (``quantity(name)`` of a candidate), distinct.

    Returns
    -------
    Selection
        ``gains``: the maximised log-likelihood each adds to those before it (nats);
        ``thresholds``: the BIC's half log n, for the record; no p-values.

    Raises
    ------
    ConfigError
        A name that is neither a candidate nor a quantity of this stage (the message lists the
        quantities), or two names that resolve to the same candidate.
    """
    r2, Phi = np.asarray(residual, dtype=float) ** 2, np.asarray(candidates, dtype=float)
    names = list(names)
    quantities = list(dict.fromkeys(quantity(nm) for nm in names))
    chosen: list[int] = []
    gains: list[float] = []
    ll, _ = fit_variance_with(r2, Phi[:, :0], None, None)
    for name in declared:
        if name in names:
            options = [names.index(name)]
        elif name in quantities:
            options = [j for j, nm in enumerate(names) if quantity(nm) == name and j not in chosen]
        else:
            raise ConfigError(f"noise source {name!r} is neither a noise-source candidate nor a quantity of this stage; "
                              f"valid quantities: {', '.join(quantities)} (or a candidate name such as "
                              f"{names[0]!r}: docs/controller.md, the noise model)")
        if not options or options[0] in chosen:
            raise ConfigError(f"noise source {name!r} names a source already named ({names[options[0]] if options else name}); "
                              "name each source once")
        fits = [(fit_variance_with(r2, Phi[:, chosen + [j]], None, None)[0], j) for j in options]
        best_ll, best = max(fits, key=lambda t: t[0])  # ties: the first shape (the dictionary's order)
        chosen.append(best)
        gains.append(best_ll - ll)
        ll = best_ll
    half_log_n = 0.5 * math.log(max(len(r2), 2))
    return Selection(tuple(chosen), tuple(names[j] for j in chosen), tuple(gains), (half_log_n,) * len(chosen), ll)
