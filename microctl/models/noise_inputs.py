"""The inputs of g's GP: the raw move ``x = [s; u]`` (eq. 3), or the actuators' positions and steps.

g's GP models the log noise variance that g's parametric prior mean (the noise sources of
:mod:`microctl.models.noise_dictionary`) leaves. With ARD on the raw inputs its lengthscales
lie along ``t_prev``, each ``q_i,prev`` and each pose coordinate of u; a scatter that grows
with an actuator's step ``dq_i = K_i u - q_i,prev`` (eq. 12) or with where it ends in its
stroke ``q_i = K_i u`` lies along none of them, so the GP needs short lengthscales on
several inputs at once to follow it. With ``g_inputs: actuators`` g's kernel reads

    [q_1 .. q_nq, dq_1 .. dq_nq] = A x,   q = K u,  dq = K u - q_prev              (eq. 12)

a fixed linear map of x (:mod:`microctl.gp.kernels`), so each ARD lengthscale belongs to one
actuator's position or step. Each ball's contact force is affine in q
(:mod:`microctl.models.noise_dictionary`), so the positions also cover the loads.
:data:`G_INPUTS` is the registry of the setting ``g_inputs``
(:class:`~microctl.models.training.ResidualModelSettings`).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from microctl.models.afm import AnalyticForwardModel

__all__ = ["G_INPUTS", "actuator_inputs", "g_input_map"]


def actuator_inputs(afm: AnalyticForwardModel) -> tuple[np.ndarray, tuple[str, ...]]:
    """The map A (2 n_q, n_s + n_p) from x = [t_prev; q_prev; u] to [q; dq] (eq. 12), and row names.

    Returns
    -------
    A : ndarray, shape (2 n_q, n_s + n_p)
        Rows 0..n_q-1: ``q_i = K_i u``; rows n_q..2 n_q-1: ``dq_i = K_i u - q_i,prev``.
    names : tuple of str
        ``q<name>`` and ``dq<name>`` per actuator.
    """
    nq, ns = afm.n_q, afm.n_s
    A = np.zeros((2 * nq, ns + afm.n_p))
    A[:nq, ns:] = afm.K
    A[nq:, ns:] = afm.K
    A[nq + np.arange(nq), 1 + np.arange(nq)] = -1.0  # s = [t_prev; q_prev]
    names = tuple(afm.actuator_names) + tuple(f"d{a}" for a in afm.actuator_names)  # q1.., dq1..
    return A, names


#: The choices of ``g_inputs``: a map builder, or None for the raw inputs.
G_INPUTS: dict[str, Callable[[AnalyticForwardModel], tuple[np.ndarray, tuple[str, ...]]] | None] = {
    "raw": None,
    "actuators": actuator_inputs,
}


def g_input_map(name: str, afm: AnalyticForwardModel) -> tuple[np.ndarray | None, tuple[str, ...]]:
    """The map and row names of the ``g_inputs`` choice ``name`` (None, () for ``raw``)."""
    build = G_INPUTS[name]
    return (None, ()) if build is None else build(afm)
