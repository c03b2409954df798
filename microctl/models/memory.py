"""What the AFM must remember between moves: the hysteresis loop's play states.

A stage whose ``stage.corrections`` hold ``hysteresis`` (:class:`~microctl.stage.causes.Hysteresis`,
a Prandtl-Ishlinskii sum of play operators on each actuator's command,
:mod:`microctl.stage.hysteresis`) reads differently at the same command q depending on how the
actuators got there: the output depends on the whole command history, not only on the state
s = [t; q_prev] of eq. 3. The residual GP sees x = [s; u] and cannot learn that memory, so the
AFM applies it, and the state of the model becomes s plus the play states z (n_q, N_PLAY).

The memory acts on the prediction as a shift of the tool displacement (eq. 13 with the actual
actuator positions instead of the commands; static corrections as in the AFM):

    z'   = max(q - r, min(q + r, z))                 (the play operators step to q = K u)
    d_h  = c . (w (sum_j z'_j - N q) + h)             (the loop's offset, relative to the zero state)
    t    = sensor(w_pred . u + d_h)

with ``c`` the tool displacement per µm of actual actuator position (``w_pred = c K``) and ``+ h``
because the zero state (the gauge's zero) is approached from below (its offset is -h). Backlash,
whose memory is only the direction of the last step, sign(q - q_prev), a function of x, stays
with the GP; contact loss and drift too (:meth:`AnalyticForwardModel.dynamic_corrections_note`).

The controllers meet the target with the memory through :mod:`microctl.control.memory`; the
training residual subtracts the shift along the log's command run
(:func:`microctl.models.training.residual_dataset`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from microctl.stage import hysteresis
from microctl.stage.sensor import Sensor

__all__ = ["ActuatorMemory"]


@dataclass(frozen=True)
class ActuatorMemory:
    """The hysteresis memory of a stage's model corrections (inactive when there is none).

    Parameters
    ----------
    r : ndarray, shape (n_q, N_PLAY)
        Play thresholds, µm (0 rows where an actuator has no hysteresis).
    w : ndarray, shape (n_q,)
        Play weights (0 where an actuator has no hysteresis).
    h : ndarray, shape (n_q,)
        Major-loop half-widths, µm (the zero state's offset is -h).
    c : ndarray, shape (n_q,)
        Tool displacement per µm of actual actuator position under the static corrections, µm/µm.
    sensor : Sensor
        The gauge transfer of the static corrections.
    """

    r: np.ndarray
    w: np.ndarray
    h: np.ndarray
    c: np.ndarray
    sensor: Sensor

    @classmethod
    def from_parts(cls, half_width_um: np.ndarray, range_um: np.ndarray, c: np.ndarray,
                   sensor: Sensor) -> "ActuatorMemory":
        """Build from the per-actuator ``hysteresis`` parameters (:class:`~microctl.stage.causes.StageParts`)."""
        h = np.asarray(half_width_um, dtype=float).reshape(-1).copy()
        r = hysteresis.thresholds(range_um)
        w = hysteresis.weights(h, range_um)
        for a in (r, w, h):
            a.setflags(write=False)
        c = np.asarray(c, dtype=float).reshape(-1).copy()
        c.setflags(write=False)
        return cls(r=r, w=w, h=h, c=c, sensor=sensor)

    @property
    def active(self) -> bool:
        """Whether some actuator has hysteresis (then the model's state carries play states)."""
        return bool(np.any(self.w > 0))

    @property
    def shape(self) -> tuple[int, int]:
        """Shape of the play states, (n_q, N_PLAY)."""
        return self.r.shape

    def zero(self) -> np.ndarray:
        """Play states at the zero state (approached from below), shape (n_q, N_PLAY)."""
        return hysteresis.zero_play(self.r[:, -1])

    def check(self, z: np.ndarray | None) -> np.ndarray:
        """``z`` as play states of this model (default the zero state's); ValueError on a wrong shape."""
        if z is None:
            return self.zero()
        z = np.asarray(z, dtype=float)
        if z.shape != self.shape or not np.all(np.isfinite(z)):
            raise ValueError(f"play states must be {self.shape[0]} x {self.shape[1]} finite numbers, got shape "
                             f"{z.shape}")
        return z

    def step(self, z: np.ndarray | None, q: np.ndarray) -> np.ndarray:
        """Play states after a move to the commands q (n_q,) from the states z (default zero)."""
        return hysteresis.play_step(self.check(z), np.asarray(q, dtype=float).reshape(-1), self.r)

    def after_run(self, q_run: np.ndarray, z0: np.ndarray | None = None) -> np.ndarray:
        """Play states after the commands ``q_run`` (m, n_q) in execution order from ``z0``."""
        z = self.check(z0)
        for q in np.atleast_2d(np.asarray(q_run, dtype=float)):
            z = hysteresis.play_step(z, q, self.r)
        return z

    def displacement_shift(self, z_before: np.ndarray | None, q: np.ndarray) -> np.ndarray:
        """The loop's tool displacement d_h at commands q from the play states before the move, µm.

        Parameters
        ----------
        z_before : ndarray, shape (n_q, N_PLAY), optional
        q : ndarray, shape (n_q,) or (m, n_q)

        Returns
        -------
        ndarray, shape () or (m,)
        """
        q = np.asarray(q, dtype=float)
        q2 = np.atleast_2d(q)
        z = hysteresis.play_step(self.check(z_before), q2, self.r)  # (m, n_q, N_PLAY)
        out = (hysteresis.offset(self.w, z, q2) + self.h) @ self.c
        return out if q.ndim == 2 else float(out[0])

    def run_shift(self, q: np.ndarray, q_prev: np.ndarray) -> np.ndarray:
        """d_h of every row of a log in execution order (each row feeds q_prev, then q), µm, shape (m,)."""
        q = np.atleast_2d(np.asarray(q, dtype=float))
        z = hysteresis.play_run(self.r, q, q_prev, z0=self.zero())
        return (hysteresis.offset(self.w, z, q) + self.h) @ self.c

    def reading_shift(self, d: np.ndarray, d_h: np.ndarray) -> np.ndarray:
        """How much the reading moves when the loop adds ``d_h`` to the AFM's displacement ``d``, µm."""
        return self.sensor.forward(np.asarray(d) + d_h) - self.sensor.forward(np.asarray(d))

    def shift_at(self, z_before: np.ndarray | None, q: np.ndarray) -> float:
        """The loop's reading shift at commands q (n_q,) from the play states before the move, µm
        (the AFM's displacement there is c . q, since w_pred = c K)."""
        q = np.asarray(q, dtype=float).reshape(-1)
        return float(self.reading_shift(float(self.c @ q), self.displacement_shift(z_before, q)))
