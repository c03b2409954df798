"""An independent stage generator for the diagnosis tests (written apart from microctl's physics).

Why: the diagnosis fits causes through microctl's own contact physics. Data planted with that
same code would let a physics bug cancel out. This module simulates the same *kind* of stage
— a flexure platform pressed by a preload onto four balls, each pushed by a PZT, one gauge at a
tool point — from first principles, with its own parametrisation, its own equilibrium solver,
its own sensor and noise code, and physical parameters the diagnosis is **not** told
(preload, ball stiffness, flexure stiffness are drawn at random). It imports nothing from
``microctl``'s physics (``physics``, ``afm``, ``extended``, the simulated backend); it reads only
the geometry numbers (contact points, tool point, actuator ranges) from a stage YAML file, and
takes the vocabulary (cause names, parameters, planted magnitudes) from the cause registry
:mod:`microctl.stage.causes`, translating each cause into its own parametrisation (:data:`SETTERS`).

Parametrisation
---------------
Platform pose P = (z µm, θx mrad, θy mrad) relative to the CAD zero. A small rotation
ω = (θx, θy, 0) moves a platform point r by ω × r, whose vertical component is
θx·r_y − θy·r_x (mrad × mm = µm), so the platform surface above ball i (at (x_i, y_i) mm)
rises by s_i(P) = z + y_i θx − x_i θy, and the tool point (x_t, y_t) by the same formula.

Forces (N, moments in N·µm/mrad so that energy is N·µm):

- ball i is a one-sided spring of stiffness k_i pushing up with f_i = k_i · max(0, b_i − s_i(P)),
  b_i = g_i · q_act,i − gap_i the height of its tip (gain g_i, a low set screw gap_i);
- the flexure pulls the platform down with the preload F (N) at its centre (the origin) and
  resists motion with stiffnesses (k_z, k_θx, k_θy): generalised force
  (−F − k_z z, −k_θx θx, −k_θy θy);
- equilibrium: Σ_i f_i (1, y_i, −x_i) + flexure = 0.

The equilibrium is found by enumerating the 2⁴ contact sets: for each set S the force balance
with the balls of S in contact is linear; the solution whose balls in S are compressed and
whose other balls are not is the equilibrium (the energy is strictly convex, so it is unique).

The gauge reads the vertical displacement of the tool point relative to its reading at the
zero command (taken once, *with* its noise, as a real gauge is zeroed), through
``scale·d + quad·d²``, plus drift·time and Gaussian noise. Drivers position each actuator
with Gaussian error; stick-slip adds Gaussian error ∝ |Δq_i|; backlash makes an actuator end
``lag`` short of its command in the direction it last moved (a move by at most
``STILL_TOL_UM`` keeps the previous direction; the zero command is approached upwards).

The commands q are what a controller sends for a pose u: the CAD inverse kinematics
q_i = z + y_i θx − x_i θy of the nominal geometry.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Callable

import numpy as np
import yaml

#: Effects outside the vocabulary (the diagnosis must call them ``unexplained``), and the shapes
#: that were outside it once and are now vocabulary causes (the diagnosis must name them).
OFF_VOCABULARY = ("smooth_bump", "periodic", "thermal_drift", "direction_curvature", "creep",
                  "gauge_periodic", "hysteresis")
IN_VOCABULARY_NOW = ("hysteresis",)

#: An actuator step this small (µm) is "held still": it keeps its last direction of approach.
STILL_TOL_UM = 1e-9


@dataclass(frozen=True)
class Geometry:
    """Nominal (CAD) geometry read from a stage file.

    Attributes
    ----------
    contacts_mm : ndarray, shape (4, 2)
        (x, y) of each ball's contact point.
    tool_mm : ndarray, shape (2,)
        (x, y) of the tool point.
    lo_um, hi_um : ndarray, shape (4,)
        Actuator command range.
    """

    contacts_mm: np.ndarray
    tool_mm: np.ndarray
    lo_um: np.ndarray
    hi_um: np.ndarray

    @property
    def n_act(self) -> int:
        return self.contacts_mm.shape[0]

    def rows(self, contacts_mm: np.ndarray | None = None) -> np.ndarray:
        """(1, y_i, −x_i) per ball, shape (n, 3): the rise of the surface above ball i per unit pose."""
        c = self.contacts_mm if contacts_mm is None else contacts_mm
        return np.column_stack([np.ones(len(c)), c[:, 1], -c[:, 0]])

    def commands(self, u: np.ndarray) -> np.ndarray:
        """CAD inverse kinematics: q = rows · u, shape (m, 4) (n·d = 1 for vertical balls)."""
        return np.atleast_2d(u) @ self.rows().T


def load_geometry(path: str | Path) -> Geometry:
    """Contact points, tool point and ranges of a stage YAML file (z, rx, ry stage, vertical balls)."""
    doc = yaml.safe_load(Path(path).read_text())
    st = doc["stage"]
    acts = st["actuators"]
    return Geometry(
        contacts_mm=np.array([[float(a["contact_mm"][0]), float(a["contact_mm"][1])] for a in acts]),
        tool_mm=np.array([float(st["tool"]["point_mm"][0]), float(st["tool"]["point_mm"][1])]),
        lo_um=np.array([float(a.get("range_um", [0, 32])[0]) for a in acts]),
        hi_um=np.array([float(a.get("range_um", [0, 32])[1]) for a in acts]),
    )


@dataclass(frozen=True)
class Truth:
    """The physical stage: random physics, defects, noise.

    Physics
        ``ball_stiffness`` (4,) N/µm, ``preload_n``, ``flexure`` (k_z N/µm, k_θx, k_θy N·µm/mrad²).
    Defects (healthy values by default)
        ``gain`` (4,), ``contact_shift_mm`` (4, 2), ``tool_shift_mm`` (2,), ``scale``,
        ``quad_per_um``, ``gap_um`` (4,), ``lag_um`` (4,), ``drift_um_per_s``,
        ``friction_per_um`` (4,), ``extra`` (an off-vocabulary term of (u, q, time, direction)),
        ``creep_per_um`` (4,): piezo creep, the actuator overshoots its command by creep × its
        last step by the time the gauge is read,
        ``play_um``, ``play_weight`` (4, m): piezo hysteresis, a Prandtl-Ishlinskii sum of m play
        operators per actuator (thresholds, weights; see :func:`play`), ``ripple`` (amplitude µm,
        period µm, phase rad): a periodic gauge error A·sin(2π d/λ + φ) in the displacement d.
    Noise
        ``gauge_um``, ``driver_um``; ``move_time_s`` per move.
    """

    geometry: Geometry
    ball_stiffness: np.ndarray
    preload_n: float
    flexure: np.ndarray
    gain: np.ndarray
    contact_shift_mm: np.ndarray
    tool_shift_mm: np.ndarray
    scale: float = 1.0
    quad_per_um: float = 0.0
    gap_um: np.ndarray = field(default_factory=lambda: np.zeros(4))
    lag_um: np.ndarray = field(default_factory=lambda: np.zeros(4))
    drift_um_per_s: float = 0.0
    friction_per_um: np.ndarray = field(default_factory=lambda: np.zeros(4))
    extra: Callable | None = None
    creep_per_um: np.ndarray = field(default_factory=lambda: np.zeros(4))
    play_um: np.ndarray | None = None
    play_weight: np.ndarray | None = None
    ripple: tuple = (0.0, 10.0, 0.0)
    gauge_um: float = 0.05
    driver_um: float = 0.01
    move_time_s: float = 1.0

    @property
    def compression_um(self) -> float:
        """Preload over the mean ball stiffness: the total compression the preload makes up, µm."""
        return float(self.preload_n / np.mean(self.ball_stiffness))


#: Defaults of ``stage.physics`` (docs/config.md) when the stage file has none.
DEFAULT_PHYSICS = {"contact_stiffness_n_per_um": 20.0, "preload_n": 100.0, "flexure_stiffness": [0.01, 5.0, 5.0]}


def load_physics(path: str | Path) -> dict:
    """``stage.physics`` of a stage YAML file (the documented defaults where absent)."""
    doc = yaml.safe_load(Path(path).read_text())
    ph = dict(DEFAULT_PHYSICS)
    ph.update((doc["stage"].get("physics") or {}))
    return ph


def configured_truth(geometry: Geometry, physics: dict, **noise) -> "Truth":
    """The stage exactly as its config describes it: equal balls, the config's preload and flexure."""
    n = geometry.n_act
    return Truth(
        geometry=geometry,
        ball_stiffness=np.full(n, float(physics["contact_stiffness_n_per_um"])),
        preload_n=float(physics["preload_n"]),
        flexure=np.array(physics["flexure_stiffness"], dtype=float),
        gain=np.ones(n), contact_shift_mm=np.zeros((n, 2)), tool_shift_mm=np.zeros(2),
        gap_um=np.zeros(n), lag_um=np.zeros(n), friction_per_um=np.zeros(n), **noise,
    )


#: A healthy random stage may differ from its config's description by at most this fraction of
#: the gauge noise (rms over the workspace, after the gauge zero): the spec's "clean data, where the
#: model is right within noise".
HEALTHY_TOLERANCE = 0.2


def healthy_difference_um(truth: "Truth", configured: "Truth", rng: np.random.Generator, n: int = 200) -> float:
    """RMS difference of the noise-free readings of two healthy stages over random moves (mean removed)."""
    q = truth.geometry.commands(random_moves(truth.geometry, n, rng))
    d = [tool_height(t, platform_pose(t, q)) - tool_height(t, platform_pose(t, np.zeros((1, q.shape[1]))))[0]
         for t in (truth, configured)]
    r = d[0] - d[1]
    return float(np.std(r))


def random_truth(geometry: Geometry, rng: np.random.Generator, *, gauge_um: float = 0.05,
                 driver_um: float = 0.01, physics: dict | None = None) -> Truth:
    """A healthy stage with random physics in physical ranges.

    - ball (+ PZT) stiffness k_b ~ U(10, 40) N/µm, each ball within ±10 % of it (manufacturing
      spread: the elastic sharing of an inconsistency is then *weighted*, unlike the model's);
    - preload compression c = F/k_b ~ U(4, 20) µm (preload 40-800 N): a well preloaded stage,
      where a 10 % gain or a 2 mm contact offset (≤ 3.2 µm of inconsistency, ≤ 0.8 µm per ball)
      does not lift a ball off (shared/spec/diagnosis.md, "physics the causes are defined against");
    - flexure: k_z ~ U(0.005, 0.05) N/µm; k_θx, k_θy ~ k_b · U(0.05, 0.4) N·µm/mrad² each
      (soft against the balls: the flexure guides, the balls carry the load).

    Healthy means the configured model is right within the noise (the spec's clean data): with
    ``physics`` (the config's ``stage.physics``, :func:`load_physics`), a draw whose healthy
    readings differ from those of the stage the config describes by more than
    :data:`HEALTHY_TOLERANCE` × ``gauge_um`` rms is drawn again. (Preload and ball spread do not
    change a healthy stage's readings; the flexure's rotational compliance k_θ/(k_b Σ y²) does —
    the platform turns a little less than commanded — and must be near the config's.)
    """
    n = geometry.n_act
    for _ in range(1000):
        kb = float(rng.uniform(10.0, 40.0))
        truth = Truth(
            geometry=geometry,
            ball_stiffness=kb * rng.uniform(0.9, 1.1, n),
            preload_n=kb * float(rng.uniform(4.0, 20.0)),
            flexure=np.array([rng.uniform(0.005, 0.05), kb * rng.uniform(0.05, 0.4), kb * rng.uniform(0.05, 0.4)]),
            gain=np.ones(n),
            contact_shift_mm=np.zeros((n, 2)),
            tool_shift_mm=np.zeros(2),
            gap_um=np.zeros(n),
            lag_um=np.zeros(n),
            friction_per_um=np.zeros(n),
            gauge_um=gauge_um,
            driver_um=driver_um,
        )
        if physics is None or gauge_um <= 0:
            return truth
        ref = configured_truth(geometry, physics)
        if healthy_difference_um(truth, ref, np.random.default_rng(0)) <= HEALTHY_TOLERANCE * gauge_um:
            return truth
    raise RuntimeError("no healthy random stage close to the config's physics in 1000 draws")


# ---- physics -----------------------------------------------------------------------------


def _contact_sets(n: int) -> list[np.ndarray]:
    # larger contact sets first: the usual answer is found early
    sets = [np.array(s, dtype=bool) for s in itertools.product([True, False], repeat=n)]
    return sorted(sets, key=lambda s: -int(s.sum()))


def platform_pose(truth: Truth, q_actual: np.ndarray) -> np.ndarray:
    """Equilibrium pose (z, θx, θy) for actual actuator positions, shape (m, 3).

    Parameters
    ----------
    q_actual : ndarray, shape (m, 4)
    """
    g = truth.geometry
    R = g.rows(g.contacts_mm + truth.contact_shift_mm)  # (n, 3)
    tips = np.atleast_2d(q_actual) * truth.gain - truth.gap_um  # (m, n)
    k = truth.ball_stiffness
    kz, ktx, kty = truth.flexure
    flex = np.diag([kz, ktx, kty])
    f0 = np.array([-truth.preload_n, 0.0, 0.0])
    m = tips.shape[0]
    pose = np.full((m, 3), np.nan)
    todo = np.ones(m, dtype=bool)
    tol = 1e-9
    for S in _contact_sets(g.n_act):
        if not todo.any():
            break
        # flex P + Σ_{i∈S} k_i r_i (r_i·P) = f0 + Σ_{i∈S} k_i b_i r_i
        M = flex + (R[S].T * k[S]) @ R[S]
        rhs = f0[None, :] + (tips[todo][:, S] * k[S]) @ R[S]
        P = np.linalg.solve(M, rhs.T).T
        comp = tips[todo] - P @ R.T  # compression of every ball
        ok = np.all(np.where(S[None, :], comp >= -tol, comp <= tol), axis=1)
        idx = np.flatnonzero(todo)[ok]
        pose[idx] = P[ok]
        todo[idx] = False
    if todo.any():  # pragma: no cover - convexity guarantees a consistent set
        raise RuntimeError(f"no consistent contact set for {int(todo.sum())} moves")
    return pose


def tool_height(truth: Truth, pose: np.ndarray) -> np.ndarray:
    """Vertical displacement of the (shifted) tool point for poses (m, 3), µm."""
    x, y = truth.geometry.tool_mm + truth.tool_shift_mm
    return pose[:, 0] + y * pose[:, 1] - x * pose[:, 2]


def gauge(truth: Truth, d_um: np.ndarray) -> np.ndarray:
    """Noise-free gauge transfer scale·d + quad·d² (+ the periodic interpolation error, if any)."""
    amp, lam, phi = truth.ripple
    return truth.scale * d_um + truth.quad_per_um * d_um * d_um + amp * np.sin(2 * np.pi * d_um / lam + phi)


def play(state: np.ndarray, cmd: np.ndarray, r: np.ndarray) -> np.ndarray:
    """The play (backlash) operator, written here from its definition: the output follows the
    input with a dead band of half-width r, y = max(x − r, min(x + r, y_prev)) (Krasnosel'skii
    & Pokrovskii; the building block of a Prandtl-Ishlinskii hysteresis model).

    Parameters
    ----------
    state : ndarray (4, m)
        The operators' outputs before the move.
    cmd : ndarray (4,)
        The command.
    r : ndarray (4, m)
        Thresholds, µm.
    """
    x = cmd[:, None]
    return np.maximum(x - r, np.minimum(x + r, state))


# ---- moves -----------------------------------------------------------------------------------


def random_moves(geometry: Geometry, n: int, rng: np.random.Generator) -> np.ndarray:
    """``n`` poses uniform in the workspace {u : lo ≤ q(u) ≤ hi} (rejection from its box), random order."""
    R = geometry.rows()
    # bounding box of the workspace from the Table-I-like geometry: z within the ranges,
    # rotations within range / lever
    lever = np.max(np.abs(geometry.contacts_mm))
    span = float(np.max(geometry.hi_um - geometry.lo_um))
    lo = np.array([geometry.lo_um.min(), -span / lever, -span / lever])
    hi = np.array([geometry.hi_um.max(), span / lever, span / lever])
    out = []
    have = 0
    while have < n:
        u = rng.uniform(lo, hi, size=(4 * n, 3))
        q = u @ R.T
        ok = np.all((q >= geometry.lo_um) & (q <= geometry.hi_um), axis=1)
        out.append(u[ok])
        have += int(ok.sum())
    return np.vstack(out)[:n]


# ---- a run -----------------------------------------------------------------------------------


@dataclass(frozen=True)
class Run:
    """One measured run, in execution order (the measurement-log columns).

    Attributes
    ----------
    u : (n, 3); q : (n, 4) commands sent; q_prev : (n, 4); t : (n,) readings relative to the
    gauge zero; t_prev : (n,); time_s : (n,); direction : (n, 4) true last-move direction.
    """

    u: np.ndarray
    q: np.ndarray
    q_prev: np.ndarray
    t: np.ndarray
    t_prev: np.ndarray
    time_s: np.ndarray
    direction: np.ndarray

    @property
    def n(self) -> int:
        return int(self.t.size)

    def corrupted(self, cells: list[tuple[int, str, float]]) -> "Run":
        """A copy with single cells of the log overwritten: (row, column, value), column one of
        ``t``, ``q1``..``q4``. Only that cell changes (the log's ``*_prev`` columns are cells of
        their own, written from the stage's state, so they keep the true values)."""
        t, q = self.t.copy(), self.q.copy()
        for row, col, value in cells:
            if col == "t":
                t[row] = value
            else:
                q[row, int(col[1:]) - 1] = value
        return replace(self, t=t, q=q)

    def write_log(self, path: str | Path, actuator_names=("q1", "q2", "q3", "q4"), dof=("z", "rx", "ry"),
                  tool: str = "t") -> None:
        """Write the run as a measurement log CSV (shared/spec/measurement-log.md), own writer."""
        cols = (["seq", "time_s"] + [f"u_{d}" for d in dof] + list(actuator_names)
                + [f"{tool}_prev"] + [f"{a}_prev" for a in actuator_names] + [tool])
        lines = [",".join(cols)]
        for k in range(self.n):
            vals = [str(k), repr(float(self.time_s[k]))] + [repr(float(v)) for v in self.u[k]]
            vals += [repr(float(v)) for v in self.q[k]] + [repr(float(self.t_prev[k]))]
            vals += [repr(float(v)) for v in self.q_prev[k]] + [repr(float(self.t[k]))]
            lines.append(",".join(vals))
        Path(path).write_text("\n".join(lines) + "\n")


def run(truth: Truth, u: np.ndarray, rng: np.random.Generator) -> Run:
    """Execute the poses ``u`` (m, 3) in order from the zero command; one reading per move."""
    g = truth.geometry
    q = g.commands(u)
    n, m = q.shape[1], q.shape[0]
    direction = np.ones(n)  # the zero command is approached upwards
    q_prev_cmd = np.zeros(n)

    hyst = truth.play_um is not None
    # Prandtl-Ishlinskii: q_act = q + Σ_j w_j (p_j − q); the zero command approached from below
    # leaves every play output at −r_j, a major-loop half-width Σ_j w_j r_j
    p_state = -truth.play_um if hyst else None

    def actual(cmd, dirn, dq):
        nonlocal p_state
        noise = truth.driver_um * rng.standard_normal(n) + truth.friction_per_um * np.abs(dq) * rng.standard_normal(n)
        out = cmd - truth.lag_um * dirn + truth.creep_per_um * dq + noise
        if hyst:
            p_state = play(p_state, cmd, truth.play_um)
            out = out + np.sum(truth.play_weight * (p_state - cmd[:, None]), axis=1)
        return out

    # the gauge is zeroed at the zero command: one noisy reading of the rest pose
    rest = platform_pose(truth, actual(np.zeros(n), direction, np.zeros(n))[None, :])
    d_rest = tool_height(truth, rest)[0]
    zero_reading = gauge(truth, 0.0) + truth.gauge_um * rng.standard_normal()
    t = np.zeros(m)
    dirs = np.zeros((m, n))
    time_s = truth.move_time_s * np.arange(1, m + 1)
    for k in range(m):
        dq = q[k] - q_prev_cmd
        direction = np.where(np.abs(dq) > STILL_TOL_UM, np.sign(dq), direction)
        dirs[k] = direction
        P = platform_pose(truth, actual(q[k], direction, dq)[None, :])
        d = tool_height(truth, P)[0] - d_rest
        reading = gauge(truth, d) + truth.drift_um_per_s * time_s[k] + truth.gauge_um * rng.standard_normal()
        t[k] = reading - zero_reading
        q_prev_cmd = q[k]
    if truth.extra is not None:
        t = t + np.asarray(truth.extra(u, q, time_s, dirs), dtype=float)
    q_prev = np.vstack([np.zeros((1, n)), q[:-1]])
    t_prev = np.concatenate([[0.0], t[:-1]])
    return Run(u=np.asarray(u, dtype=float), q=q, q_prev=q_prev, t=t, t_prev=t_prev, time_s=time_s, direction=dirs)


# ---- planting ------------------------------------------------------------------------------


def _set_per(truth: Truth, attr: str, act: int, value):
    v = getattr(truth, attr).copy()
    v[act - 1] = value
    return replace(truth, **{attr: v})


#: How each vocabulary cause changes *this* stage (its own parametrisation): cause name ->
#: (truth, registry entry) -> truth. Every cause of microctl's registry must be here.
SETTERS: dict[str, Callable] = {
    "actuator_gain": lambda tr, c: _set_per(tr, "gain", c.actuator, c.gain),
    "contact_offset": lambda tr, c: _set_per(tr, "contact_shift_mm", c.actuator, (c.dx_mm, c.dy_mm)),
    "tool_offset": lambda tr, c: replace(tr, tool_shift_mm=np.array([c.dx_mm, c.dy_mm])),
    "sensor_scale": lambda tr, c: replace(tr, scale=c.scale),
    "sensor_nonlinearity": lambda tr, c: replace(tr, quad_per_um=c.quad_per_um),
    "contact_loss": lambda tr, c: _set_per(tr, "gap_um", c.actuator, c.gap_um),
    "backlash": lambda tr, c: _set_per(tr, "lag_um", c.actuator, c.lag_um),
    "drift": lambda tr, c: replace(tr, drift_um_per_s=c.rate_um_per_s),
    "actuator_friction": lambda tr, c: _set_per(tr, "friction_per_um", c.actuator, c.std_per_um),
    "hysteresis": lambda tr, c: _set_loop(tr, c.actuator, c.half_width_um, c.range_um),
}


def _set_loop(truth: Truth, act: int, half_width_um: float, range_um: float, m: int = 4) -> Truth:
    """A Prandtl-Ishlinskii loop on actuator ``act`` in this stage's own terms: m play operators with
    thresholds R·j/m and equal weights whose Σ_j w_j r_j is the major loop's half-width."""
    n = truth.geometry.n_act
    r = np.zeros((n, m)) if truth.play_um is None else truth.play_um.copy()
    w = np.zeros((n, m)) if truth.play_weight is None else truth.play_weight.copy()
    r[act - 1] = range_um * np.arange(1, m + 1) / m
    w[act - 1] = half_width_um / r[act - 1].sum()
    return replace(truth, play_um=r, play_weight=w)


def plant(truth: Truth, cause, rng: np.random.Generator | None = None) -> tuple[Truth, dict]:
    """Plant one vocabulary cause into this stage.

    Parameters
    ----------
    truth : Truth
    cause : str or registry entry
        A cause name (its magnitude and actuator are then drawn by the registry's
        ``Cause.draw`` with ``rng``, sized for *this* stage's preload compression where that
        matters), or an entry such as ``ActuatorGain(2, 0.95)``.
    rng : numpy Generator
        Needed when ``cause`` is a name.

    Returns
    -------
    truth : Truth
    planted : dict
        ``{"cause", "actuator" (1-based or None), "params": {...}}`` in the report's names.
    """
    if isinstance(cause, str):
        from microctl.stage.causes import (
            REGISTRY,  # the vocabulary only: names, parameters, magnitudes
        )

        cls = REGISTRY[cause]
        act = int(rng.integers(1, truth.geometry.n_act + 1))
        cause = cls.draw(rng, act if cls.per_actuator else None, compression_um=truth.compression_um)
    params = {k: float(v) for k, v in cause.report_params().items() if k != "actuator"}
    planted = {"cause": cause.name, "actuator": getattr(cause, "actuator", None), "params": params}
    return SETTERS[cause.name](truth, cause), planted


def plant_off_vocabulary(truth: Truth, shape: str, rng: np.random.Generator, n_moves: int) -> tuple[Truth, dict]:
    """Plant an effect outside the vocabulary (amplitudes 0.3-1 µm, 6-20 × the gauge noise).

    - ``smooth_bump``: A·exp(−|z − z0|²/(2 w²)) over the standardised pose z = u/span, a
      Gaussian bump of width w ∈ U(0.2, 0.4) at a random centre inside the workspace;
    - ``periodic``: A·sin(2π u_j/λ + φ) in one random input j, 2-4 periods over its range;
    - ``thermal_drift``: A·(1 − exp(−time/τ)), τ ∈ U(0.1, 0.4) × the run's duration (warm-up);
    - ``direction_curvature``: A·dir_i·(q_i/range)² on one actuator i (a hysteresis whose
      size grows with the stroke);
    - ``hysteresis``: a Prandtl-Ishlinskii loop (4 play operators, thresholds R·j/4 with
      R ∈ U(4, 10) µm, equal weights) of major-loop half-width h ∈ U(0.15, 0.3) µm on one random
      actuator or (half the draws) on all four: the output depends on the direction *and the
      length* of the moves, not on the pose alone;
    - ``gauge_periodic``: a periodic gauge error A·sin(2π d/λ + φ) in the displacement d with
      A ∈ U(0.15, 0.3) µm, λ ∈ U(8, 12) µm;
    - ``creep``: piezo creep on one random actuator i, which by the time the gauge is read has
      moved on past its command by c·Δq_i, c ∈ U(0.01, 0.03) (0.1-0.9 µm on a 10-30 µm step):
      an overshoot in the direction of the last step that grows with its length, history the
      ``hysteresis`` cause (a lag, never an overshoot) cannot express. Written down before the
      diagnosis was run on it; its first run is reported by scripts/diagnosis_confusion.py.
    """
    g = truth.geometry
    A = float(rng.uniform(0.3, 1.0)) * (1.0 if rng.random() < 0.5 else -1.0)
    lever = np.max(np.abs(g.contacts_mm))
    span = np.array([g.hi_um.max() - g.lo_um.min(), 2 * (g.hi_um.max() - g.lo_um.min()) / lever,
                     2 * (g.hi_um.max() - g.lo_um.min()) / lever])
    if shape == "smooth_bump":
        w = float(rng.uniform(0.2, 0.4))
        centre = random_moves(g, 1, rng)[0] / span

        def extra(u, q, time_s, dirs):
            z = np.atleast_2d(u) / span
            return A * np.exp(-np.sum((z - centre) ** 2, axis=1) / (2 * w * w))

        info = {"amplitude_um": A, "width": w}
    elif shape == "periodic":
        j = int(rng.integers(0, 3))
        lam = span[j] / float(rng.uniform(2.0, 4.0))
        phi = float(rng.uniform(0, 2 * np.pi))

        def extra(u, q, time_s, dirs):
            return A * np.sin(2 * np.pi * np.atleast_2d(u)[:, j] / lam + phi)

        info = {"amplitude_um": A, "input": j, "period": lam}
    elif shape == "thermal_drift":
        tau = float(rng.uniform(0.1, 0.4)) * n_moves * truth.move_time_s

        def extra(u, q, time_s, dirs):
            return A * (1.0 - np.exp(-np.asarray(time_s) / tau))

        info = {"amplitude_um": A, "tau_s": tau}
    elif shape == "direction_curvature":
        i = int(rng.integers(0, g.n_act))
        rng_i = g.hi_um[i] - g.lo_um[i]

        def extra(u, q, time_s, dirs):
            return A * dirs[:, i] * (q[:, i] / rng_i) ** 2

        info = {"amplitude_um": A, "actuator": i + 1}
    elif shape in ("hysteresis", "gauge_periodic"):
        return plant_history(truth, shape, rng)
    elif shape == "creep":
        i = int(rng.integers(0, g.n_act))
        c = float(rng.uniform(0.01, 0.03))
        return _set_per(truth, "creep_per_um", i + 1, c), {"shape": shape, "creep_per_um": c, "actuator": i + 1}
    else:
        raise ValueError(f"unknown off-vocabulary shape {shape!r}; known: {', '.join(OFF_VOCABULARY)}")
    return replace(truth, extra=extra), {"shape": shape, **info}


def plant_history(truth: Truth, shape: str, rng: np.random.Generator, *, half_width_um: float | None = None,
                  actuators: tuple | None = None, amplitude_um: float | None = None,
                  period_um: float | None = None) -> tuple[Truth, dict]:
    """Plant a hysteresis loop or a periodic gauge error (the history-dependent shapes of
    :func:`plant_off_vocabulary`); keywords fix what is otherwise drawn."""
    n = truth.geometry.n_act
    if shape == "hysteresis":
        h = float(rng.uniform(0.15, 0.3)) if half_width_um is None else half_width_um
        big = float(rng.uniform(4.0, 10.0))
        if actuators is None:
            actuators = tuple(range(1, n + 1)) if rng.random() < 0.5 else (int(rng.integers(1, n + 1)),)
        m = 4
        r = np.tile(big * np.arange(1, m + 1) / m, (n, 1))
        w = np.zeros((n, m))
        for a in actuators:
            w[a - 1] = h / r[a - 1].sum()  # Σ_j w_j r_j = h
        return replace(truth, play_um=r, play_weight=w), {"shape": shape, "half_width_um": h,
                                                         "largest_threshold_um": big, "actuators": list(actuators)}
    A = float(rng.uniform(0.15, 0.3)) if amplitude_um is None else amplitude_um
    lam = float(rng.uniform(8.0, 12.0)) if period_um is None else period_um
    phi = float(rng.uniform(0, 2 * np.pi))
    return replace(truth, ripple=(A, lam, phi)), {"shape": shape, "amplitude_um": A, "period_um": lam}


def corrupt_cells(run_: Run, rng: np.random.Generator, count: int) -> tuple[Run, list[tuple[int, str, float]]]:
    """Overwrite ``count`` random cells (rows ≥ 1, columns t or q1..q4) with a plausible-looking
    but wrong number: a q cell with a value in 40-60 µm (a typo'd command), a t cell shifted by
    5-50 µm. Returns the run and the cells (row, column, value)."""
    rows = rng.choice(np.arange(1, run_.n - 1), size=count, replace=False)
    cells = []
    for r in rows:
        col = ["t", "q1", "q2", "q3", "q4"][int(rng.integers(0, 5))]
        if col == "t":
            val = float(run_.t[r] + rng.choice([-1, 1]) * rng.uniform(5.0, 50.0))
        else:
            val = float(rng.uniform(40.0, 60.0))
        cells.append((int(r), col, val))
    return run_.corrupted(cells), cells
