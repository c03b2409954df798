"""Rig families: simulated piezo stages whose scatter has a chosen physical structure (issue 18).

Written from piezo-stage physics, independently of microctl's noise model (microctl/gp/,
microctl/models/training.py were not consulted for the shapes). Each family is a seeded random
draw of a rig plus a noise structure.

The rig (every family)
----------------------
Table I geometry (configs/stage/sim_paper.yaml: four PZTs under steel balls at 15 mm, a gauge
50 mm out at 145°), ranges 0-32 µm; every actuator's gain within ±5 %; gauge noise
0.03-0.08 µm; preload 300-800 N, redrawn (and counted) until every ball is loaded at every
vertex of the workspace polytope. No backlash, no gap, a linear gauge.

How the noise enters
--------------------
One move from the commanded state q_prev to q = K u (eq. 12):

1. the actual actuator positions are the noise-free ones (gains, through the stage model)
   plus a zero-mean Gaussian displacement e_i ~ N(0, sigma_i²) per actuator, where sigma_i
   is the family's function of (q_prev, q, dq, direction history, ball forces);
2. the platform settles in the contact equilibrium of those actual positions (the stage
   model's contact physics: flexure + preloaded ball contacts);
3. the gauge reads the tool point plus N(0, gauge²).

So the scatter reaches the reading through the stage's equilibrium exactly as a real
actuator error does (it is larger for the actuators the tool is more sensitive to, and it
depends on which balls carry load).

Why wrap :class:`~microctl.backends.simulated.SimulatedStage`
-------------------------------------------------------------
The deterministic part of the stage (gains, contact equilibrium, gauge transfer) is the stage,
not a noise model, so :class:`FamilyStage` takes it from a ``SimulatedStage`` configured with
no actuator noise at all (no friction, driver accuracy 0) and only uses its ``truth.pose`` /
``truth.reading`` / ``truth.model`` arrays; every random term (actuator scatter and gauge
noise) is drawn here, from two streams spawned from the seed. ``tests/independent_stage.py``
would be an independent copy of the same physics, but it lives in tests/ and has no backend
interface; the point of the families is an independent *noise* truth, which this gives.

The truth
---------
``true_mean(s, u)``: the reading of the noise-free equilibrium. ``true_var(s, u)``: the
variance of the reading. While every ball stays in contact the equilibrium is *affine* in the
actual positions (a fixed contact set gives a linear system), so with zero-mean independent
actuator errors the mean is exactly the noise-free reading and the variance is exactly
``sum_i S_i² sigma_i² + gauge²`` with S_i the (constant) slope of the reading in actuator i,
found by a finite difference of the full simulator (exact up to round-off for an affine map).
This is exact, not a linearisation, as long as no draw changes the contact set; the minimum
ball compression is checked against 6 sigma of the ball-height scatter and, where it is not
met, the moments come from Monte Carlo of the simulator itself (``mc_moments``). The test
``tests/test_rig_families.py`` checks the exact moments against Monte Carlo of :meth:`FamilyStage.move`.

Families (name: physics; parameters and ranges; units µm unless said)
---------------------------------------------------------------------
Every family except ``clean`` also has a driver scatter of 0.01 µm per actuator per move
(amplifier/DAC resolution), as today's bench rigs.

``clean``
    Gauge noise only (driver scatter 0 too). For the "no feature is found, never worse than
    the AFM" bar.
``stick_slip`` (today's structure)
    The ball/stack interface sticks and slips while the actuator moves: the slip is a random
    fraction of the distance travelled. sigma_i = c_i |dq_i| on 1 or 2 random actuators,
    c_i ~ U(0.02, 0.08) per µm.
``stroke_patch``
    A rough patch of one actuator's stroke (a damaged stretch of the flexure guide / a pitted
    spot of the ball seat or a cracked layer of the stack that engages over part of the
    travel): the scatter depends on where the actuator *ends*, not how far it moved.
    sigma_i(q_i) = a * 0.5 [tanh((q_i - lo)/e) - tanh((q_i - hi)/e)] on one random actuator;
    patch width hi - lo ~ U(4, 10), lo ~ U(2, 30 - width), edge e = 0.5, peak a ~ U(0.1, 0.3).
``light_ball``
    A lightly loaded ball seats less repeatably: Hertz contact stiffness falls as F^(1/3) and
    the ball's micro-slip under the stage's tangential disturbances is bounded by mu F, so the
    seating scatter of ball i grows as its contact force F_i (from the noise-free equilibrium
    at the commanded pose) falls. On every ball: sigma_i = min(s0 (F_ref / max(F_i, 1 N))^gamma,
    0.5) with F_ref = preload / 4, s0 ~ U(0.01, 0.03), gamma ~ U(1, 2).
``settling``
    Piezo creep: after a step the stack keeps drifting (logarithmically) and the reading is
    taken a fixed time after the step; the residual creep's random part grows with the step
    but saturates (domain-wall pinning bounds it). sigma_i = a_i (1 - exp(-|dq_i| / d0_i)) on
    1 or 2 random actuators, a_i ~ U(0.1, 0.3), d0_i ~ U(1, 6).
``reversal``
    Hysteresis: where the actuator turns round (its step has the opposite sign to its previous
    step), the turning point of the minor loop is not repeatable; moves that continue in the
    same direction are repeatable. sigma_i = r_i (1 - exp(-|dq_i| / 0.5)) if sign(dq_i) is
    opposite to the actuator's last direction of motion (a held actuator keeps its direction;
    the zero state counts as approached "up"), else 0; on 1 or 2 random actuators,
    r_i ~ U(0.1, 0.3).
``stiction``
    Static friction with a breakaway threshold: small steps are taken up elastically by the
    ball contact (repeatable); once the step exceeds the breakaway travel the interface slips
    by a random amount of fixed size. sigma_i = s_i / (1 + exp(-(|dq_i| - d_i) / 0.25)) on 1 or
    2 random actuators, s_i ~ U(0.08, 0.25), breakaway d_i ~ U(1, 5).
``extension``
    Drive-voltage noise: amplifier ripple and dielectric noise are proportional to the drive
    voltage, i.e. to the actuator's absolute extension. sigma_i = v_i (q_i / 32)^p_i on 1 or 2
    random actuators, v_i ~ U(0.1, 0.3), p_i ~ U(1, 3).
``mix``
    ``stick_slip`` plus one of ``stroke_patch, light_ball, settling, reversal, stiction,
    extension`` (drawn per rig), independent (variances add).

Usage: ``make_family_rig(family, seed)`` -> :class:`FamilyRig`; ``rig.stage(seed)`` ->
:class:`FamilyStage` (a ``StageBackend``: ``move``, ``read``, ``true_mean``, ``true_var``).
"""
