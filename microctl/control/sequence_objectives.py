"""What sequence control minimises over the moves' r_e (``ControllerSettings.sequence_objective``).

Each sequence objective is a class registered in :data:`SEQUENCE_OBJECTIVES` under its setting
name, used by both the EAFM sequence controller (:mod:`microctl.control.sequence`) and the
sequence oracle on the truth (:class:`~microctl.control.oracle.OracleSequenceController`):

- ``sum`` (:class:`SumObjective`): the cumulative r_e of the moves (µm²);
- ``max`` (:class:`MaxObjective`): the worst move's r_e, plus the cumulative one with weight
  :data:`MAX_TIE_WEIGHT` per move, which picks one plan among those with the same worst move.

An objective gives its value of a plan's r_e (:meth:`SequenceObjective.value`), its scale
(the NLP's J_ref), its CasADi form (:meth:`SequenceObjective.nlp`, the objective and the extra
variables, constraints and bounds of the multi-stage NLP) and its dynamic-programming rules: the
score of a DP label (worst move, cumulative r_e) and the choice of a predecessor.
"""

from __future__ import annotations

from typing import ClassVar

import casadi as ca
import numpy as np

from microctl.control.registry import Registry

__all__ = ["SEQUENCE_OBJECTIVES", "MAX_TIE_WEIGHT", "SequenceObjective", "SumObjective", "MaxObjective"]

#: The sequence objectives by setting name (``ControllerSettings.sequence_objective``).
SEQUENCE_OBJECTIVES: Registry = Registry("sequence objective")

#: Weight of the cumulative r_e (per move) added to the worst move's r_e with
#: ``sequence_objective = "max"``: among plans with the same worst move, the quietest overall.
MAX_TIE_WEIGHT = 1e-3


class SequenceObjective:
    """A function of the per-move r_e of a plan, to be minimised (base class).

    Attributes
    ----------
    name : str
        The setting's name.
    description : str
        What is minimised, in words.
    """

    name: ClassVar[str]
    description: ClassVar[str]

    def value(self, r: np.ndarray) -> float:
        """The objective of per-move r_e values (µm²), shape (T,)."""
        raise NotImplementedError

    def scale(self, r: np.ndarray) -> float:
        """The NLP's objective scale J_ref from a start's per-move r_e, shape (T,)."""
        raise NotImplementedError

    def nlp(self, x_u: ca.MX, r: ca.MX, jref: ca.MX, T: int) -> tuple[ca.MX, ca.MX, list[ca.MX]]:
        """The NLP's variables x, objective f and extra constraints g (after the plan's own).

        Parameters
        ----------
        x_u : casadi.MX, shape (T n_p,)
            The commands.
        r : casadi.MX, shape (T,)
            r_e of each move.
        jref : casadi.MX
            The objective scale (a parameter).
        """
        raise NotImplementedError

    def bounds(self, lbx: np.ndarray, ubx: np.ndarray, lbg: np.ndarray, ubg: np.ndarray, T: int
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The plan's bounds (commands; constraints) extended by those of :meth:`nlp`'s extras."""
        return lbx, ubx, lbg, ubg

    def x0(self, u0: np.ndarray, r0: np.ndarray, jref: float) -> np.ndarray:
        """The NLP's start from the commands u0 (shape (T n_p,)) and their r_e, shape (T,)."""
        return u0

    def score(self, worst: np.ndarray, total: np.ndarray, T: int) -> np.ndarray:
        """The value of DP labels (worst move so far, cumulative r_e), elementwise; T the horizon."""
        raise NotImplementedError

    def predecessor(self, worst: np.ndarray, total: np.ndarray) -> np.ndarray:
        """The sequence controller's DP choice: for each candidate j (column), the row i of the
        best label (``worst[i, j]``, ``total[i, j]``: arriving at j from predecessor i)."""
        raise NotImplementedError


@SEQUENCE_OBJECTIVES.register
class SumObjective(SequenceObjective):
    """``sum_k r_e(s_{k-1}, u_k)``: the cumulative noise variance (µm²)."""

    name = "sum"
    description = "the sum of the moves' r_e"

    def value(self, r: np.ndarray) -> float:
        return float(np.sum(r))

    def scale(self, r: np.ndarray) -> float:
        return float(np.sum(r))

    def nlp(self, x_u, r, jref, T):
        return x_u, ca.sum1(r) / jref, []

    def score(self, worst, total, T):
        return total

    def predecessor(self, worst, total):
        return np.argmin(total, axis=0)  # Bellman: exact


@SEQUENCE_OBJECTIVES.register
class MaxObjective(SequenceObjective):
    """``max_k r_e(s_{k-1}, u_k) + MAX_TIE_WEIGHT mean_k r_e``: the worst move's, ties broken by
    the cumulative one. In the NLP an epigraph variable z (``r_k / J_ref <= z``)."""

    name = "max"
    description = "the worst move's r_e"

    def value(self, r: np.ndarray) -> float:
        return float(np.max(r) + MAX_TIE_WEIGHT * np.mean(r))

    def scale(self, r: np.ndarray) -> float:
        return float(np.max(r))

    def nlp(self, x_u, r, jref, T):
        z = ca.MX.sym("z")
        return ca.vertcat(x_u, z), z + MAX_TIE_WEIGHT * ca.sum1(r) / (T * jref), [r / jref - z]

    def bounds(self, lbx, ubx, lbg, ubg, T):
        return np.append(lbx, 0.0), np.append(ubx, np.inf), np.append(lbg, np.full(T, -np.inf)), np.append(
            ubg, np.zeros(T))

    def x0(self, u0, r0, jref):
        return np.append(u0, float(np.max(r0)) / jref)

    def score(self, worst, total, T):
        return worst + MAX_TIE_WEIGHT * total / T

    def predecessor(self, worst, total):
        # exact minimax (the worst move so far); among predecessors with the same worst move,
        # the smaller cumulative r_e (a tie-break only: (max, sum) has no exact one-label DP)
        tie = worst <= worst.min(axis=0) * (1.0 + 1e-12)
        return np.argmin(np.where(tie, total, np.inf), axis=0)
