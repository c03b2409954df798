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

__all__ = ["G_INPUTS", "G_STARTS", "actuator_inputs", "g_input_map", "step_map"]


def step_map(afm: AnalyticForwardModel) -> np.ndarray:
    """The steps ``dq_i = K_i u - q_i,prev`` (eq. 12) as a map of x = [t_prev; q_prev; u] (eq. 3).

    Returns
    -------
    ndarray, shape (n_q, n_s + n_p)
        Row i: -1 at ``q_i,prev``, K_i on u.
    """
    A = np.zeros((afm.n_q, afm.n_s + afm.n_p))
    A[np.arange(afm.n_q), 1 + np.arange(afm.n_q)] = -1.0  # s = [t_prev; q_prev]
    A[:, afm.n_s:] = afm.K
    return A


def actuator_inputs(afm: AnalyticForwardModel) -> tuple[np.ndarray, tuple[str, ...]]:
    """The map A (2 n_q, n_s + n_p) from x = [t_prev; q_prev; u] to [q; dq] (eq. 12), and row names.

    Returns
    -------
    A : ndarray, shape (2 n_q, n_s + n_p)
        Rows 0..n_q-1: ``q_i = K_i u``; rows n_q..2 n_q-1: ``dq_i = K_i u - q_i,prev``
        (:func:`step_map`).
    names : tuple of str
        The actuators' names (``q1``, ...), then each with a ``d`` in front (``dq1``, ...).
    """
    positions = np.zeros((afm.n_q, afm.n_s + afm.n_p))
    positions[:, afm.n_s:] = afm.K
    names = tuple(afm.actuator_names) + tuple(f"d{a}" for a in afm.actuator_names)
    return np.vstack([positions, step_map(afm)]), names


#: The choices of ``g_inputs``: a map builder, or None for the raw inputs.
G_INPUTS: dict[str, Callable[[AnalyticForwardModel], tuple[np.ndarray, tuple[str, ...]]] | None] = {
    "raw": None,
    "actuators": actuator_inputs,
}


#: The choices of the residual model's ``g_start`` (:class:`~microctl.gp.trainer.VHGPR`: the
#: exact form's start of g; the sparse form always uses ``"both"``).
G_STARTS = ("f", "residuals")


def g_input_map(name: str, afm: AnalyticForwardModel) -> tuple[np.ndarray | None, tuple[str, ...]]:
    """The map and row names of the ``g_inputs`` choice ``name`` (None, () for ``raw``)."""
    build = G_INPUTS[name]
    return (None, ()) if build is None else build(afm)
