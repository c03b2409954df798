"""The simulated stage: the stage model (:class:`~microctl.models.extended.ExtendedForwardModel`) with noise.

One model object is the truth of the moves *and* of the oracle (``true_mean``, ``true_var``),
and the model the diagnosis fits (with candidate causes instead of the planted ones). One
move, in order:

1. q = K u (eq. 12, CAD geometry), refused if out of range (nothing changes);
2. backlash direction per actuator by the one rule (``model.next_direction``: the sign of
   Δq_i, kept when the actuator is held still; the zero state counts as approached "up");
3. hysteresis play states (the loop's memory) step to q (``model.next_play``);
   actual positions q_act = model.actual_positions(q, direction, play) + e_driver + e_friction with
   e_driver ~ N(0, driver_accuracy²) per actuator and e_friction,i ~ N(0, (std_i |Δq_i|)²);
4. contact equilibrium p (``model.pose``), the clock advances by move_time_s;
5. reading = model.reading(p, time) + N(0, gauge_noise²) (the sensor of the effects).

The truth of a move (``true_mean``, ``true_var``: what the oracle optimises and every "expected under
the truth" figure is computed from) is exact where the first-order propagation is exact and
Monte Carlo elsewhere (:meth:`SimulatedStage.true_moments`).

Actuator noise and gauge noise come from two independent streams spawned from the seed
(``SeedSequence(seed).spawn(2)``): per move exactly 2·n_q actuator normals (driver first,
then friction) and one gauge normal per reading are drawn, so the emulator, which reads the
gauge through the serial dialect, reproduces the same data.
"""

from __future__ import annotations

import itertools

import numpy as np

from microctl.backends.base import StageBackend, register_backend
from microctl.errors import BackendError
from microctl.measurement.log import Measurement
from microctl.models.extended import ExtendedForwardModel, ExtendedPrediction
from microctl.stage.config import StageConfig
from microctl.stage.physics import ZERO_STATE_DIRECTION, ball_heights, tool_displacement

#: Monte Carlo draws of the truth where it is not exact (antithetic pairs), and their seed (fixed: the
#: truth of a pose is the same number every time it is asked, so the oracle's search sees a smooth
#: function; common random numbers across poses).
TRUTH_DRAWS, TRUTH_SEED = 1024, 20_240_611

#: The first-order truth is exact when no ball can change contact: every ball's compression (or
#: gap) at the noise-free pose exceeds this many standard deviations of its change under the
#: actuator noise, and the gauge is linear.
EXACT_MARGIN_SD = 6.0

#: Poses per Monte Carlo batch (memory: batch x TRUTH_DRAWS equilibrium solves).
_MC_BATCH = 64


def enumerated_equilibrium(model, h: np.ndarray) -> np.ndarray:
    """Contact equilibrium poses for ball heights h (m, n_c), by enumerating the contact sets.

    The elastic energy is strictly convex (the flexure stiffness is positive), so its minimiser is
    the one pose p_S = H_S^-1 (f_preload + k_c A_S^T h_S) of a contact set S whose balls in S are
    compressed and whose others are not (the KKT conditions of the piecewise quadratic). With 2^n_c
    sets of precomputed H_S^-1 this is a few matrix products per set: the Monte Carlo truth's
    many solves cost little (the same answer as :func:`microctl.stage.physics.solve_equilibrium`,
    which iterates; tested). Among sets consistent within round-off, the first in enumeration
    order (larger sets first) is taken.

    Returns
    -------
    ndarray, shape (m, n_p)
    """
    A, kc = model.A, model.k_c
    n_c = A.shape[0]
    h = np.atleast_2d(np.asarray(h, dtype=float))
    p_out = np.full((h.shape[0], A.shape[1]), np.nan)
    todo = np.arange(h.shape[0])
    tol = 1e-9 * (1.0 + np.max(np.abs(h), axis=1))
    for size in range(n_c, -1, -1):
        for S in itertools.combinations(range(n_c), size):
            mask = np.zeros(n_c, dtype=bool)
            mask[list(S)] = True
            AS = A[mask]
            Hinv = np.linalg.inv(kc * AS.T @ AS + np.diag(model.k_h))
            hs = h[todo]
            p = (model.f_preload + kc * hs[:, mask] @ AS) @ Hinv.T
            c = hs - p @ A.T
            tl = tol[todo, None]
            ok = np.all(np.where(mask, c >= -tl, c <= tl), axis=1)
            p_out[todo[ok]] = p[ok]
            todo = todo[~ok]
            if todo.size == 0:
                return p_out
    return p_out


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
    play : ndarray, shape (n_q, N_PLAY) or None
        Play states of the hysteresis (:mod:`microctl.stage.hysteresis`; None without it).
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
        self.play = self.truth.zero_play()
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
        play = self.truth.next_play(q, self.play)
        q_act = self.truth.actual_positions(q, self.direction, play)[0]
        self.play = None if play is None else play[0]
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
        the stage's current backlash direction; the hysteresis starts from its current play
        states), at the time it would settle."""
        s = np.asarray(s, dtype=float).reshape(-1)
        q = np.atleast_2d(np.asarray(u, dtype=float)) @ self.K.T
        pred = self.truth.predict_q(q, q_prev=s[1:], last_direction=self.direction, last_play=self.play,
                                    time_s=self.time_s + self.settings.move_time_s)
        return q - s[1:], pred

    def true_moments(self, s: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Mean and variance (µm, µm²) of the next reading from state s, for each row of u.

        Exact where no ball can change contact: the actuator noise (driver accuracy, stick-slip
        std_i |Δq_i|) enters the ball heights linearly, and while no ball can change contact
        (:data:`EXACT_MARGIN_SD`) the equilibrium is linear in them, so the tool displacement is
        Gaussian; a linear gauge reads it with the noise-free mean and the propagated variance
        (``truth.variance``), a quadratic one with the exact moments of a quadratic of a Gaussian;
        plus the gauge noise. Elsewhere (a ball that may lift off or touch down) Monte Carlo over
        :data:`TRUTH_DRAWS` antithetic draws of the same noise through the contact equilibrium
        and the gauge.

        Parameters
        ----------
        s : ndarray, shape (1 + n_q,)
        u : ndarray, shape (n_p,) or (m, n_p)

        Returns
        -------
        mean, var : ndarray, shape (m,)
        """
        dq, pred = self._oracle(s, u)
        mean = np.array(pred.t, dtype=float)
        var = self.truth.variance(pred, dq, actuator_std_um=self.settings.driver_accuracy_um,
                                  gauge_std_um=self.settings.gauge_noise_std_um)
        # the noise-free actual positions of the moves (backlash direction and play as in _oracle)
        q_act = self.truth.actual_positions(pred.q, self.truth.next_direction(dq, self.direction),
                                            self.truth.next_play(pred.q, self.play))
        exact = self._first_order_exact(pred, dq, q_act)
        sensor = self.model.sensor
        if not sensor.is_linear:
            # reading = scale d + quad d^2 of a Gaussian d ~ N(d0, sd^2) (linear equilibrium): exact
            # moments E = forward(d0) + quad sd^2, Var = forward'(d0)^2 sd^2 + 2 quad^2 sd^4
            d0 = tool_displacement(self.model, pred.p)
            slope = sensor.derivative(d0)
            exact &= np.abs(slope) > 1e-6
            sd2 = (var - self.settings.gauge_noise_std_um**2) / np.where(exact, slope * slope, 1.0)
            q2 = sensor.quad_per_um
            mean = np.where(exact, mean + q2 * sd2, mean)
            var = np.where(exact, slope * slope * sd2 + 2.0 * q2 * q2 * sd2 * sd2
                           + self.settings.gauge_noise_std_um**2, var)
        mc = ~exact
        if mc.any():
            mean[mc], var[mc] = self._monte_carlo(q_act[mc], dq[mc], pred.sensitivity[mc])
        return mean, var

    def _actuator_std(self, dq: np.ndarray) -> np.ndarray:
        """Std of each actuator's actual position for steps dq (m, n_q), µm."""
        return np.sqrt(self.settings.driver_accuracy_um**2 + (self.model.friction_std_per_um * np.abs(dq)) ** 2)

    def _first_order_exact(self, pred: ExtendedPrediction, dq: np.ndarray, q_act: np.ndarray) -> np.ndarray:
        """Per move: can no ball change contact under the actuator noise?"""
        m = self.model
        A, kc = m.A, m.k_c
        S = pred.active.astype(float)
        H = np.einsum("mi,ij,ik->mjk", S, A, A) * kc
        idx = np.arange(m.n_p)
        H[:, idx, idx] += m.k_h
        # compression c = h - A p; dc/dh = I - A H^-1 kc A_S^T  (per move), dh/dq = nd gain
        Hinv_At = np.linalg.solve(H, np.broadcast_to(A.T, (len(pred.t),) + A.T.shape))  # (m, n_p, n_c)
        dc_dh = np.eye(m.n_c)[None] - kc * np.einsum("ij,mjk->mik", A, Hinv_At) * S[:, None, :]
        J = dc_dh * (m.nd * m.gain)[None, None, :]
        sd_c = np.sqrt(np.einsum("mij,mj->mi", J * J, self._actuator_std(dq) ** 2))
        compression = ball_heights(m, q_act) - pred.p @ A.T  # negative: a gap
        return np.all(np.abs(compression) > EXACT_MARGIN_SD * sd_c, axis=1)

    def _monte_carlo(self, q_act: np.ndarray, dq: np.ndarray, sensitivity: np.ndarray | None = None
                     ) -> tuple[np.ndarray, np.ndarray]:
        """Monte Carlo mean and variance of the readings of moves with noise-free actual positions
        q_act (m, n_q) and steps dq (m, n_q).

        With ``sensitivity`` (m, n_q), the first-order reading change L of the same draws is a
        control variate: the part of the sample variance that L explains, beta^2 var(L) with beta
        the regression coefficient of the reading on L, is taken at L's exact variance
        (sum_i J_i^2 var q_i) instead of its sample variance, so the sampling error is that of the
        nonlinear part only where a ball rarely changes contact, and the plain sample variance
        where the reading stops following L (a ball that lifts off). Never negative. The antithetic
        pairs make the control variate's sample mean exactly 0."""
        n_q = q_act.shape[1]
        z = np.random.default_rng(TRUTH_SEED).standard_normal((TRUTH_DRAWS // 2, 2, n_q))
        z = np.concatenate([z, -z])  # antithetic pairs
        t_read = self.time_s + self.settings.move_time_s
        means, vars_ = np.empty(len(q_act)), np.empty(len(q_act))
        for b in range(0, len(q_act), _MC_BATCH):
            sl = slice(b, b + _MC_BATCH)
            noise = (self.settings.driver_accuracy_um * z[None, :, 0, :]
                     + (self.model.friction_std_per_um * np.abs(dq[sl]))[:, None, :] * z[None, :, 1, :])
            qa = (q_act[sl][:, None, :] + noise).reshape(-1, n_q)
            p = enumerated_equilibrium(self.model, ball_heights(self.model, qa))
            r = self.truth.reading(p, t_read).reshape(-1, TRUTH_DRAWS)
            means[sl] = r.mean(axis=1)
            vars_[sl] = r.var(axis=1, ddof=1)
            if sensitivity is not None:
                J = sensitivity[sl]
                lin = np.einsum("mkq,mq->mk", noise, J)
                exact_lin = np.sum(J * J * self._actuator_std(dq[sl]) ** 2, axis=1)
                # regression-adjusted control variate: beta = cov(r, L) / var(L), so where a ball
                # lifts off and the reading stops following L (beta -> 0) the plain sample variance
                # remains; var_r - beta^2 var_L >= 0 (Cauchy-Schwarz), so the estimate never
                # goes negative
                var_l = lin.var(axis=1, ddof=1)
                cov = np.einsum("mk,mk->m", r - r.mean(axis=1, keepdims=True), lin) / (TRUTH_DRAWS - 1)
                beta = np.where(var_l > 0, cov / np.where(var_l > 0, var_l, 1.0), 0.0)
                vars_[sl] += beta * beta * (exact_lin - var_l)
            vars_[sl] += self.settings.gauge_noise_std_um**2
        return means, vars_

    def true_mean(self, s: np.ndarray, u: np.ndarray) -> np.ndarray | float:
        """Expected reading of the next move from state s (:meth:`true_moments`).

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
        mean, _ = self.true_moments(s, u)
        return float(mean[0]) if np.ndim(u) == 1 else mean

    def true_var(self, s: np.ndarray, u: np.ndarray) -> np.ndarray | float:
        """Variance of the next reading from state s (µm²), shape () or (m,) (:meth:`true_moments`)."""
        _, var = self.true_moments(s, u)
        return float(var[0]) if np.ndim(u) == 1 else var
