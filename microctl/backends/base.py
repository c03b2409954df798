"""The stage backend interface: one move in, one measurement out.

A backend drives a stage (simulated or hardware) with control signals u = p (the hinge
pose of eq. 5) and returns the gauge reading t after the move has settled. Every move is
converted to actuator commands q = K u with the CAD inverse kinematics (eq. 12) and checked
against the configured actuator ranges *before* anything is sent or changed: a move out of
range raises :class:`~microctl.errors.BackendError` naming the actuator, the value and the
range; it is never clipped and never executed in part.
"""

from __future__ import annotations

import abc
from typing import Callable, TypeVar

import numpy as np

from microctl.errors import BackendError, ConfigError

# Measurement lives beside the log that records it; re-exported here for compatibility.
from microctl.measurement.log import Measurement  # noqa: F401
from microctl.stage.config import StageConfig
from microctl.stage.kinematics import inverse_kinematics_matrix, tool_vector

#: Commands this close outside a range (round-off of K u at a bound) are snapped onto the
#: bound; anything further out is refused. Nothing outside a range is ever sent.
RANGE_TOLERANCE_UM = 1e-9


class StageBackend(abc.ABC):
    """A stage that executes moves (abstract).

    Parameters
    ----------
    config : StageConfig
        The stage (geometry, ranges) and backend settings.

    Attributes
    ----------
    K : ndarray, shape (n_q, n_p)
        CAD inverse kinematics q = K u (eq. 12): what the drivers are sent.
    w : ndarray, shape (n_p,)
        CAD tool map (eq. 13).
    notes : list of str
        What the backend found at connect that the user should know (the serial backend's
        start state and tare; empty for the simulator).
    """

    def __init__(self, config: StageConfig):
        self.config = config
        self.stage = config.stage
        self.K = inverse_kinematics_matrix(config.stage)
        self.w = tool_vector(config.stage)
        self.range_lo = config.stage.range_lo
        self.range_hi = config.stage.range_hi
        self._state = np.zeros(1 + config.stage.n_act)
        self._closed = False
        self.notes: list[str] = []

    # ---- state ---------------------------------------------------------------------
    @property
    def state(self) -> np.ndarray:
        """s = [t; q] after the last move, shape (1 + n_q,).

        Before the first move: the backend's start state (the zero state unless the backend
        reads where the stage stands, as the serial backend does at connect).
        """
        return self._state.copy()

    def _set_state(self, t_um: float, q_um: np.ndarray) -> None:
        self._state = np.concatenate([[float(t_um)], np.asarray(q_um, dtype=float)])

    # ---- checks --------------------------------------------------------------------
    def command_for(self, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Validate a control signal and return (u, q = K u), refusing any out-of-range move.

        Parameters
        ----------
        u : array_like, shape (n_p,)

        Returns
        -------
        u : ndarray, shape (n_p,)
        q : ndarray, shape (n_q,)

        Raises
        ------
        BackendError
            Wrong shape, non-finite values, or an actuator command outside its range.
        """
        if self._closed:
            raise BackendError("the backend is closed")
        u = np.asarray(u, dtype=float).reshape(-1)
        n_p = self.stage.n_dof
        if u.size != n_p:
            raise BackendError(f"control signal has {u.size} entries, the stage has {n_p} DoF {list(self.stage.dof)}")
        if not np.all(np.isfinite(u)):
            raise BackendError(f"control signal {u.tolist()} is not finite")
        q = self.K @ u  # eq. 12
        for i, name in enumerate(self.stage.actuator_names):
            lo, hi = self.range_lo[i], self.range_hi[i]
            if q[i] < lo - RANGE_TOLERANCE_UM or q[i] > hi + RANGE_TOLERANCE_UM:
                raise BackendError(
                    f"move refused: actuator {name} would be commanded to {q[i]:.4f} µm, outside its range "
                    f"[{lo:g}, {hi:g}] µm (u = {np.array2string(u, precision=4)}); nothing was sent"
                )
        return u, np.clip(q, self.range_lo, self.range_hi)  # round-off only (checked above)

    # ---- interface -----------------------------------------------------------------
    @abc.abstractmethod
    def move(self, u: np.ndarray) -> Measurement:
        """Execute one move to control signal u (shape (n_p,)) and read the gauge."""

    @abc.abstractmethod
    def read(self) -> float:
        """A gauge reading now, µm, without moving."""

    def close(self) -> None:
        """Release the stage (idempotent)."""
        self._closed = True

    def __enter__(self) -> "StageBackend":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


# --------------------------------------------------------------------------------------
# the registry of backends by kind
# --------------------------------------------------------------------------------------

#: ``backend.kind`` -> backend class, filled by :func:`register_backend` (the kinds the stage
#: config accepts, :data:`~microctl.stage.config.BACKEND_KINDS`, are all registered:
#: ``tests/backends`` checks it).
BACKENDS: dict[str, type[StageBackend]] = {}

_B = TypeVar("_B", bound=type[StageBackend])


def register_backend(kind: str) -> Callable[[_B], _B]:
    """Class decorator: register a :class:`StageBackend` subclass as the backend of ``backend.kind: kind``."""

    def add(cls: _B) -> _B:
        if kind in BACKENDS:
            raise ValueError(f"backend kind '{kind}' is registered already ({BACKENDS[kind].__name__})")
        BACKENDS[kind] = cls
        return cls

    return add


def make_backend(config: StageConfig, **kwargs) -> StageBackend:
    """The backend ``config.backend.kind`` names, opened and ready to move.

    Parameters
    ----------
    config : StageConfig
    **kwargs
        Passed to the backend's constructor (e.g. ``seed`` for the simulated stage).

    Returns
    -------
    StageBackend

    Raises
    ------
    ConfigError
        No backend is registered for the kind.
    """
    kind = config.backend.kind
    cls = BACKENDS.get(kind)
    if cls is None:
        raise ConfigError(f"{config.source}: backend.kind: '{kind}' is not a backend; valid: {', '.join(BACKENDS)}")
    return cls(config, **kwargs)
