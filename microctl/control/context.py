"""Controllers for a model that reads the move's context (each actuator's last direction).

A model with a reversal noise source (:mod:`microctl.models.noise_dictionary`, ``rev``) predicts
a move's scatter from x = [s; u] *and* the direction each actuator last moved in
(:mod:`microctl.models.direction`), which whoever moves the stage tracks from the commands it
sent. The direction is fixed during a solve, so it is built into the EAFM's graph
(:meth:`~microctl.models.eafm.EAFM.with_direction`) and each direction met gets its own
controller, built on first use and kept (at most 2^n_q of them). A model without such a source
has one controller whatever the direction.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from microctl.control.result import Controller
from microctl.models.eafm import EAFM

__all__ = ["ByDirection"]


class ByDirection:
    """The controller of ``make(eafm.with_direction(d))`` for each direction d, built once.

    Parameters
    ----------
    eafm : EAFM
    make : callable
        ``make(eafm) -> Controller``.
    """

    def __init__(self, eafm: EAFM, make: Callable[[EAFM], Controller]):
        self.eafm = eafm
        self._make = make
        self._built: dict[tuple[float, ...], Controller] = {}

    def __call__(self, direction: np.ndarray | None = None) -> Controller:
        """The controller for moves after the actuators last moved in ``direction`` (n_q values of
        +1 or -1; None: the zero state's, all +1)."""
        eafm = self.eafm.with_direction(direction)
        key = tuple(eafm.direction.tolist()) if eafm.uses_direction else ()
        if key not in self._built:
            self._built[key] = self._make(eafm)
        return self._built[key]
