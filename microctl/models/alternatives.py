"""The noise sources a model's selection did not take, each weighed by its evidence.

The dictionary selection (:mod:`microctl.models.noise_dictionary`) keeps a source only when it
is significant at a family-wise level; a source the data cannot rule out is then absent from g,
whose posterior says "flat, and certain" about it. ``microctl train`` stores, for every
candidate source j of the stage's dictionary, its best size c_j when it is added alone to the
selected model and the log-likelihood gain G_j it had on the training residuals
(``info["noise_selection"]["alternatives"]``, :func:`~microctl.models.noise_dictionary.alternatives`).
With BIC weights ``w_j = exp(G_j - log(n) / 2)`` against 1 for the selected model (one parameter
more), the model-averaged extra noise variance of a move is

    v_alt(x) = sum_j w_j c_j phi_j(x) / (1 + sum_j w_j)                 (µm²)

(the average of the noise variance over the selected model and the models "selected + source
j", minus the selected model's). It is what the least-motion rule weighs
(:mod:`microctl.control.credible`) and what eq. 4's objective adds with
``ControllerSettings.weigh_alternatives``. A model file written before the alternatives were
stored has none: ``v_alt = 0``.
"""

from __future__ import annotations

from typing import Any

import casadi as ca
import numpy as np

from microctl.gp.shaped_features import GATED, ShapedFeatures
from microctl.models.noise_dictionary import alternatives
from microctl.util.bic import bic_penalty

__all__ = ["Alternatives", "alternatives_record"]


class Alternatives:
    """The stage's candidate noise sources, each added alone at its best size, weighed by evidence.

    Parameters
    ----------
    model_info : dict
        The residual model's ``info``; its ``["noise_selection"]["alternatives"]`` (name ->
        [coefficient per unit of the candidate at scale 1, log-likelihood gain in nats]) and
        ``["noise_selection"]["n"]`` (training moves) are read.
    candidates : ShapedFeatures
        The stage's candidate features of x = [s; u]
        (:func:`~microctl.models.noise_dictionary.candidate_features`); those with a stored entry
        and no gate are used (the ``rev`` sources read the move's context: not weighed here).
    """

    def __init__(self, model_info: dict | None, candidates: ShapedFeatures):
        record = (model_info or {}).get("noise_selection", {}) or {}
        alts = record.get("alternatives") or {}
        # a source that reads the move's context (a reversal) is not weighed here: x = [s; u] alone
        idx = [j for j, nm in enumerate(candidates.names) if nm in alts and candidates.shapes[j] not in GATED]
        self.features: ShapedFeatures | None = candidates.subset(idx) if idx else None
        self.coef = np.array([float(alts[candidates.names[j]][0]) for j in idx])
        gain = np.array([float(alts[candidates.names[j]][1]) for j in idx])
        n = max(int(record.get("n", 1)), 1)
        w = np.exp(gain - bic_penalty(1, n))  # BIC: one parameter more than the selected model
        #: Normalised weights w_j / (1 + sum w), shape (p,).
        self.weights = w / (1.0 + float(np.sum(w)))

    def values(self, X: np.ndarray) -> np.ndarray:
        """``v_alt`` at the rows of X = [s, u] (shape (m, n_s + n_p)), µm², shape (m,)."""
        X = np.atleast_2d(np.asarray(X, dtype=float))
        if self.features is None:
            return np.zeros(X.shape[0])
        return self.features.values(X) @ (self.weights * self.coef)

    def casadi(self, x: ca.MX) -> ca.MX:
        """``v_alt`` for a symbolic x = [s; u] (n_s + n_p, 1), µm², shape (1, 1)."""
        if self.features is None:
            return ca.MX(0.0)
        return self.features.casadi_dot(x, self.weights * self.coef)

    def expected_excess(self, state: np.ndarray, u_a: np.ndarray, u_b: np.ndarray) -> float:
        """``v_alt(a) - v_alt(b)`` for two moves from ``state``, µm² (0 without alternatives).

        Parameters
        ----------
        state : ndarray, shape (n_s,)
        u_a, u_b : ndarray, shape (n_p,)
        """
        s = np.asarray(state, dtype=float)
        X = np.vstack([np.concatenate([s, np.asarray(u_a, dtype=float)]),
                       np.concatenate([s, np.asarray(u_b, dtype=float)])])
        v = self.values(X)
        return float(v[0] - v[1])


def alternatives_record(model: Any, data: Any, afm: Any, cands: ShapedFeatures) -> dict:
    """Every candidate added alone at its best size to ``model``'s noise, with its likelihood gain:
    ``{name: [coefficient per unit of the candidate at scale 1, gain in nats]}`` (what ``microctl
    train`` stores; ``model`` a FittedVHGPR, ``data`` its ResidualData, ``afm`` the stage's AFM)."""
    Xc = data.context_inputs(afm.n_q)  # x = [s; u] and the move's context
    pred = model.predict(Xc if model.n_context else data.X)
    coef, gain = alternatives(data.y - pred.f_mean, np.exp(pred.g_mean), cands.values(Xc))
    coef = coef / np.asarray(cands.scale, dtype=float)
    return {nm: [float(c), float(g)] for nm, c, g in zip(cands.names, coef, gain)}
