"""Kinematic matrices of a contact-driven flexure platform (paper III-A, eq. 5-13).

J_h (eq. 5), the contact twist transfer P_i and frame R̄_i (eq. 6-8), the contact map
H R̄^T J and the inverse kinematics K (eq. 10-12), and the tool vector w (eq. 13), from a
:class:`~microctl.stage.geometry.Stage` with its static corrections applied
(:func:`microctl.stage.causes.stage_parts`). The AFM built on them is
:class:`microctl.models.afm.AnalyticForwardModel`.
"""

from __future__ import annotations

from functools import lru_cache
from typing import Sequence

import numpy as np

from microctl.stage.causes import MEAN_KINDS, Effects, StageParts, stage_parts
from microctl.stage.geometry import TWIST_COMPONENTS, Stage


def skew(r: Sequence[float]) -> np.ndarray:
    """Cross-product matrix S(r) of the paper (S(r) x = r × x), shape (3, 3)."""
    r1, r2, r3 = r
    return np.array([[0.0, -r3, r2], [r3, 0.0, -r1], [-r2, r1, 0.0]])


def hinge_jacobian(dof: Sequence[str]) -> np.ndarray:
    """J_h of eq. 5: the twist v = J_h ṗ allowed by the hinge, shape (6, n_p).

    For the default DoF (z, rx, ry) this is [0_{3×2} I_3 0_{3×1}]^T.
    """
    Jh = np.zeros((6, len(dof)))
    for j, name in enumerate(dof):
        Jh[TWIST_COMPONENTS.index(name), j] = 1.0
    return Jh


def twist_transfer(point_mm: Sequence[float]) -> np.ndarray:
    """P_i of eq. 6 for a point, shape (6, 6): [[I, 0], [S(c), I]].

    P_i^T [v; ω] = [v + ω × c; ω] is the twist of the point c on the platform.
    """
    P = np.eye(6)
    P[3:, :3] = skew(point_mm)
    return P


def contact_frame(normal: Sequence[float]) -> np.ndarray:
    """R_i = [n_i o_i a_i] of eq. 6, a right-handed orthonormal frame with n_i first.

    The choice of o_i and a_i is arbitrary (the paper's words); H_i keeps only n_i.
    """
    return _contact_frame(tuple(float(x) for x in normal)).copy()


@lru_cache(maxsize=64)
def _contact_frame(normal: tuple[float, ...]) -> np.ndarray:
    n = np.asarray(normal, dtype=float)
    helper = np.array([1.0, 0.0, 0.0]) if abs(n[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    o = np.cross(n, helper)
    o /= np.linalg.norm(o)
    a = np.cross(n, o)
    return np.column_stack([n, o, a])


def contact_map(stage: Stage, corrections: Effects | StageParts | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The stacked contact matrices of eq. 9.

    Parameters
    ----------
    stage : Stage
    corrections : Effects or StageParts, optional
        Causes to apply to the CAD contact points (contact offsets), or the stage's parts
        with them already applied (:func:`microctl.stage.causes.stage_parts`).

    Returns
    -------
    hrj : ndarray, shape (n_c, n_q)
        H R̄^T J: normal ball velocity per actuator velocity.
    hrp : ndarray, shape (n_c, 6)
        H R̄^T P^T: normal velocity of each contact point per platform twist.
    """
    n_q = stage.n_act
    H_rows_J = []
    H_rows_P = []
    H_i = np.zeros((1, 6))
    H_i[0, 0] = 1.0  # eq. 8: only the normal translational component is transmitted
    parts = corrections if isinstance(corrections, StageParts) else stage_parts(stage, corrections, MEAN_KINDS)
    for i, (a, c) in enumerate(zip(stage.actuators, parts.contacts_mm)):
        R = contact_frame(a.normal)
        Rbar = np.zeros((6, 6))
        Rbar[:3, :3] = R
        Rbar[3:, 3:] = R
        J_i = np.zeros((6, n_q))  # eq. 7: actuator i translates its ball along d_i
        J_i[:3, i] = a.direction
        H_rows_J.append(H_i @ Rbar.T @ J_i)
        H_rows_P.append(H_i @ Rbar.T @ twist_transfer(c).T)
    return np.vstack(H_rows_J), np.vstack(H_rows_P)


def inverse_kinematics_matrix(stage: Stage, corrections: Effects | StageParts | None = None) -> np.ndarray:
    """K of eq. 12, q = K p, shape (n_q, n_p)."""
    hrj, hrp = contact_map(stage, corrections)
    return np.linalg.solve(hrj, hrp @ hinge_jacobian(stage.dof))


def tool_vector(stage: Stage, corrections: Effects | StageParts | None = None) -> np.ndarray:
    """w of eq. 13, t = w · p relative to the zero state, shape (n_p,).

    T_s (P_t^T J_h p + t0) with T_s = [s^T 0]: the gauge reads the translation of the tool
    point along the sensor direction s; the constant T_s t0 cancels against the zero state.
    ``corrections`` (Effects or StageParts) may move t0 (a tool offset).
    """
    parts = corrections if isinstance(corrections, StageParts) else stage_parts(stage, corrections, MEAN_KINDS)
    t0 = parts.tool_mm
    Ts = np.concatenate([np.asarray(stage.tool.direction, dtype=float), np.zeros(3)])
    return Ts @ twist_transfer(t0).T @ hinge_jacobian(stage.dof)
