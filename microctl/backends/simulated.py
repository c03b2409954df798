"""The simulated stage: the stage model (:class:`~microctl.models.extended.ExtendedForwardModel`) with noise.

One model object is the truth of the moves *and* of the oracle (``true_mean``, ``true_var``),
and the model the diagnosis fits (with candidate causes instead of the planted ones). One
move, in order:

1. q = K u (eq. 12, CAD geometry), refused if out of range (nothing changes);
2. backlash direction per actuator by the one rule (``model.next_direction``: the sign of
   Δq_i, kept when the actuator is held still; the zero state counts as approached "up");
3. actual positions q_act = model.actual_positions(q, direction) + e_driver + e_friction with
   e_driver ~ N(0, driver_accuracy²) per actuator and e_friction,i ~ N(0, (std_i |Δq_i|)²);
4. contact equilibrium p (``model.pose``), the clock advances by move_time_s;
5. reading = model.reading(p, time) + N(0, gauge_noise²) (the sensor of the effects).

Actuator noise and gauge noise come from two independent streams spawned from the seed
(``SeedSequence(seed).spawn(2)``): per move exactly 2·n_q actuator normals (driver first,
then friction) and one gauge normal per reading are drawn, so the emulator, which reads the
gauge through the serial dialect, reproduces the same data.
"""

from __future__ import annotations

import numpy as np

from microctl.backends.base import StageBackend, register_backend
from microctl.errors import BackendError
from microctl.measurement.log import Measurement
from microctl.models.extended import ExtendedForwardModel, ExtendedPrediction
from microctl.stage.config import StageConfig
from microctl.stage.physics import ZERO_STATE_DIRECTION


@register_backend("simulated")
class SimulatedStage(StageBackend):
    """The simulated stage with the effects of ``config.backend.simulated``.

    Parameters
    ----------
    config : StageConfig
    seed : int, optional
        Overrides ``config.backend.simulated.seed``.

    Attributes
    ----------
    truth : ExtendedForwardModel
        The stage model with the true effects (moves and oracle).
    model : ContactModel
        Its physics arrays (``truth.model``).
    direction : ndarray, shape (n_q,)
        Direction each actuator last moved (backlash state).
    time_s : float
        Simulated clock, s.
    """

    def __init__(self, config: StageConfig, seed: int | None = None):
        super().__init__(config)
        sim = config.backend.simulated
        self.settings = sim
        self.seed = int(sim.seed if seed is None else seed)
        act_seq, gauge_seq = np.random.SeedSequence(self.seed).spawn(2)
        self._rng_act = np.random.default_rng(act_seq)
        self._rng_gauge = np.random.default_rng(gauge_seq)
        # the noise-free truth: the stage with the simulated effects through the physics
        self.truth = ExtendedForwardModel(config.stage, sim.effects)
        self.model = self.truth.model
        n = config.stage.n_act
        self._q_cmd = np.zeros(n)
        self.direction = np.full(n, ZERO_STATE_DIRECTION)
        self._p = self.model.p_zero.copy()
        self.time_s = 0.0
        self.moves = 0

    # ---- physical move -------------------------------------------------------------
    def settle(self, q_cmd: np.ndarray) -> None:
        """Move the actuators to commands q (n_q,) (no range check) and settle the platform.

        Used by :meth:`move` and by the emulator, which receives q over the serial dialect.
        """
        q = np.array(q_cmd, dtype=float).reshape(-1)  # a copy: the caller may reuse its array
        dq = q - self._q_cmd
        self.direction = self.truth.next_direction(dq, self.direction)
        z_driver = self._rng_act.standard_normal(q.size)
        z_friction = self._rng_act.standard_normal(q.size)
        q_act = self.truth.actual_positions(q, self.direction)[0]
        q_act = q_act + self.settings.driver_accuracy_um * z_driver
        q_act = q_act + self.model.friction_std_per_um * np.abs(dq) * z_friction
        p, _ = self.truth.pose(q_act[None, :])
        self._p = p[0]
        self._q_cmd = q
        self.time_s += self.settings.move_time_s
        self.moves += 1

    def read(self) -> float:
        """Gauge reading of the current pose now (one gauge-noise draw), µm."""
        if self._closed:
            raise BackendError("the backend is closed")
        mean = self.truth.reading(self._p[None, :], self.time_s)[0]
        return float(mean + self.settings.gauge_noise_std_um * self._rng_gauge.standard_normal())

    def move(self, u: np.ndarray) -> Measurement:
        """Execute one move (see the module docstring) and read the gauge once."""
        u, q = self.command_for(u)
        self.settle(q)
        t = self.read()
        self._set_state(t, q)
        return Measurement(t_um=t, q_um=q, u=u, time_s=self.time_s)

    # ---- oracle --------------------------------------------------------------------
    def _oracle(self, s: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, ExtendedPrediction]:
        """Δq and the noise-free prediction of the next move from state s (a held actuator keeps
        the stage's current backlash direction), at the time it would settle."""
        s = np.asarray(s, dtype=float).reshape(-1)
        q = np.atleast_2d(np.asarray(u, dtype=float)) @ self.K.T
        pred = self.truth.predict_q(q, q_prev=s[1:], last_direction=self.direction,
                                    time_s=self.time_s + self.settings.move_time_s)
        return q - s[1:], pred

    def true_mean(self, s: np.ndarray, u: np.ndarray) -> np.ndarray | float:
        """Noise-free expected reading of the next move from state s.

        Parameters
        ----------
        s : ndarray, shape (1 + n_q,)
            State [t_prev, q_prev] (only q_prev matters; a Δq_i = 0 keeps the stage's
            current backlash direction).
        u : ndarray, shape (n_p,) or (m, n_p)

        Returns
        -------
        float or ndarray (m,)
            At the time the next move would settle (clock + move_time_s).
        """
        _, pred = self._oracle(s, u)
        return float(pred.t[0]) if np.ndim(u) == 1 else pred.t

    def true_var(self, s: np.ndarray, u: np.ndarray) -> np.ndarray | float:
        """Variance of the next reading from state s (µm²), shape () or (m,).

        Driver accuracy and friction (std_i |Δq_i|) propagated linearly through the contact
        equilibrium (``truth.variance``), plus the gauge noise.
        """
        dq, pred = self._oracle(s, u)
        out = self.truth.variance(pred, dq, actuator_std_um=self.settings.driver_accuracy_um,
                                  gauge_std_um=self.settings.gauge_noise_std_um)
        return float(out[0]) if np.ndim(u) == 1 else out
