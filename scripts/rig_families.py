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
This is exact, not a linearisation, as long as no draw changes the contact set; every ball's
compression is checked against 4.5 stds of its own scatter (the compression is affine in the
actuator errors too: same finite difference) and, where it is not
met, the moments come from Monte Carlo (common random numbers, so
the oracle's Newton projection sees a smooth function) of the simulator itself (``mc_moments``). The test
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
    0.5) with F_ref = preload / 4, s0 ~ U(0.01, 0.03), gamma ~ U(1, 2). One random ball is the
    light one: its seat is worn (it sits low by a gap, the stage's ``contact_loss``) so that at
    the zero state it carries a fraction phi ~ U(0.15, 0.4) of the load it would carry without
    the gap (the gap is solved for phi; the rig is still redrawn unless every ball stays loaded
    over the workspace). Its load then moves with the pose through the platform's twist mode.
    *Revised before any model was run on it*: the first draft (commit 42ef099) had no worn
    seat; measured on the truth alone, the four loads then vary by only about ±10 % over the
    workspace (the CAD kinematics keep the twist mode at zero and only the ±5 % gains move it),
    so the scatter stayed under 0.04 µm, below the gauge: a clean rig, not a light ball.
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
    r_i ~ U(0.1, 0.3). A step of at most ``HELD_UM`` (1e-6 µm, a picometre) holds the actuator:
    commands computed in floating point differ from the previous ones by round-off where an
    actuator is meant to stay, and a hysteresis loop does not turn round on a picometre (until
    2026-11-28 any nonzero step did, so a held actuator's round-off of -1e-12 µm made the next
    long step up a full reversal).
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

Two more, written down on 2026-11-27 before any model was run on them (their scatter enters
at the reading, after the equilibrium, not through the actuators; neither is drawn by ``mix``,
whose rigs stay as they were):

``gauge_tilt``
    A capacitance gauge over a tilted target: the gap varies across the probe's face, so the
    gauge's noise (its electronics referred to the gap) and its pick-up of the platform's
    lateral vibration grow with the target's tilt. Every reading at a pose gets, besides the
    gauge noise, an independent N(0, sigma_r²) with sigma_r = a (theta / theta_max)^k, theta =
    sqrt(rx² + ry²) the platform's tilt (mrad) and theta_max the largest tilt at the vertices
    of the workspace polytope; a ~ U(0.1, 0.3), k ~ U(1, 2).
``hinge_slip``
    A flexure hinge with a dry-friction contact (a leaf clamped between plates that slips in
    its clamp): the platform's rotation about each tilt axis slips by a random fraction of the
    rotation the move makes there, and the slip stays (a re-read sees it). The actual rx, ry
    after a move are the equilibrium's plus N(0, (c_x |drx|)²) and N(0, (c_y |dry|)²), drx and
    dry the change of the noise-free tilt over the move; c_x, c_y ~ U(0.02, 0.06). So the
    reading's std is sqrt((c_x L_x drx)² + (c_y L_y dry)²), L the reading's sensitivity to
    rx, ry (the tool's lever arms): a step that tilts the platform is noisy whichever
    actuators make it, a pure lift is not.

Usage: ``make_family_rig(family, seed)`` -> :class:`FamilyRig`; ``rig.stage(seed)`` ->
:class:`FamilyStage` (a ``StageBackend``: ``move``, ``read``, ``true_mean``, ``true_var``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from microctl.backends.base import StageBackend
from microctl.backends.simulated import SimulatedStage
from microctl.control.controller import RedundantSet
from microctl.errors import BackendError
from microctl.measurement.log import Measurement
from microctl.models.afm import AnalyticForwardModel
from microctl.stage.config import StageConfig, parse_stage_config

CONTACTS_MM = ([15, 0, 5], [0, -15, 5], [-15, 0, 5], [0, 15, 5])
TOOL_MM = [-40.957602214449594, 28.678821817552297, 10.0]
STROKE_UM = 32.0
DRIVER_STD_UM = 0.01
#: A commanded step of at most this (µm) holds the actuator: it keeps its direction of motion and
#: does not turn a hysteresis loop round (floating-point round-off of a held command).
HELD_UM = 1e-6
#: The contact set is trusted fixed when every ball's compression exceeds this many stds of
#: its height scatter (else the moments come from Monte Carlo).
CONTACT_MARGIN_SIGMAS = 4.5
_FD_UM = 1e-3
OTHERS = ("stroke_patch", "light_ball", "settling", "reversal", "stiction", "extension")
#: Families whose scatter enters at the reading (after the equilibrium); not drawn by ``mix``.
READING = ("gauge_tilt", "hinge_slip")
FAMILIES = ("clean", "stick_slip", *OTHERS, "mix", *READING)


# --------------------------------------------------------------------------- noise structures


def _some(r: np.random.Generator, n: int = 4) -> list[int]:
    """1 or 2 distinct random actuators (0-based, sorted)."""
    return sorted(int(i) for i in r.choice(n, int(r.integers(1, 3)), replace=False))


def _draw_term(kind: str, r: np.random.Generator) -> dict:
    """Parameters of one noise term of ``kind`` (module docstring for the ranges)."""
    if kind == "stick_slip":
        acts = _some(r)
        return {"kind": kind, "act": acts, "c": [float(r.uniform(0.02, 0.08)) for _ in acts]}
    if kind == "stroke_patch":
        width = float(r.uniform(4.0, 10.0))
        lo = float(r.uniform(2.0, 30.0 - width))
        return {"kind": kind, "act": [int(r.integers(4))], "lo": lo, "hi": lo + width, "edge": 0.5,
                "a": float(r.uniform(0.1, 0.3))}
    if kind == "light_ball":
        return {"kind": kind, "act": [0, 1, 2, 3], "s0": float(r.uniform(0.01, 0.03)),
                "gamma": float(r.uniform(1.0, 2.0)), "cap": 0.5, "ball": int(r.integers(4)),
                "fraction": float(r.uniform(0.15, 0.4))}
    if kind == "settling":
        acts = _some(r)
        return {"kind": kind, "act": acts, "a": [float(r.uniform(0.1, 0.3)) for _ in acts],
                "d0": [float(r.uniform(1.0, 6.0)) for _ in acts]}
    if kind == "reversal":
        acts = _some(r)
        return {"kind": kind, "act": acts, "r": [float(r.uniform(0.1, 0.3)) for _ in acts], "scale": 0.5}
    if kind == "stiction":
        acts = _some(r)
        return {"kind": kind, "act": acts, "s": [float(r.uniform(0.08, 0.25)) for _ in acts],
                "d": [float(r.uniform(1.0, 5.0)) for _ in acts], "width": 0.25}
    if kind == "extension":
        acts = _some(r)
        return {"kind": kind, "act": acts, "v": [float(r.uniform(0.1, 0.3)) for _ in acts],
                "p": [float(r.uniform(1.0, 3.0)) for _ in acts]}
    if kind == "gauge_tilt":  # theta_max is set from the rig's workspace (make_family_rig)
        return {"kind": kind, "act": [], "a": float(r.uniform(0.1, 0.3)), "k": float(r.uniform(1.0, 2.0))}
    if kind == "hinge_slip":
        return {"kind": kind, "act": [], "c": [float(r.uniform(0.02, 0.06)) for _ in range(2)]}
    raise ValueError(f"unknown noise term {kind!r}")


def _tilt_var(terms: list[dict], p: np.ndarray) -> np.ndarray:
    """Variance (µm²) the ``gauge_tilt`` terms add to a reading at the poses p (m, 3: z, rx, ry), shape (m,)."""
    out = np.zeros(p.shape[0])
    for t in terms:
        if t["kind"] == "gauge_tilt":
            theta = np.hypot(p[:, 1], p[:, 2])
            out += (t["a"] * (theta / t["theta_max"]) ** t["k"]) ** 2
    return out


def _slip_sd(terms: list[dict], p_prev: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Std (mrad) of the ``hinge_slip`` terms' slip of rx and ry over moves p_prev -> p, shape (m, 2)."""
    out = np.zeros((p.shape[0], 2))
    for t in terms:
        if t["kind"] == "hinge_slip":
            out = np.sqrt(out ** 2 + (np.asarray(t["c"])[None, :] * np.abs(p[:, 1:3] - p_prev[:, 1:3])) ** 2)
    return out


def _term_std(t: dict, q_prev: np.ndarray, q: np.ndarray, reverses: np.ndarray, force_n: np.ndarray,
              f_ref: float) -> np.ndarray:
    """Actuator-position scatter of one term, shape (m, n_q).

    Parameters
    ----------
    q_prev, q : ndarray, shape (m, n_q)
        Commands before and after the move.
    reverses : ndarray of bool, shape (m, n_q)
        The move turns the actuator round.
    force_n : ndarray, shape (m, n_q)
        Ball contact forces at the noise-free equilibrium of the move, N.
    """
    out = np.zeros_like(q)
    dq = np.abs(q - q_prev)
    k = t["kind"]
    for j, i in enumerate(t["act"]):
        if k == "stick_slip":
            out[:, i] = t["c"][j] * dq[:, i]
        elif k == "stroke_patch":
            out[:, i] = t["a"] * 0.5 * (np.tanh((q[:, i] - t["lo"]) / t["edge"]) - np.tanh((q[:, i] - t["hi"]) / t["edge"]))
        elif k == "light_ball":
            out[:, i] = np.minimum(t["s0"] * (f_ref / np.maximum(force_n[:, i], 1.0)) ** t["gamma"], t["cap"])
        elif k == "settling":
            out[:, i] = t["a"][j] * (1.0 - np.exp(-dq[:, i] / t["d0"][j]))
        elif k == "reversal":
            out[:, i] = np.where(reverses[:, i], t["r"][j] * (1.0 - np.exp(-dq[:, i] / t["scale"])), 0.0)
        elif k == "stiction":
            out[:, i] = t["s"][j] / (1.0 + np.exp(-(dq[:, i] - t["d"][j]) / t["width"]))
        elif k == "extension":
            out[:, i] = t["v"][j] * np.clip(q[:, i] / STROKE_UM, 0.0, None) ** t["p"][j]
    return out


def draw_terms(family: str, r: np.random.Generator) -> list[dict]:
    """The noise terms of one rig of ``family``."""
    if family == "clean":
        return []
    if family == "mix":
        return [_draw_term("stick_slip", r), _draw_term(OTHERS[int(r.integers(len(OTHERS)))], r)]
    if family not in FAMILIES:
        raise ValueError(f"unknown family {family!r}; choose from {', '.join(FAMILIES)}")
    return [_draw_term(family, r)]


# --------------------------------------------------------------------------- rigs


def _rig_dict(family: str, seed: int, draw: int) -> tuple[dict, np.random.Generator]:
    r = np.random.default_rng([seed, 7919, draw, FAMILIES.index(family)])
    return {
        "stage": {
            "name": f"{family}-rig-{seed}", "dof": ["z", "rx", "ry"],
            "tool": {"name": "t", "point_mm": TOOL_MM, "direction": [0, 0, 1]},
            "actuators": [{"name": f"q{i + 1}", "contact_mm": CONTACTS_MM[i], "range_um": [0, 32],
                           "limit_um": [0, 38]} for i in range(4)],
            "physics": {"contact_stiffness_n_per_um": 20.0, "preload_n": float(r.uniform(300.0, 800.0)),
                        "flexure_stiffness": [0.01, 5.0, 5.0]},
        },
        "backend": {"kind": "simulated", "simulated": {
            "seed": int(seed), "gauge_noise_std_um": float(r.uniform(0.03, 0.08)), "driver_accuracy_um": 0.0,
            "move_time_s": 1.0,
            "effects": {
                "actuator_gain": [{"actuator": i + 1, "gain": float(1.0 + r.uniform(-0.05, 0.05))} for i in range(4)],
            }}},
    }, r


@dataclass(frozen=True)
class FamilyRig:
    """One drawn rig: its stage configuration (no actuator noise) and its noise terms."""

    family: str
    seed: int
    config: StageConfig
    terms: list = field(default_factory=list)
    driver_std_um: float = DRIVER_STD_UM
    redraws: int = 0

    def stage(self, seed: int | None = None) -> "FamilyStage":
        """A fresh stage of this rig (noise streams from ``seed``, default the rig's)."""
        return FamilyStage(self, self.seed if seed is None else seed)

    def true_sources(self) -> tuple[str, ...]:
        """The noise-source quantities of the package's dictionary (microctl.models.noise_dictionary)
        that carry this rig's scatter: what the ``told`` reference of scripts/bench_rigs.py names.

        Per term: the step ``dq<i>`` of each actuator of a stick_slip, settling, reversal or stiction
        term; the position ``q<i>`` of a stroke_patch or extension term; the load ``f<i>`` of the light
        ball (the other balls stay loaded: their scatter is nearly the floor); the pose's rotations
        ``rx, ry`` for gauge_tilt; the rotation steps ``drx, dry`` for hinge_slip.
        """
        out: list[str] = []
        for t in self.terms:
            k = t["kind"]
            if k in ("stick_slip", "settling", "reversal", "stiction"):
                out += [f"dq{i + 1}" for i in t["act"]]
            elif k in ("stroke_patch", "extension"):
                out += [f"q{i + 1}" for i in t["act"]]
            elif k == "light_ball":
                out.append(f"f{t['ball'] + 1}")
            elif k == "gauge_tilt":
                out += ["rx", "ry"]
            elif k == "hinge_slip":
                out += ["drx", "dry"]
            else:
                raise ValueError(f"no dictionary quantity for noise term {k!r}")
        return tuple(dict.fromkeys(out))

    def describe(self) -> dict:
        """What was drawn (JSON-able)."""
        sim = self.config.backend.simulated
        return {"family": self.family, "seed": self.seed, "redraws": self.redraws,
                "preload_n": self.config.stage.physics.preload_n, "gauge_um": sim.gauge_noise_std_um,
                "gains": [g.gain for g in sim.effects.actuator_gain], "driver_um": self.driver_std_um,
                "terms": self.terms}


def _all_balls_loaded(config: StageConfig) -> bool:
    """Every ball in contact at every vertex of the workspace polytope (the physics is convex in q)."""
    afm = AnalyticForwardModel(config.stage)
    truth = SimulatedStage(config).truth
    q = RedundantSet(afm).vertices @ afm.K.T
    _, active = truth.pose(truth.actual_positions(q, np.ones_like(q)))
    return bool(np.all(active))


def _zero_state_force(d: dict, ball: int, gap_um: float) -> float:
    """Contact force (N) of ``ball`` at the zero state of the rig ``d`` with that ball ``gap_um`` low."""
    d = {**d, "backend": {**d["backend"], "simulated": {**d["backend"]["simulated"], "effects": {
        **d["backend"]["simulated"]["effects"], "contact_loss": [{"actuator": ball + 1, "gap_um": gap_um}]}}}}
    model = SimulatedStage(parse_stage_config(d, "<light ball>")).truth.model
    h = model.nd * model.gain * model.q_zero - model.gap_um
    return float(model.k_c * max(h[ball] - model.A[ball] @ model.p_zero, 0.0))


def _light_gap(d: dict, ball: int, fraction: float) -> float:
    """The gap (µm) that leaves ``ball`` a ``fraction`` of its gap-free zero-state load (the
    load is affine in the gap while the ball stays in contact)."""
    f0, f1 = _zero_state_force(d, ball, 0.0), _zero_state_force(d, ball, 1.0)
    return float((1.0 - fraction) * f0 / (f0 - f1))


def _theta_max(config: StageConfig) -> float:
    """The largest platform tilt (mrad) at the vertices of the workspace polytope (noise-free)."""
    afm = AnalyticForwardModel(config.stage)
    truth = SimulatedStage(config).truth
    q = RedundantSet(afm).vertices @ afm.K.T
    p, _ = truth.pose(truth.actual_positions(q, np.ones_like(q)))
    return float(np.max(np.hypot(p[:, 1], p[:, 2])))


def make_family_rig(family: str, seed: int) -> FamilyRig:
    """The rig of ``family`` and ``seed`` (redrawn until every ball is loaded over the workspace)."""
    if family not in FAMILIES:
        raise ValueError(f"unknown family {family!r}; choose from {', '.join(FAMILIES)}")
    for draw in range(20):
        d, r = _rig_dict(family, seed, draw)
        terms = draw_terms(family, r)
        light = [t for t in terms if t["kind"] == "light_ball"]
        if light:
            t = light[0]
            t["gap_um"] = _light_gap(d, t["ball"], t["fraction"])
            d["backend"]["simulated"]["effects"]["contact_loss"] = [{"actuator": t["ball"] + 1, "gap_um": t["gap_um"]}]
        cfg = parse_stage_config(d, f"<{family} rig {seed}>")
        for t in terms:
            if t["kind"] == "gauge_tilt":
                t["theta_max"] = _theta_max(cfg)
        if _all_balls_loaded(cfg):
            return FamilyRig(family, seed, cfg, terms, 0.0 if family == "clean" else DRIVER_STD_UM, draw)
    raise RuntimeError(f"{family} rig {seed}: no well-preloaded draw in 20 tries")


# --------------------------------------------------------------------------- the stage


class FamilyStage(StageBackend):
    """A simulated stage of a :class:`FamilyRig` (module docstring: how the noise enters).

    Parameters
    ----------
    rig : FamilyRig
    seed : int
        Seeds the actuator-scatter and gauge streams (``SeedSequence(seed).spawn(2)``).

    Attributes
    ----------
    truth : ExtendedForwardModel
        The deterministic stage (a noise-free ``SimulatedStage``'s ``truth``).
    direction : ndarray, shape (n_q,)
        Last direction of motion per actuator (+1 at the zero state).
    """

    def __init__(self, rig: FamilyRig, seed: int):
        super().__init__(rig.config)
        self.rig = rig
        self._inner = SimulatedStage(rig.config, seed=seed)
        self.truth = self._inner.truth
        self.model = self.truth.model
        self.gauge_std_um = rig.config.backend.simulated.gauge_noise_std_um
        act_seq, gauge_seq = np.random.SeedSequence(seed).spawn(2)
        self._rng_act = np.random.default_rng(act_seq)
        self._rng_gauge = np.random.default_rng(gauge_seq)
        self.f_ref = float(rig.config.stage.physics.preload_n) / 4.0
        self._q_cmd = np.zeros(self.stage.n_act)
        self.direction = np.ones(self.stage.n_act)
        self._p = self.model.p_zero.copy()
        self._p_nominal = self.model.p_zero.copy()  # the noise-free pose (the hinge's slip is measured on it)
        # the reading's sensitivity to rx and ry (µm per mrad; the families' gauge is linear)
        bump = self.model.p_zero[None, :] + _FD_UM * np.eye(3)[1:]
        base = self.truth.reading(self.model.p_zero[None, :], 0.0)
        self.tilt_lever = (self.truth.reading(bump, 0.0) - base) / _FD_UM
        self._slips = any(t["kind"] == "hinge_slip" for t in rig.terms)
        self.time_s = 0.0
        self.move_time_s = rig.config.backend.simulated.move_time_s

    # ---- physics of a batch of moves -------------------------------------------------
    def _directions(self, dq: np.ndarray, last: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """New directions (m, n_q) and whether each move turns the actuator round."""
        moved = np.abs(dq) > HELD_UM
        new = np.where(moved, np.sign(dq), last)
        return new, moved & (new != last)

    def _nominal(self, q: np.ndarray, direction: np.ndarray):
        """Actual positions, pose, reading and ball forces of the noise-free moves."""
        q_act = self.truth.actual_positions(q, direction)
        p, active = self.truth.pose(q_act)
        h = self.model.nd * self.model.gain * q_act - self.model.gap_um
        comp = h - p @ self.model.A.T
        return q_act, p, active, comp, self.model.k_c * np.maximum(comp, 0.0)

    def actuator_std(self, q_prev: np.ndarray, q: np.ndarray, reverses: np.ndarray, force_n: np.ndarray) -> np.ndarray:
        """Scatter of each actuator's actual position, shape (m, n_q) (variances of the terms add)."""
        var = np.full(q.shape, self.rig.driver_std_um ** 2)
        for t in self.rig.terms:
            var = var + _term_std(t, q_prev, q, reverses, force_n, self.f_ref) ** 2
        return np.sqrt(var)

    def _read_mean(self, p: np.ndarray) -> np.ndarray:
        return self.truth.reading(p, self.time_s + self.move_time_s)

    # ---- moving ------------------------------------------------------------------------
    def move(self, u: np.ndarray) -> Measurement:
        """One move: scatter the actual positions, settle, read once."""
        u, q = self.command_for(u)
        q2 = q[None, :]
        dq = q2 - self._q_cmd[None, :]
        new_dir, rev = self._directions(dq, self.direction[None, :])
        _, p_nom, _, _, force = self._nominal(q2, new_dir)
        sd = self.actuator_std(self._q_cmd[None, :], q2, rev, force)[0]
        q_act = self.truth.actual_positions(q2, new_dir)[0] + sd * self._rng_act.standard_normal(q.size)
        p, _ = self.truth.pose(q_act[None, :])
        if self._slips:  # drawn only on rigs that have the term (the other families' streams are unchanged)
            p[0, 1:3] += _slip_sd(self.rig.terms, self._p_nominal[None, :], p_nom)[0] * self._rng_act.standard_normal(2)
        self._p, self._q_cmd, self.direction, self._p_nominal = p[0], q.copy(), new_dir[0], p_nom[0]
        self.time_s += self.move_time_s
        t = self.read()
        self._set_state(t, q)
        return Measurement(t_um=t, q_um=q, u=u, time_s=self.time_s)

    def read(self) -> float:
        """A gauge reading of the current pose (one gauge-noise draw), µm."""
        if self._closed:
            raise BackendError("the backend is closed")
        std = math.sqrt(self.gauge_std_um ** 2 + float(_tilt_var(self.rig.terms, self._p[None, :])[0]))
        return float(self.truth.reading(self._p[None, :], self.time_s)[0] + std * self._rng_gauge.standard_normal())

    # ---- truth -------------------------------------------------------------------------
    def _setup(self, s: np.ndarray, u: np.ndarray):
        s = np.asarray(s, dtype=float).reshape(-1)
        q = np.atleast_2d(np.asarray(u, dtype=float)) @ self.K.T
        q_prev = np.broadcast_to(s[1:], q.shape)
        new_dir, rev = self._directions(q - q_prev, np.broadcast_to(self.direction, q.shape))
        return q_prev, q, new_dir, rev

    def moments(self, s: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Exact mean and variance of the next reading from state s (see the module docstring).

        Returns
        -------
        mean, var : ndarray, shape (m,)
        exact : ndarray of bool, shape (m,)
            The contact set is safely fixed (else use :meth:`mc_moments`).
        """
        q_prev, q, new_dir, rev = self._setup(s, u)
        q_act, p, active, comp, force = self._nominal(q, new_dir)
        sd = self.actuator_std(q_prev, q, rev, force)
        mean = self._read_mean(p)
        m, n = q.shape
        bumped = np.repeat(q_act[:, None, :], n, axis=1) + _FD_UM * np.eye(n)[None, :, :]
        pb, _ = self.truth.pose(bumped.reshape(m * n, n))
        S = (self._read_mean(pb).reshape(m, n) - mean[:, None]) / _FD_UM
        var = np.sum(S * S * sd * sd, axis=1) + self.gauge_std_um ** 2 + self._reading_var(q_prev, p)
        # the balls' compressions respond to the actuator errors affinely too (rows: bumped actuator)
        hb = self.model.nd * self.model.gain * bumped.reshape(m * n, n) - self.model.gap_um
        C = ((hb - pb @ self.model.A.T).reshape(m, n, n) - comp[:, None, :]) / _FD_UM
        comp_sd = np.sqrt(np.einsum("mji,mj->mi", C * C, sd * sd))
        exact = np.all(active, axis=1) & np.all(comp > CONTACT_MARGIN_SIGMAS * comp_sd, axis=1)
        return mean, var, exact

    def _reading_var(self, q_prev: np.ndarray, p: np.ndarray) -> np.ndarray:
        """Variance the reading-level terms add to moves from q_prev (m, n_q) to the noise-free
        poses p (m, 3), shape (m,): the tilted gauge's, and the hinge's slip through the levers."""
        slip = self._slip_std(q_prev, p)
        return _tilt_var(self.rig.terms, p) + np.sum((slip * self.tilt_lever[None, :]) ** 2, axis=1)

    def _slip_std(self, q_prev: np.ndarray, p: np.ndarray) -> np.ndarray:
        """The hinge's slip std (mrad) of rx, ry over moves from q_prev (m, n_q; its first row, the
        state's) to the noise-free poses p (m, 3), shape (m, 2); zeros without a hinge term."""
        if not self._slips:
            return np.zeros((p.shape[0], 2))
        _, p_prev, _, _, _ = self._nominal(q_prev[:1], self.direction[None, :])
        return _slip_sd(self.rig.terms, np.broadcast_to(p_prev, p.shape), p)

    def mc_moments(self, s: np.ndarray, u: np.ndarray, n_draws: int = 1000, seed: int = 0
                   ) -> tuple[np.ndarray, np.ndarray]:
        """Monte Carlo mean and variance of the next reading (the simulator's own draws).

        Parameters
        ----------
        u : ndarray, shape (m, n_p) or (n_p,)
        n_draws : int
        seed : int
            Common random numbers for every row.
        """
        q_prev, q, new_dir, rev = self._setup(s, u)
        q_act, p_nom, _, _, force = self._nominal(q, new_dir)
        sd = self.actuator_std(q_prev, q, rev, force)
        slip = self._slip_std(q_prev, p_nom)
        r = np.random.default_rng(seed)
        Z = r.standard_normal((n_draws, q.shape[1]))
        G = r.standard_normal(n_draws)
        W = r.standard_normal((n_draws, 2)) if self._slips else np.zeros((n_draws, 2))
        m, n = q.shape
        means, vars_ = np.empty(m), np.empty(m)
        chunk = max(1, 200_000 // n_draws)
        for k0 in range(0, m, chunk):
            qa, sdk = q_act[k0:k0 + chunk], sd[k0:k0 + chunk]
            draws = qa[:, None, :] + sdk[:, None, :] * Z[None, :, :]
            p, _ = self.truth.pose(draws.reshape(-1, n))
            p[:, 1:3] += (slip[k0:k0 + chunk][:, None, :] * W[None, :, :]).reshape(-1, 2)
            g_std = np.sqrt(self.gauge_std_um ** 2 + _tilt_var(self.rig.terms, p)).reshape(len(qa), n_draws)
            t = self._read_mean(p).reshape(len(qa), n_draws) + g_std * G[None, :]
            means[k0:k0 + chunk] = np.mean(t, axis=1)
            vars_[k0:k0 + chunk] = np.var(t, axis=1, ddof=1)
        return means, vars_

    def _checked(self, s: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        mean, var, exact = self.moments(s, u)
        if not np.all(exact):
            bad = np.flatnonzero(~exact)
            U = np.atleast_2d(np.asarray(u, dtype=float))
            mean[bad], var[bad] = self.mc_moments(s, U[bad])
        return mean, var

    def true_mean(self, s: np.ndarray, u: np.ndarray) -> np.ndarray | float:
        """Expected reading of the next move from state s, shape () or (m,)."""
        mean, _ = self._checked(s, u)
        return float(mean[0]) if np.ndim(u) == 1 else mean

    def true_var(self, s: np.ndarray, u: np.ndarray) -> np.ndarray | float:
        """Variance of the next reading from state s (µm²), shape () or (m,)."""
        _, var = self._checked(s, u)
        return float(var[0]) if np.ndim(u) == 1 else var
