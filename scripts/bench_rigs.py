#!/usr/bin/env python
"""Does the EAFM's repeatability transfer? Seeded random simulated rigs, scored against the truth.

For each of ``--rigs`` random rigs (seeded; nothing is tuned per rig) — Table I geometry;
stick-slip 0.02-0.08 µm per µm moved on one or two random actuators; every actuator's gain
within ±5 %; gauge noise 0.03-0.08 µm; preload 300-800 N (every ball stays loaded over the
workspace: checked at the polytope's vertices, else the rig is redrawn and the redraw
counted) — and each training size in ``--sizes``:

1. ``collect``: the method's training design on the simulated rig (a measurement log);
2. ``train``: the residual VHGPR (eq. 3) with the method's settings;
3. ``solve`` the targets 6, 12, 18, 24 µm in sequence on a fresh simulated stage, each from
   the state the previous executed command left and with the actuators' last directions of
   motion that the commands sent give (what ``api.Operator`` passes; read by a model with a
   reversal source, docs/controller.md "The move's context").

Each chosen pose is scored with the simulator's truth from the same state: its true
(noise-free) mean error, its true scatter (std), the oracle's scatter (the quietest pose
that truly reaches the target: eq. 4 solved on the true mean and variance) and the AFM
baseline's; and the predicted std is compared with the true one (calibration). Each trained
model is also audited at its training moves (scripts/rig_audit.py): the evidence the readings
carry against it (the truth's expected log-likelihood ratio over the model's predictive
distribution), against what one noise source needs to enter the selection, so that a failing
rig whose data could not show the model's error is told from one whose data did.

Methods (columns):

- ``paper``: the first release as shipped: space-filling design, the paper's noise model
  (``hgp``: g ~ GP(mu0, K_g)), SE kernel only, r_e = noise_mean;
- ``hgp``: today's pipeline with the paper's noise model (the default design, linear trend,
  r_e = noise_quantile), to show what the noise model alone changes;
- ``physical``: the previous release's noise model (every actuator's stick-slip);
- ``default``: today's defaults (the noise dictionary, selected by the data; f's variance in
  the objective; the least-motion rule);
- ``eq4``: the default without the least-motion rule (eq. 4's optimum always);
- ``credible``: the default with the previous release's least-motion rule (the optimum also
  better with posterior probability >= ``credible_level``: ``least_motion_credible``);
- ``weighed``: the default with the unselected sources' model-averaged variance in eq. 4's
  objective (``weigh_alternatives``);
- ``noise_only``: today's model with the previous objective (no f variance);
- ``params``: the default with the noise parameters' uncertainty in the objective;
- ``g_on``: the default with g's GP always kept beside the selected sources (``g_gp: on``; the
  default keeps it only where the bound pays for it, microctl.models.g_gp_selection);
- ``covering``: the default trained on the previous default design, ``covering``: the default
  design ``covering_still`` without its still moves (every 20th move the previous command again,
  which reads the noise floor; microctl.measurement.design);
- ``refined``: the default, trained on as many moves of which 40 % are refinement moves (rounds of
  40 after the designed ones, each chosen where the model is least sure of the optimum, then
  training again: ``microctl learn``, microctl.api.learn, microctl.control.refine);
- ``told`` (a reference): the default told which dictionary quantities carry the rig's true
  scatter (``noise_sources``, microctl.models.declared_sources; rig_families.FamilyRig.true_sources)
  instead of selecting them. A family bar the ``told`` reference misses too is not missed by the
  selection.

Bars (issue 10): with 200 moves, on >= 90 % of rigs, at every target, true std <= 1.25 x
the oracle's and |true error| <= 0.1 µm; the readings' true RMS deviation from the prediction
(sqrt(std^2 + error^2)) / the predicted std (sqrt(f_var + noise), what the result states) in
[0.67, 1.5] on >= 90 % of rig-targets. (Until 2026-11-27 the true std alone was divided by the
predicted std, which includes f's variance: scatter against scatter plus bias. The table also
gives the scatter alone against the predicted noise: "scatter calibration".)

The main job over seed sets (``--seed-sets N``): ``configs/experiments/paper.yaml`` run N times
with every seed of the file shifted by ``10000 k`` (k = 1..N; ``microctl experiment
--seed-offset``), with the controllers the bars judge (AFM, EAFM, oracle; the sequence
controllers are left out), each bar of docs/experiments.md evaluated (:mod:`microctl.experiments.bars`)
and its pass count printed. Bar: every bar on >= 9 of 10 sets.

Usage: ``python scripts/bench_rigs.py [--rigs 24] [--sizes 125,200] [--methods paper,hgp,default]
[--params] [--seed-sets 10] [--seed 0] [--jobs 2] [--json out.json] [--verbose]``. Seeds: rig k uses
``seed + k``. ``--rigs 0`` skips the rigs, ``--seed-sets 0`` (default) the main job.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import sys
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, replace
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from microctl.cli import one_blas_thread  # noqa: E402

# Before NumPy loads: the workers' numerics on one BLAS thread each, as the command line runs
# them (two threads per worker on two cores oversubscribed them; a user's count wins).
one_blas_thread(os.environ, sys.modules)

import numpy as np

from microctl.backends.collect import run_collect  # noqa: E402
from microctl.backends.simulated import SimulatedStage  # noqa: E402
from microctl.control.controller import (  # noqa: E402
    AFMController,
    ControllerSettings,
    OptimalController,
    RedundantSet,  # noqa: E402
)
from microctl.control.context import ByDirection  # noqa: E402
from microctl.control.oracle import OracleController  # noqa: E402
from microctl import api  # noqa: E402
from microctl.measurement.design import DEFAULT_DESIGN, training_moves  # noqa: E402
from microctl.measurement.log import read_log  # noqa: E402
from microctl.models.afm import AnalyticForwardModel  # noqa: E402
from microctl.models import direction  # noqa: E402
from microctl.models.eafm import EAFM  # noqa: E402
from microctl.models.floor_check import finding_of, with_floor_check  # noqa: E402
from microctl.models.noise_dictionary import candidate_features  # noqa: E402
from microctl.models.training import (  # noqa: E402
    SELECTION_ALPHA,
    ResidualModelSettings,
    residual_dataset,
    train_residual_model,
)
from microctl.stage.config import StageConfig, parse_stage_config  # noqa: E402
from microctl.stage.physics import actual_positions, ball_heights, solve_equilibrium  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
import rig_audit  # noqa: E402
import rig_families  # noqa: E402

TARGETS_UM = (6.0, 12.0, 18.0, 24.0)
STD_BAR, ERR_BAR_UM, CAL_BAR = 1.25, 0.1, (0.67, 1.5)
#: The mean half of the bar judged against the accuracy the training data allow (reported beside
#: issue 18's 0.1 µm, never instead of it): |true error| <= max(ERR_BAR_UM, DATA_ERR_K x sigma*),
#: sigma* the std that the training noise gives f's mean at the *oracle's* pose when f's form is
#: told the readings' true variances (``noise_std_best_um`` of :func:`_mean_parts`; at the oracle's
#: pose so that parking where f is poorly determined widens nothing). A method that put the
#: oracle's pose and the best weighting to use still errs by N(0, sigma*^2) there, so it fails
#: issue 18's 0.1 µm on a share of rig-targets set by the rig's noise and the number of moves, not
#: by the method: a bar that fails the oracle's equal is the rig's, not the method's. K = 3 was
#: fixed before any run was scored with it: such a method then fails a target with probability
#: 0.27 % (its four targets are strongly correlated, so about that per rig); where sigma* is not
#: available (a sparse model, a reading set aside) the bar stays 0.1 µm.
DATA_ERR_K = 3.0
#: Relative RMS error (v_fit / v - 1) up to which a fit of the truth's variances at the training
#: moves by candidate sources counts as describing them (scripts/rig_audit.py ``dictionary_fit``):
#: the relative standard error of one variance estimated from n Gaussian readings is sqrt(2 / n),
#: 0.10 at n = 200, so 200 readings cannot resolve a misfit much below a tenth. Fixed before it
#: was read on any rig.
DICT_FIT_REL = 0.1
#: What the calibration columns compare (the page's legend).
CAL_TEXT = ("calibration = the readings' true RMS deviation from the prediction (scatter and mean error) / the "
            f"predicted std sqrt(f_var + noise), in {list(CAL_BAR)}; scatter calibration = true std / predicted "
            "noise std, in the same interval")
CONTACTS_MM = ([15, 0, 5], [0, -15, 5], [-15, 0, 5], [0, 15, 5])
TOOL_MM = [-40.957602214449594, 28.678821817552297, 10.0]


@dataclass(frozen=True)
class Method:
    """A training design, a residual model and a controller objective; ``refine``: part of the
    training moves chosen by the trained model (:func:`collect_and_train`)."""

    name: str
    design: str
    model: ResidualModelSettings
    controller: ControllerSettings
    refine: bool = False


METHODS = {
    "paper": Method("paper", "space_filling", ResidualModelSettings(noise_model="hgp", linear_trend=False),
                    ControllerSettings(r_e="noise_mean")),
    "hgp": Method("hgp", DEFAULT_DESIGN, ResidualModelSettings(noise_model="hgp"), ControllerSettings()),
    # the previous release's default (issue 10): g's prior mean is every actuator's stick-slip
    "physical": Method("physical", DEFAULT_DESIGN, ResidualModelSettings(noise_model="physical"), ControllerSettings()),
    "default": Method("default", DEFAULT_DESIGN, ResidualModelSettings(), ControllerSettings()),
    # the default, with the same number of training moves of which 40 % are refinement moves
    # (microctl learn, microctl.api.learn): collect, train, then rounds of 40 moves chosen by
    # the model (microctl.control.refine), each followed by training again
    "refined": Method("refined", DEFAULT_DESIGN, ResidualModelSettings(), ControllerSettings(), refine=True),
    # the default trained on the previous default design, covering without its still moves
    # (microctl.measurement.design: every 20th move of covering_still repeats the previous command)
    "covering": Method("covering", "covering", ResidualModelSettings(), ControllerSettings()),
    # a reference, not a method: the default told the dictionary quantities that carry the rig's true
    # scatter (FamilyRig.true_sources; the stick-slip actuators on the default rigs) instead of
    # selecting them (microctl.models.declared_sources); what the selection misses is the difference
    "told": Method("told", DEFAULT_DESIGN, ResidualModelSettings(noise_sources=()), ControllerSettings()),
    # the default without the least-motion rule (microctl.control.credible): eq. 4's optimum always,
    # the default before issue 18's least-motion change
    "eq4": Method("eq4", DEFAULT_DESIGN, ResidualModelSettings(), ControllerSettings(prefer_least_motion=False)),
    # the default with the previous release's least-motion rule: the optimum also had to be better
    # with posterior probability >= credible_level (microctl.control.credible)
    "credible": Method("credible", DEFAULT_DESIGN, ResidualModelSettings(), ControllerSettings(least_motion_credible=True)),
    # the default with the unselected noise sources' model-averaged variance in eq. 4's objective
    # (microctl.models.alternatives)
    "weighed": Method("weighed", DEFAULT_DESIGN, ResidualModelSettings(), ControllerSettings(weigh_alternatives=True)),
    # the default without the mean correction's posterior variance in the objective (the
    # previous release's objective; the default adds it since issue 18)
    "noise_only": Method("noise_only", DEFAULT_DESIGN, ResidualModelSettings(), ControllerSettings(epistemic=False)),
    # the default with the noise parameters' uncertainty propagated into the objective
    "params": Method("params", DEFAULT_DESIGN, ResidualModelSettings(noise_parameter_uncertainty=True),
                     ControllerSettings()),
    # the default with g's GP always kept beside the selected sources (g_gp: on, the default until
    # g_gp: auto was measured; microctl.models.g_gp_selection)
    "g_on": Method("g_on", DEFAULT_DESIGN, ResidualModelSettings(g_gp="on"), ControllerSettings()),
    # the default with g's GP on the actuators' positions and steps (microctl.models.noise_inputs)
    "g_actuators": Method("g_actuators", DEFAULT_DESIGN, ResidualModelSettings(g_inputs="actuators"),
                          ControllerSettings()),
    # ... and g's fit started also from the log squared residuals (microctl.gp.noise_start)
    "g_act_res": Method("g_act_res", DEFAULT_DESIGN, ResidualModelSettings(g_inputs="actuators", g_start="residuals"),
                        ControllerSettings()),
    # the paper's constant prior mean, g's GP on the actuators and started from the residuals:
    # how much of the repeatability g's GP learns without the dictionary
    "hgp_act_res": Method("hgp_act_res", DEFAULT_DESIGN,
                          ResidualModelSettings(noise_model="hgp", g_inputs="actuators", g_start="residuals"),
                          ControllerSettings()),
}
SEED_SET_STRIDE = 10_000
#: Controllers a seed-set run keeps (those the bars of microctl.experiments.bars judge).
SEED_SET_CONTROLLERS = ("afm", "eafm", "oracle")
MAIN_JOB = Path(__file__).resolve().parents[1] / "configs" / "experiments" / "paper.yaml"


# --------------------------------------------------------------------------- rigs


def _rig_dict(seed: int, draw: int) -> dict:
    r = np.random.default_rng([seed, 7919, draw])
    n_fric = int(r.integers(1, 3))
    fric = sorted(int(i) for i in r.choice(4, n_fric, replace=False))
    return {
        "stage": {
            "name": f"bench-rig-{seed}", "dof": ["z", "rx", "ry"],
            "tool": {"name": "t", "point_mm": TOOL_MM, "direction": [0, 0, 1]},
            "actuators": [{"name": f"q{i + 1}", "contact_mm": CONTACTS_MM[i], "range_um": [0, 32],
                           "limit_um": [0, 38]} for i in range(4)],
            "physics": {"contact_stiffness_n_per_um": 20.0, "preload_n": float(r.uniform(300.0, 800.0)),
                        "flexure_stiffness": [0.01, 5.0, 5.0]},
        },
        "backend": {"kind": "simulated", "simulated": {
            "seed": int(seed), "gauge_noise_std_um": float(r.uniform(0.03, 0.08)), "driver_accuracy_um": 0.01,
            "move_time_s": 1.0,
            "effects": {
                "actuator_gain": [{"actuator": i + 1, "gain": float(1.0 + r.uniform(-0.05, 0.05))} for i in range(4)],
                "actuator_friction": [{"actuator": i + 1, "std_per_um": float(r.uniform(0.02, 0.08))} for i in fric],
            }}},
    }


def _all_balls_loaded(config: StageConfig) -> bool:
    """Every ball in contact at every vertex of the workspace polytope (the physics is convex in q)."""
    afm = AnalyticForwardModel(config.stage)
    stage = SimulatedStage(config)
    V = RedundantSet(afm).vertices
    q = V @ afm.K.T
    q_act = actual_positions(stage.model, q, np.ones_like(q))
    _, active = solve_equilibrium(stage.model, ball_heights(stage.model, q_act))
    return bool(np.all(active))


def make_rig(seed: int) -> tuple[StageConfig, int]:
    """The rig of ``seed`` and how many draws were rejected for lifting a ball."""
    for draw in range(20):
        cfg = parse_stage_config(_rig_dict(seed, draw), f"<bench rig {seed}>")
        if _all_balls_loaded(cfg):
            return cfg, draw
    raise RuntimeError(f"rig {seed}: no well-preloaded draw in 20 tries")


# --------------------------------------------------------------------------- one rig


#: Method ``refined``: ``microctl learn`` (:func:`microctl.api.learn`): 40 % of the training moves
#: as refinement rounds of 40 (1 of 125, 2 of 200), the targets of their episodes drawn from
#: REFINE_TARGETS_UM (the working range of TARGETS_UM with a margin; what a user would give
#: ``--target-range``).
REFINE_TARGETS_UM = (0.0, 30.0)


def collect_and_train(open_stage, cfg: StageConfig, afm: AnalyticForwardModel, meth: Method, n: int, seed: int,
                      settings: ResidualModelSettings):
    """What a user runs: ``collect`` (``meth.design`` moves, seed ``seed``) to a log, ``train``; for a
    refining method ``learn`` (:func:`microctl.api.learn`: the design, then refinement rounds,
    each followed by training, targets seeded by ``seed`` and the round). ``open_stage()``
    gives the stage the moves run on (one stage for all).

    Returns
    -------
    model : FittedVHGPR
    data : ResidualData
    log : MeasurementLog
        Every executed move (designed and refinement), in order.
    """
    with tempfile.TemporaryDirectory() as tmp, open_stage() as stage:
        log_path = Path(tmp) / "train.csv"
        model = None
        if meth.refine:
            model = api.learn(api.Stage(cfg, afm), n, log_path, seed=seed, design=meth.design,
                              target_range_um=REFINE_TARGETS_UM, settings=settings, controller=meth.controller,
                              backend=stage)
        else:
            run_collect(stage, training_moves(afm, meth.design, n, seed), log_path, quiet=True)
        log = read_log(log_path, cfg.stage, min_rows=5)
        data = residual_dataset(log, afm)
        if model is None:
            model = train_residual_model(data, afm, settings)
    return model, data, log


def train_on_rig(cfg: StageConfig, afm: AnalyticForwardModel, design: str, n: int, seed: int,
                 settings: ResidualModelSettings):
    """The model :func:`collect_and_train` gives for n ``design`` moves on the rig ``cfg`` (stage
    seed + 10000)."""
    meth = Method("design", design, settings, ControllerSettings())
    return collect_and_train(lambda: SimulatedStage(cfg, seed=seed + 10_000), cfg, afm, meth, n, seed, settings)[0]


def _told(meth: Method, sources: tuple[str, ...]) -> ResidualModelSettings:
    """The method's residual model; the ``told`` reference's names the rig's true ``sources``."""
    return replace(meth.model, noise_sources=sources) if meth.name == "told" else meth.model


def run_rig(seed: int, sizes: tuple[int, ...], methods: tuple[str, ...]) -> dict:
    """Collect, train and solve on one rig for every size and method; score against the truth."""
    cfg, redraws = make_rig(seed)
    afm = AnalyticForwardModel(cfg.stage)
    eff = cfg.backend.simulated.effects
    out = {"seed": seed, "redraws": redraws, "preload_n": cfg.stage.physics.preload_n,
           "gauge_um": cfg.backend.simulated.gauge_noise_std_um,
           "friction": {f"q{e.actuator}": e.std_per_um for e in eff.actuator_friction},
           "gains": [g.gain for g in eff.actuator_gain], "runs": []}
    told = tuple(f"dq{e.actuator}" for e in eff.actuator_friction)  # the stick-slip actuators (method told)
    for n in sizes:
        for name in methods:
            meth = METHODS[name]
            t0 = time.perf_counter()
            model, _, _ = collect_and_train(lambda: SimulatedStage(cfg, seed=seed + 10_000), cfg, afm, meth, n, seed,
                                            _told(meth, told))
            t_fit = time.perf_counter() - t0
            ctrls = ByDirection(EAFM(afm, model), lambda e: OptimalController(e, meth.controller))
            base = AFMController(afm)
            rows = []
            with SimulatedStage(cfg, seed=seed + 20_000) as stage:
                oracle = OracleController(afm, stage)
                prev, last = None, direction.initial(afm.n_q)  # the directions, from the commands sent
                for target in TARGETS_UM:
                    s = stage.state
                    ctrl = ctrls(last)
                    res = ctrl.solve(target, s, u_init=prev)
                    last = direction.after_move(last, s[1:], res.q)
                    o = oracle.solve(target, s)
                    a = base.solve(target, s)
                    true_mean = float(stage.true_mean(s, res.u))
                    true_std = math.sqrt(float(stage.true_var(s, res.u)))
                    (noise_c, f_c), (noise_o, f_o) = _model_noise(ctrl.eafm, s, res.u), _model_noise(ctrl.eafm, s, o.u)
                    rows.append({"pred_noise_std_um": noise_c, "f_std_um": f_c, "pred_noise_std_oracle_um": noise_o,
                                 "f_std_oracle_um": f_o, "target_um": target, "err_um": true_mean - target,
                                 "std_um": true_std,
                                 "oracle_std_um": o.predicted_std_um,
                                 "afm_std_um": math.sqrt(float(stage.true_var(s, a.u))),
                                 "pred_std_um": res.predicted_std_um,
                                 "pred_alt_var_um2": float(ctrl.eafm.alt_var(s, res.u)[0]),
                                 "q_um": res.q.round(3).tolist(), "oracle_q_um": o.q.round(3).tolist(),
                                 "solve_ms": 1e3 * res.solve_time_s})
                    stage.move(res.u)
                    prev = res.u
            sel = (model.info.get("noise_selection") or {}).get("selected")
            out["runs"].append({"n": n, "method": name, "fit_s": t_fit, "selected": sel, "targets": rows})
    return out


# --------------------------------------------------------------------------- rig families (issue 18)

#: Fine oracle search on the families (the default rigs keep the shipped settings).
FAMILY_ORACLE = {"grid": 41, "line_points": 81, "zooms": 3}
#: Random reaching poses per target that check the oracle, and the tolerance of "quieter"
#: (relative, in std: the truth is exact up to round-off, or Monte Carlo with common random numbers).
VERIFY_POSES, VERIFY_TOL = 400, 0.01


def _random_reaching(oracle: OracleController, stage, s: np.ndarray, target: float, n: int, seed: int) -> np.ndarray:
    """``n`` random poses of the redundant set moved onto true_mean = target, in range, shape (k, n_p)."""
    rs = oracle.rset
    U, _ = rs.grid(target, 11)
    C = (U / rs.D) @ rs.N
    r = np.random.default_rng(seed)
    Cr = r.uniform(C.min(axis=0), C.max(axis=0), size=(n, C.shape[1]))
    Ur = (Cr @ rs.N.T) * rs.D + (U[0] / rs.D @ rs.v_hat) * rs.v_hat * rs.D
    for _ in range(8):  # Newton along dir_u onto the true mean
        t = np.asarray(stage.true_mean(s, Ur))
        slope = (np.asarray(stage.true_mean(s, Ur + 1e-4 * rs.dir_u)) - t) / 1e-4
        Ur = Ur + ((target - t) / np.where(np.abs(slope) > 1e-9, slope, 1e-9))[:, None] * rs.dir_u
    ok = np.abs(np.asarray(stage.true_mean(s, Ur)) - target) <= 1e-6 * max(1.0, target)
    q = Ur @ oracle.afm.K.T
    ok &= np.all((q >= oracle.afm.lo - 1e-9) & (q <= oracle.afm.hi + 1e-9), axis=1)
    return Ur[ok]


def _model_noise(eafm: EAFM, s: np.ndarray, u: np.ndarray) -> tuple[float, float]:
    """The model's predicted noise std exp(g)^(1/2) (with g's variance) and f's posterior std at u."""
    p = eafm.predict(s, u)
    return float(np.sqrt(np.exp(p.g_mean[0] + p.g_var[0] / 2.0))), float(np.sqrt(p.f_var[0]))


def _mean_parts(eafm: EAFM, train, s: np.ndarray, u: np.ndarray, true_mean: float) -> dict | None:
    """f's error at the chosen pose split into the part noise-free training data would leave and
    the part the training noise draws add (scripts/rig_audit.py, ``mean_error_parts``), and
    ``noise_std_best_um``: the noise part's std for f's form weighed by the true variances (what
    the noise model's weighting cost); None where the split is not available (a sparse model, a
    reading set aside)."""
    if train is None:
        return None
    y, y_true, v = train
    x = np.concatenate([s, u] + ([eafm.direction] if eafm.uses_direction else []))
    w = rig_audit.f_weights(eafm.model, y, x)
    if w is None:
        return None
    y_star = true_mean - float(eafm.afm.t_of(u[None, :])[0])
    w_best = rig_audit.f_weights(eafm.model, y, x, noise_var=v)  # the same form told the true variances
    return {**rig_audit.mean_error_parts(w, y, y_true, v, y_star),
            "noise_std_best_um": rig_audit.mean_error_parts(w_best, y, y_true, v, y_star)["noise_std_um"]}


def _score_target(stage, ctrl, oracle, base, target: float, s: np.ndarray, prev, seed: int, train=None) -> dict:
    """Solve one target with the method, the oracle and the AFM; score them with the family's truth
    (``train``: the training residuals, their noise-free truth and true variances, for
    :func:`_mean_parts`)."""
    res = ctrl.solve(target, s, u_init=prev)
    o = oracle.solve(target, s)
    a = base.solve(target, s)
    rand = _random_reaching(oracle, stage, s, target, VERIFY_POSES, seed)
    rand_std = np.sqrt(np.asarray(stage.true_var(s, rand))) if len(rand) else np.zeros(0)
    viol = int(np.sum(rand_std < o.predicted_std_um * (1.0 - VERIFY_TOL)))
    mc_mean, mc_var = stage.mc_moments(s, res.u[None, :], n_draws=4000, seed=seed)
    true_mean = float(stage.true_mean(s, res.u))
    noise_c, f_c = _model_noise(ctrl.eafm, s, res.u)
    noise_o, f_o = _model_noise(ctrl.eafm, s, o.u)
    at_oracle = _mean_parts(ctrl.eafm, train, s, o.u, target)  # the oracle reaches the target in truth
    return {"pred_noise_std_um": noise_c, "f_std_um": f_c, "pred_noise_std_oracle_um": noise_o,
            "f_std_oracle_um": f_o, "target_um": target, "err_um": true_mean - target, "std_um": math.sqrt(float(stage.true_var(s, res.u))),
            "mc_std_um": float(math.sqrt(mc_var[0])), "mc_err_um": float(mc_mean[0] - target),
            "oracle_std_um": o.predicted_std_um, "afm_std_um": math.sqrt(float(stage.true_var(s, a.u))),
            "afm_err_um": float(stage.true_mean(s, a.u)) - target,
            "pred_std_um": res.predicted_std_um, "pred_alt_var_um2": float(ctrl.eafm.alt_var(s, res.u)[0]),
            "u": res.u.tolist(), "q_um": res.q.round(3).tolist(),
            "q_prev_um": s[1:].round(3).tolist(), "oracle_q_um": o.q.round(3).tolist(), "afm_q_um": a.q.round(3).tolist(), "solve_ms": 1e3 * res.solve_time_s, "choice": res.choice,
            "verify_n": int(len(rand)), "verify_violations": viol,
            "mean_parts": _mean_parts(ctrl.eafm, train, s, res.u, true_mean),
            "f_noise_std_best_oracle_um": at_oracle["noise_std_best_um"] if at_oracle else math.nan,
            "verify_min_std_um": float(rand_std.min()) if len(rand) else float("nan")}


def run_family_rig(family: str, seed: int, sizes: tuple[int, ...], methods: tuple[str, ...]) -> dict:
    """:func:`run_rig` on a rig of ``family`` (scripts/rig_families.py): the same collect, train
    and solve, scored with the family's truth, the oracle by the fine search and checked
    against random reaching poses."""
    rig = rig_families.make_family_rig(family, seed)
    cfg = rig.config
    afm = AnalyticForwardModel(cfg.stage)
    out = {"seed": seed, "family": family, **rig.describe(), "runs": []}
    for n in sizes:
        for name in methods:
            meth = METHODS[name]
            t0 = time.perf_counter()
            model, data, log = collect_and_train(lambda: rig.stage(seed + 10_000), cfg, afm, meth, n, seed,
                                                 _told(meth, rig.true_sources()))
            t_fit = time.perf_counter() - t0
            model, _ = with_floor_check(model, data)  # kept in the JSON (microctl.models.floor_check)
            with rig.stage(seed + 10_000) as stage:  # the collection's seed: the replay meets the same states
                truth = rig_audit.replay_truth(stage, log.u)
                audit = rig_audit.training_evidence(stage, log.u, log.t, data, model, truth=truth)
            # the training residuals, the truth's noise-free ones and the readings' true variances
            train = (data.y, truth[0] - (np.asarray(log.t) - data.y), truth[1])
            audit["entry_nats"] = rig_audit.entry_evidence(
                SELECTION_ALPHA, (model.info.get("noise_selection") or {}).get("candidates", 1))
            audit.update(_dictionary_fit(afm, data, model, truth[1]))
            ctrls = ByDirection(EAFM(afm, model), lambda e: OptimalController(e, meth.controller))
            base = AFMController(afm)
            rows = []
            with rig.stage(seed + 20_000) as stage:
                oracle = OracleController(afm, stage, **FAMILY_ORACLE)
                prev, last = None, direction.initial(afm.n_q)  # the directions, from the commands sent
                for k, target in enumerate(TARGETS_UM):
                    s = stage.state
                    rows.append(_score_target(stage, ctrls(last), oracle, base, target, s, prev, seed * 10 + k, train))
                    prev = np.asarray(rows[-1]["u"])
                    stage.move(prev)
                    last = direction.after_move(last, s[1:], afm.q_of(prev))
            sel = (model.info.get("noise_selection") or {}).get("selected")
            out["runs"].append({"n": n, "method": name, "fit_s": t_fit, "selected": sel, "audit": audit,
                                "floor_check": model.info.get("floor_check"), "targets": rows})
    return out


# --------------------------------------------------------------------------- summary


def _q(a, p):
    return float(np.percentile(a, p)) if len(a) else float("nan")


def summarise(results: list[dict], sizes, methods) -> list[dict]:
    table = []
    for n in sizes:
        for name in methods:
            runs = [r for res in results for r in res["runs"] if r["n"] == n and r["method"] == name]
            ratio = np.array([t["std_um"] / t["oracle_std_um"] for r in runs for t in r["targets"]])
            err = np.array([abs(t["err_um"]) for r in runs for t in r["targets"]])
            # the prediction N(target, pred_std^2) against the readings' true RMS deviation from it
            # (scatter and mean error); and the predicted scatter alone against the true scatter
            cal = np.array([math.hypot(t["std_um"], t["err_um"]) / t["pred_std_um"] for r in runs for t in r["targets"]])
            cal_scatter = np.array([t["std_um"] / t["pred_noise_std_um"] for r in runs for t in r["targets"]])
            afm_ratio = np.array([t["afm_std_um"] / t["oracle_std_um"] for r in runs for t in r["targets"]])
            rig_ok = [_rig_passes(r) for r in runs]
            rig_std_ok = [all(t["std_um"] <= STD_BAR * t["oracle_std_um"] for t in r["targets"]) for r in runs]
            rig_err_ok = [all(abs(t["err_um"]) <= ERR_BAR_UM for t in r["targets"]) for r in runs]
            cal_ok = (cal >= CAL_BAR[0]) & (cal <= CAL_BAR[1])
            table.append({
                "n": n, "method": name, "rigs": len(runs), "rigs_pass": int(sum(rig_ok)),
                "rigs_std_pass": int(sum(rig_std_ok)), "rigs_err_pass": int(sum(rig_err_ok)),
                "ratio_median": _q(ratio, 50), "ratio_p90": _q(ratio, 90), "ratio_max": float(np.max(ratio)),
                "err_median_um": _q(err, 50), "err_p90_um": _q(err, 90), "err_max_um": float(np.max(err)),
                "cal_pass": int(np.sum(cal_ok)), "cal_n": int(cal.size), "cal_median": _q(cal, 50),
                "cal_min": float(np.min(cal)), "cal_max": float(np.max(cal)),
                "cal_scatter_pass": int(np.sum((cal_scatter >= CAL_BAR[0]) & (cal_scatter <= CAL_BAR[1]))),
                "afm_ratio_median": _q(afm_ratio, 50),
                "fit_s_median": _q([r["fit_s"] for r in runs], 50),
                "solve_ms_median": _q([t["solve_ms"] for r in runs for t in r["targets"]], 50),
            })
    return table


def print_table(table: list[dict], n_rigs: int) -> None:
    print(f"\nrigs passing = at every target true std <= {STD_BAR} x oracle AND |true error| <= {ERR_BAR_UM} µm "
          f"(bar: >= 90 % of {n_rigs} rigs at n = 200); calibration = true RMS error/predicted std in {list(CAL_BAR)} "
          "(bar: >= 90 % of rig-targets)")
    hdr = (f"{'n':>4} {'method':>8} {'pass':>7} {'std ok':>7} {'err ok':>7} | {'std/oracle med':>14} {'p90':>6} "
           f"{'max':>7} | {'|err| med':>9} {'p90':>6} {'max':>6} | {'calib ok':>9} {'med':>5} {'min':>5} {'max':>5} | "
           f"{'AFM/oracle':>10} {'fit s':>6} {'solve ms':>8}")
    print(hdr)
    print("-" * len(hdr))
    for t in table:
        print(f"{t['n']:>4} {t['method']:>8} {t['rigs_pass']:>3}/{t['rigs']:<3} {t['rigs_std_pass']:>3}/{t['rigs']:<3} "
              f"{t['rigs_err_pass']:>3}/{t['rigs']:<3} | {t['ratio_median']:>14.2f} {t['ratio_p90']:>6.2f} "
              f"{t['ratio_max']:>7.2f} | {t['err_median_um']:>9.3f} {t['err_p90_um']:>6.3f} {t['err_max_um']:>6.3f} | "
              f"{t['cal_pass']:>4}/{t['cal_n']:<4} {t['cal_median']:>5.2f} {t['cal_min']:>5.2f} {t['cal_max']:>5.2f} | "
              f"{t['afm_ratio_median']:>10.2f} {t['fit_s_median']:>6.2f} {t['solve_ms_median']:>8.1f}")


#: Columns of the rig table in Markdown: (summary key, header, format); the header row and the
#: row labels (n, method) are what tests/test_docs.py compares with docs/generated/bench_rigs.md.
RIG_COLUMNS = (
    ("n", "n (moves)", "{}"), ("method", "method", "{}"),
    ("rigs_pass", "rigs passing", None), ("rigs_std_pass", "std ok", None), ("rigs_err_pass", "err ok", None),
    ("ratio_median", "true std / oracle, median", "{:.2f}"), ("ratio_p90", "p90", "{:.2f}"),
    ("ratio_max", "max", "{:.2f}"),
    ("err_median_um", "abs true error median (µm)", "{:.3f}"), ("err_p90_um", "p90 (µm)", "{:.3f}"),
    ("err_max_um", "max (µm)", "{:.3f}"),
    ("cal_pass", "calibration ok", None), ("cal_median", "true RMS error / predicted std, median", "{:.2f}"),
    ("cal_min", "min", "{:.2f}"), ("cal_max", "max", "{:.2f}"),
    ("cal_scatter_pass", "scatter calibration ok", None),
    ("afm_ratio_median", "AFM std / oracle, median", "{:.2f}"), ("fit_s_median", "fit (s), median", "{:.2f}"),
    ("solve_ms_median", "solve (ms), median", "{:.1f}"),
)


def _markdown_table(tag: str, columns, table: list[dict]) -> list[str]:
    """A summary as a Markdown table, one row per entry of ``table``; a column whose format is None
    is a count "k/N", out of the rig-targets (calibration), the random poses tried (oracle check)
    or the rigs."""
    L = [f"<!-- table: {tag} -->", "| " + " | ".join(h for _, h, _ in columns) + " |", "|" + "---|" * len(columns)]
    for t in table:
        cells = []
        for key, _, fmt in columns:
            if fmt is None:
                total = t["cal_n"] if key.startswith("cal_") else t["verify_n"] if key == "verify_violations" \
                    else t["data_n"] if key == "data_widened" else t["rigs"]
                cells.append(f"{t[key]}/{total}")
            else:
                cells.append(fmt.format(t[key]))
        L.append("| " + " | ".join(cells) + " |")
    return L


def rig_table_markdown(table: list[dict]) -> list[str]:
    """The rig summary as a Markdown table (one row per size and method)."""
    return _markdown_table("rigs", RIG_COLUMNS, table)


def failing_targets(results: list[dict]) -> list[dict]:
    """Every rig-target that misses the bar, with why: ``scatter`` (std > 1.25 x oracle), ``mean``
    (|true error| > 0.1 µm) or both, and the numbers to read it by."""
    out = []
    for res in results:
        for r in res["runs"]:
            for t in r["targets"]:
                why = [w for w, bad in (("scatter", t["std_um"] > STD_BAR * t["oracle_std_um"]),
                                        ("mean", abs(t["err_um"]) > ERR_BAR_UM)) if bad]
                if why:
                    out.append({"family": res.get("family", "stick_slip"), "seed": res["seed"], "n": r["n"],
                                "method": r["method"], "why": "+".join(why), "audit": r.get("audit"),
                                "floor_check": r.get("floor_check"), **t})
    return out


def family_tables(results: list[dict], families, sizes, methods) -> list[dict]:
    """:func:`summarise` per family, with the oracle's check against random reaching poses."""
    table = []
    for fam in families:
        sub = [r for r in results if r["family"] == fam]
        if not sub:
            continue
        for row in summarise(sub, sizes, methods):
            runs = [r for res in sub for r in res["runs"] if r["n"] == row["n"] and r["method"] == row["method"]]
            tg = [t for r in runs for t in r["targets"]]
            row.update(family=fam, verify_n=sum(t["verify_n"] for t in tg),
                       verify_violations=sum(t["verify_violations"] for t in tg),
                       mc_std_dev_max=float(max(abs(t["mc_std_um"] / t["std_um"] - 1.0) for t in tg)),
                       controller_losses=_controller_losses(runs), mean_draws=_mean_draws(runs),
                       **_audit_summary(runs), **data_bar_summary(runs))
            table.append(row)
    return table


#: A failing rig-target is the controller's loss when the model's own expected squared error
#: (f's variance plus the mean noise variance) at the oracle's pose is below the chosen pose's by
#: more than this fraction: the model saw the better pose and the controller did not take it.
CONTROLLER_LOSS_MARGIN = 0.05


def controller_loss(t: dict) -> bool:
    """Whether the model itself ranks the oracle's pose better than the one the controller chose
    (by more than :data:`CONTROLLER_LOSS_MARGIN` in expected squared error, f_var + noise);
    otherwise a failing target is the model's loss (it predicts the oracle's pose no better)."""
    chosen = t["pred_noise_std_um"] ** 2 + t["f_std_um"] ** 2
    oracle = t["pred_noise_std_oracle_um"] ** 2 + t["f_std_oracle_um"] ** 2
    return oracle < (1.0 - CONTROLLER_LOSS_MARGIN) * chosen


def _controller_losses(runs: list[dict]) -> str:
    """``"k of m"``: of the m failing rig-targets, k where the model ranked the oracle's pose better."""
    fails = [t for r in runs for t in r["targets"] if not _target_passes(t)]
    return f"{sum(controller_loss(t) for t in fails)} of {len(fails)}"


def _mean_draws(runs: list[dict]) -> str:
    """``"k of m (|z| med x)"``: of the m rig-targets failing on the mean whose error could be
    split (:func:`_mean_parts`), k where the model trained on the truth's noise-free residuals
    would be within the bar at the same pose (the error is the training noise's draw), and the
    median |z| of the noise part under the truth."""
    parts = [t["mean_parts"] for r in runs for t in r["targets"]
             if abs(t["err_um"]) > ERR_BAR_UM and t.get("mean_parts")]
    if not parts:
        return "0 of 0"
    k = sum(abs(p["bias_um"]) <= ERR_BAR_UM for p in parts)
    z = _q([abs(p["noise_um"]) / p["noise_std_um"] for p in parts if p["noise_std_um"] > 0], 50)
    return f"{k} of {len(parts)} (|z| med {z:.1f})"


def _target_passes(t: dict, err_bar_um: float = ERR_BAR_UM) -> bool:
    """The bar at one rig-target: true std <= STD_BAR x the oracle's and |true error| <= err_bar_um."""
    return t["std_um"] <= STD_BAR * t["oracle_std_um"] and abs(t["err_um"]) <= err_bar_um


def _rig_passes(run: dict) -> bool:
    return all(_target_passes(t) for t in run["targets"])


def data_err_bar_um(t: dict) -> float:
    """The mean bar at one rig-target judged by the data's accuracy (:data:`DATA_ERR_K`), µm."""
    sigma = float(t.get("f_noise_std_best_oracle_um", math.nan))
    return max(ERR_BAR_UM, DATA_ERR_K * sigma) if math.isfinite(sigma) else ERR_BAR_UM


def _rig_passes_data(run: dict) -> bool:
    """The rig bar with its mean half judged by :func:`data_err_bar_um` (the std half unchanged)."""
    return all(_target_passes(t, data_err_bar_um(t)) for t in run["targets"])


def data_bar_summary(runs: list[dict]) -> dict:
    """Counts for the bar of :data:`DATA_ERR_K` over ``runs``: rigs passing it, rig-targets whose
    mean bar it widens beyond 0.1 µm, and the median sigma* at the oracle's pose."""
    tg = [t for r in runs for t in r["targets"]]
    sig = [t.get("f_noise_std_best_oracle_um", math.nan) for t in tg]
    return {"rigs_data_pass": int(sum(_rig_passes_data(r) for r in runs)),
            "data_widened": int(sum(data_err_bar_um(t) > ERR_BAR_UM for t in tg)), "data_n": len(tg),
            "sigma_best_median_um": _q([x for x in sig if math.isfinite(x)], 50)}


def _dictionary_fit(afm: AnalyticForwardModel, data, model, var_true: np.ndarray) -> dict:
    """:func:`rig_audit.dictionary_fit` of the truth's variances at the training moves by the
    stage's candidate sources (as training evaluates them: on x and the move's context). A
    selected tilt (its direction fitted, not a candidate) is left out of the selected ones' fit,
    which then overstates their error."""
    Xc = data.context_inputs(afm.n_q)
    cands = candidate_features(afm, context=True).rescaled(Xc)
    chosen = (model.info.get("noise_selection") or {}).get("selected") or []
    cols = [cands.names.index(nm) for nm in chosen if nm in cands.names]  # the tilt is no candidate
    return rig_audit.dictionary_fit(var_true, cands.values(Xc), cols)


def _audit_summary(runs: list[dict]) -> dict:
    """The truth's evidence against the models at their training moves (scripts/rig_audit.py):
    its median over the rigs, and how many failing rigs had evidence at least one source's entry
    level (below it, their data could not be expected to show the model's error)."""
    ev = [r["audit"]["evidence_nats"] for r in runs if "audit" in r]
    failing = [r for r in runs if "audit" in r and not _rig_passes(r)]
    shown = sum(r["audit"]["evidence_nats"] >= r["audit"]["entry_nats"] for r in failing)
    fitted = [r for r in failing if "all_rel_rms" in r["audit"]]
    held = sum(r["audit"]["all_rel_rms"] <= DICT_FIT_REL for r in fitted)

    def missed(rs):  # the dictionary describes the truth, the selected sources do not
        return sum(r["audit"]["all_rel_rms"] <= DICT_FIT_REL < r["audit"]["selected_rel_rms"] for r in rs)

    # the same count over the passing rigs: its base rate (a passing controller needs the scatter
    # ranked at the poses it compares, not described at every training move)
    passing = [r for r in runs if "all_rel_rms" in r.get("audit", {}) and _rig_passes(r)]
    return {"evidence_median": _q(ev, 50), "fail_shown": f"{shown} of {len(failing)}",
            "fail_dict": f"{held} of {len(fitted)}", "fail_dict_missed": f"{missed(fitted)} of {len(fitted)}",
            "pass_dict_missed": f"{missed(passing)} of {len(passing)}"}


FAMILY_COLUMNS = (("family", "family", "{}"),) + RIG_COLUMNS + (
    ("verify_violations", "oracle beaten by a random pose", None),
    ("mc_std_dev_max", "max abs(MC std / exact std - 1)", "{:.3f}"),
    ("evidence_median", "evidence against the model at the training moves, median (nats)", "{:.1f}"),
    ("fail_shown", "failing rigs whose training data show the error", "{}"),
    ("controller_losses", "failing rig-targets where the model ranks the oracle's pose better", "{}"),
)


def family_table_markdown(table: list[dict]) -> list[str]:
    """The per-family summary as a Markdown table."""
    return _markdown_table("families", FAMILY_COLUMNS, table)


#: The rig bar beside the same bar with its mean half judged by the data's accuracy (:data:`DATA_ERR_K`).
DATA_BAR_COLUMNS = (
    ("family", "family", "{}"), ("n", "n (moves)", "{}"), ("method", "method", "{}"),
    ("rigs_pass", "rigs passing (issue 18's bar)", None), ("rigs_err_pass", "mean within 0.1 µm", None),
    ("rigs_data_pass", f"rigs passing, mean within max(0.1 µm, {DATA_ERR_K:g} sigma*)", None),
    ("data_widened", "rig-targets whose mean bar it widens", None),
    ("sigma_best_median_um", "sigma* at the oracle's pose, median (µm)", "{:.3f}"),
)


def data_bar_markdown(table: list[dict]) -> list[str]:
    """:data:`DATA_BAR_COLUMNS` as a Markdown table (rows of :func:`family_tables`)."""
    return _markdown_table("data_bar", DATA_BAR_COLUMNS, [t for t in table if "rigs_data_pass" in t])


def _fmt_fail(f: dict) -> str:
    return (f"{f['family']} rig {f['seed']} n={f['n']} {f['method']} t={f['target_um']:g}: {f['why']}; "
            f"err {f['err_um']:+.3f} µm, std {f['std_um']:.3f} vs oracle {f['oracle_std_um']:.3f} "
            f"({f['std_um'] / f['oracle_std_um']:.2f}x), AFM {f['afm_std_um']:.3f}; predicted std {f['pred_std_um']:.3f} "
            f"(noise {f['pred_noise_std_um']:.3f}, f {f['f_std_um']:.3f}); model's noise at the oracle pose "
            f"{f['pred_noise_std_oracle_um']:.3f} (f {f['f_std_oracle_um']:.3f}: "
            + ("the model ranks it better, the controller's loss" if controller_loss(f)
               else "the model ranks it no better, the model's loss")
            + f"); q_prev {f['q_prev_um']} q {f['q_um']} oracle q {f['oracle_q_um']}"
            + ("" if not f.get("audit") else
               f"; evidence against the model at the training moves {f['audit']['evidence_nats']:.1f} nats "
               f"(of it the mean {f['audit']['mean_part_nats']:.1f}; one source enters at "
               f"{f['audit']['entry_nats']:.1f})"
               + ("" if "all_rel_rms" not in f["audit"] else
                  f"; the truth's variance at the training moves fitted by every candidate source to "
                  f"{f['audit']['all_rel_rms']:.3f} rel. RMS, by the selected ones to "
                  f"{f['audit']['selected_rel_rms']:.3f}"))
            + ("" if not f.get("mean_parts") else
               f"; f's error {-f['err_um']:+.3f} µm = {f['mean_parts']['bias_um']:+.3f} with noise-free training "
               f"data + {f['mean_parts']['noise_um']:+.3f} from the training noise (its std under the truth "
               f"{f['mean_parts']['noise_std_um']:.3f}; the same form told the true variances "
               f"{f['mean_parts'].get('noise_std_best_um', math.nan):.3f})")
            + ("" if not f.get("floor_check") else
               f"; floor not an estimate: {finding_of(f['floor_check'])} (floor std "
               f"{f['floor_check']['floor_std_um']:.2g} µm, microctl.models.floor_check)"))


def print_families(table: list[dict], results: list[dict]) -> None:
    """The family table and every failing rig-target."""
    print("\nrig families: " + " ; ".join(f"{t['family']} n={t['n']} {t['method']}: {t['rigs_pass']}/{t['rigs']} pass "
                                         f"(std {t['rigs_std_pass']}, err {t['rigs_err_pass']}), ratio med "
                                         f"{t['ratio_median']:.2f} p90 {t['ratio_p90']:.2f} max {t['ratio_max']:.2f}, "
                                         f"|err| med {t['err_median_um']:.3f} max {t['err_max_um']:.3f}, calib "
                                         f"{t['cal_pass']}/{t['cal_n']}, oracle beaten {t['verify_violations']}/"
                                         f"{t['verify_n']}, evidence med {t['evidence_median']:.1f} nats, failing "
                                         f"rigs whose data show the error {t['fail_shown']}, whose true scatter "
                                         f"the dictionary describes {t['fail_dict']} (the selection not {t['fail_dict_missed']}; among passing "
                                         f"rigs {t['pass_dict_missed']}), failing targets the model ranked the oracle's pose "
                                         f"better at {t['controller_losses']}, mean failures within the bar with "
                                         f"noise-free training data {t['mean_draws']}; with the mean judged by "
                                         f"max({ERR_BAR_UM}, {DATA_ERR_K:g} sigma*) {t['rigs_data_pass']}/{t['rigs']} "
                                         f"pass ({t['data_widened']}/{t['data_n']} targets widened, sigma* med "
                                         f"{t['sigma_best_median_um']:.3f})"
                                         for t in table).replace(" ; ", "\n  "))
    fails = failing_targets(results)
    print(f"\nfailing rig-targets ({len(fails)}):")
    for f in fails:
        print("  " + _fmt_fail(f))


def families_markdown(table: list[dict], results: list[dict], header: str, wall_s: float,
                      sets: list[dict] | None = None, experiment: str | Path = MAIN_JOB) -> str:
    """The family run (and the main job over seed sets, when run) as Markdown (``--family ... --markdown FILE``)."""
    L = [header, ""]
    if sets:
        L += markdown([], sets, 0, "", 0.0, experiment).split("\n")[2:-2] + [""]
    L += ["### Rig families (scripts/rig_families.py)", "",
         f"Rigs passing = at every target true std <= {STD_BAR} x the oracle's AND |true error| <= {ERR_BAR_UM} µm; "
         f"{CAL_TEXT}. Targets {list(TARGETS_UM)} µm in sequence. "
         f"Oracle: grid search {FAMILY_ORACLE} over the redundant set on the family's exact truth; checked against "
         f"{VERIFY_POSES} random reaching poses per target (a violation = a random pose more than "
         f"{VERIFY_TOL:.0%} quieter in std). MC column: the chosen pose's std by 4000 draws of the simulator "
         "against the exact std. The last column splits the failing rig-targets: the controller's loss where the "
         "model's own expected squared error (f's variance plus the noise variance) at the oracle's pose is more than "
         f"{CONTROLLER_LOSS_MARGIN:.0%} below the chosen pose's, else the model's (it predicts the oracle's pose no "
         "better).", ""]
    L += family_table_markdown(table)
    L += ["", f"The same rigs with the mean half of the bar judged by the data's accuracy: |true error| <= "
          f"max({ERR_BAR_UM} µm, {DATA_ERR_K:g} sigma*), sigma* the std the training noise gives f's mean at the "
          "oracle's pose when f's form is told the readings' true variances (what a method that found the oracle's "
          "pose and weighed the readings right would still err by; scripts/bench_rigs.py, `DATA_ERR_K`). Reported "
          "beside issue 18's bar, not instead of it.", ""]
    L += data_bar_markdown(table)
    fails = failing_targets(results)
    L += ["", f"Failing rig-targets ({len(fails)}):", ""] + [f"- {_fmt_fail(f)}" for f in fails]
    L += ["", f"Wall time {wall_s:.0f} s.", ""]
    return "\n".join(L)


def seed_set_columns() -> list[str]:
    """Header of the seed-set table: the set, its seed offset, every bar, all bars, time."""
    from microctl.experiments.bars import BARS

    return ["set", "seed offset", *BARS, "all", "time (s)"]


def seed_sets_markdown(sets: list[dict]) -> list[str]:
    """The main job over seed sets as a Markdown table, a pass-count row and the failures."""
    from microctl.experiments.bars import BARS

    cols = seed_set_columns()
    L = ["<!-- table: seed_sets -->", "| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    for r in sets:
        cells = [str(r["set"]), str(r["offset"])]
        cells += [("yes" if r["bars"][b]["passed"] else "NO") if b in r["bars"] else "–" for b in BARS]
        cells += ["yes" if all(b["passed"] for b in r["bars"].values()) else "NO", f"{r['time_s']:.1f}"]
        L.append("| " + " | ".join(cells) + " |")
    n = len(sets)
    met = [f"{sum(r['bars'][b]['passed'] for r in sets if b in r['bars'])}/{sum(b in r['bars'] for r in sets)}"
           if any(b in r["bars"] for r in sets) else "–" for b in BARS]
    met_all = f"{sum(all(b['passed'] for b in r['bars'].values()) for r in sets)}/{n}"
    L.append("| met on | " + " | ".join(["", *met, met_all, ""]) + " |")
    fails = [f"- set {r['set']}: `{b}`: {d['detail']}" for r in sets for b, d in r["bars"].items() if not d["passed"]]
    if fails:
        L += ["", "Bars not met:", ""] + fails
    return L


def markdown(table: list[dict], sets: list[dict], n_rigs: int, header: str, wall_s: float,
             experiment: str | Path = MAIN_JOB) -> str:
    """Everything the run measured, as Markdown (``--markdown FILE``)."""
    L = [header, ""]
    if sets:
        exp = Path(experiment).resolve()
        root = Path(__file__).resolve().parents[1]
        shown = exp.relative_to(root) if exp.is_relative_to(root) else exp
        L += [f"### The main job over {len(sets)} seed sets", "",
              f"`{shown}` run with every seed shifted by {SEED_SET_STRIDE} k "
              "(k = 1..N, `microctl experiment --seed-offset`); each bar of docs/experiments.md evaluated "
              "(microctl/experiments/bars.py). Bar: every bar on >= 9 of 10 sets.", ""]
        L += seed_sets_markdown(sets) + [""]
    if table:
        L += [f"### Random rigs ({n_rigs})", "",
              f"Rigs passing = at every target true std <= {STD_BAR} x the oracle's AND |true error| <= "
              f"{ERR_BAR_UM} µm (bar: >= 90 % of rigs at n = 200); {CAL_TEXT} "
              f"(bar: >= 90 % of rig-targets). Targets {list(TARGETS_UM)} µm in sequence.", ""]
        L += rig_table_markdown(table) + [""]
    L += [f"Wall time {wall_s:.0f} s.", ""]
    return "\n".join(L)


def run_seed_set(k: int, experiment: str) -> dict:
    """The main job with every seed shifted by SEED_SET_STRIDE * k; its bars and timings."""
    from microctl.experiments.config import load_experiment_config
    from microctl.experiments.runner import run_experiment

    cfg = load_experiment_config(experiment).with_seed_offset(SEED_SET_STRIDE * k)
    # the controllers the bars judge (the sequence controllers are compared on the main job's
    # page, not barred; the sequence oracle is most of a run's time)
    judged = tuple(c for c in cfg.controllers if c in SEED_SET_CONTROLLERS)
    with tempfile.TemporaryDirectory() as tmp:
        res = run_experiment(replace(cfg, figures=False, controllers=judged), tmp, quiet=True)
    e = res["incremental"]["controllers"]["eafm"]
    return {"set": k, "offset": SEED_SET_STRIDE * k, "bars": res["bars"], "time_s": res["timings_s"]["total"],
            "vsse_eafm_over_oracle": res["incremental"]["ratios"].get("vsse_eafm_over_oracle"),
            "coverage": res["absolute"]["fraction_within_2sigma"], "eafm_msse_um": e["msse_um"]}


def print_seed_sets(sets: list[dict]) -> None:
    from microctl.experiments.bars import BARS

    print(f"\nmain job ({MAIN_JOB.name}) over {len(sets)} seed sets (offsets {SEED_SET_STRIDE} k): bars met per set")
    names = [b for b in BARS if any(b in r["bars"] for r in sets)]
    print(f"{'set':>4} " + " ".join(f"{n:>18}" for n in names) + f" {'all':>5} {'time s':>7}")
    for r in sets:
        print(f"{r['set']:>4} " + " ".join(f"{('yes' if r['bars'][n]['passed'] else 'NO'):>18}" for n in names)
              + f" {('yes' if all(b['passed'] for b in r['bars'].values()) else 'NO'):>5} {r['time_s']:>7.1f}")
    print(f"{'pass':>4} " + " ".join(f"{sum(r['bars'][n]['passed'] for r in sets):>15}/{len(sets):<2}" for n in names)
          + f" {sum(all(b['passed'] for b in r['bars'].values()) for r in sets):>3}/{len(sets)}")
    for r in sets:
        for n, b in r["bars"].items():
            if not b["passed"]:
                print(f"  set {r['set']}: {n}: {b['detail']}")


def each_done(fn, arg_lists: list[tuple], jobs: int):
    """``fn(*args)`` for each ``args`` of ``arg_lists``, in ``jobs`` worker processes when
    ``jobs > 1``; yields the results in that order, each as soon as it (and those before it) ended."""
    if jobs > 1:
        with ProcessPoolExecutor(jobs) as ex:
            futs = [ex.submit(fn, *a) for a in arg_lists]
            for fu in futs:
                yield fu.result()
    else:
        for a in arg_lists:
            yield fn(*a)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rigs", type=int, default=24)
    ap.add_argument("--sizes", default="125,200")
    ap.add_argument("--methods", default="paper,hgp,default")
    ap.add_argument("--seed", type=int, default=0, help="rig k uses seed + k")
    ap.add_argument("--jobs", type=int, default=1, help="worker processes (rigs in parallel)")
    ap.add_argument("--json", metavar="FILE", help="write every rig's results and the summary")
    ap.add_argument("--verbose", action="store_true", help="print every rig-target")
    ap.add_argument("--seed-sets", type=int, default=0, help="also run the main job over this many seed sets")
    ap.add_argument("--experiment", default=str(MAIN_JOB), help="experiment file for --seed-sets")
    ap.add_argument("--markdown", metavar="FILE", help="also write the tables as Markdown (docs/generated/)")
    ap.add_argument("--family", default=None,
                    help="rig families (scripts/rig_families.py), comma-separated or 'all': "
                         f"{', '.join(rig_families.FAMILIES)}; default: today's stick-slip rigs")
    args = ap.parse_args(argv)
    if args.family:
        return main_families(args)
    sizes = tuple(int(s) for s in args.sizes.split(","))
    methods = tuple(m.strip() for m in args.methods.split(","))
    unknown = [m for m in methods if m not in METHODS]
    if unknown:
        ap.error(f"unknown method(s) {unknown}; choose from {', '.join(METHODS)}")
    seeds = [args.seed + k for k in range(args.rigs)]
    header = (f"machine: {platform.machine()} {platform.processor() or ''} {os.cpu_count()} cpu, Python "
              f"{platform.python_version()}, numpy {np.__version__}; {args.rigs} rigs (seeds {args.seed}.."
              f"{args.seed + args.rigs - 1}), sizes {list(sizes)}, methods {list(methods)}, targets "
              f"{list(TARGETS_UM)} µm, {args.seed_sets} main-job seed sets, jobs {args.jobs}")
    print(header)
    t0 = time.perf_counter()
    sets: list[dict] = []
    if args.seed_sets:
        ks = list(range(1, args.seed_sets + 1))
        if args.jobs > 1:
            with ProcessPoolExecutor(args.jobs) as ex:
                sets = list(ex.map(run_seed_set, ks, [args.experiment] * len(ks)))
        else:
            sets = [run_seed_set(k, args.experiment) for k in ks]
        print_seed_sets(sets)
    results: list[dict] = []
    for res in each_done(run_rig, [(s, sizes, methods) for s in seeds], args.jobs):
        results.append(res)
        print(f"  rig {res['seed']} done", file=sys.stderr)
    if args.verbose and results:
        for res in results:
            print(f"\nrig {res['seed']}: friction {res['friction']}, gauge {res['gauge_um']:.3f} µm, "
                  f"preload {res['preload_n']:.0f} N, gains {np.round(res['gains'], 3).tolist()}")
            for r in res["runs"]:
                for t in r["targets"]:
                    bad = not _target_passes(t)
                    print(f"  n={r['n']:>3} {r['method']:>8} t={t['target_um']:>4g} err {t['err_um']:+.3f} "
                          f"std {t['std_um']:.3f} oracle {t['oracle_std_um']:.3f} "
                          f"({t['std_um'] / t['oracle_std_um']:.2f}x) AFM {t['afm_std_um']:.3f} "
                          f"pred {t['pred_std_um']:.3f} q {t['q_um']}{'  <-' if bad else ''}")
    table = summarise(results, sizes, methods) if results else []
    if results:
        print_table(table, len(seeds))
        print(f"\nredrawn rigs (a ball lifted off): {sum(r['redraws'] > 0 for r in results)}")
    wall = time.perf_counter() - t0
    print(f"wall time {wall:.0f} s")
    if args.markdown:
        Path(args.markdown).write_text(markdown(table, sets, len(seeds), header, wall, args.experiment))
    if args.json:
        Path(args.json).write_text(json.dumps({"summary": table, "rigs": results, "seed_sets": sets}, indent=1,
                                              default=float))
    return 0


def main_families(args) -> int:
    """``--family``: the rigs of each family, summarised per family."""
    sizes = tuple(int(x) for x in args.sizes.split(","))
    methods = tuple(m.strip() for m in args.methods.split(","))
    fams = rig_families.FAMILIES if args.family == "all" else tuple(f.strip() for f in args.family.split(","))
    bad = [m for m in methods if m not in METHODS] + [f for f in fams if f not in rig_families.FAMILIES]
    if bad:
        raise SystemExit(f"unknown method(s) or family(ies) {bad}")
    seeds = [args.seed + k for k in range(args.rigs)]
    header = (f"machine: {platform.machine()} {platform.processor() or ''} {os.cpu_count()} cpu, Python "
              f"{platform.python_version()}, numpy {np.__version__}; families {list(fams)}, {args.rigs} rigs each "
              f"(seeds {args.seed}..{args.seed + args.rigs - 1}), sizes {list(sizes)}, methods {list(methods)}, "
              f"targets {list(TARGETS_UM)} µm, {args.seed_sets} main-job seed sets, jobs {args.jobs}")
    print(header)
    t0 = time.perf_counter()
    sets: list[dict] = []
    if args.seed_sets:
        ks = list(range(1, args.seed_sets + 1))
        with ProcessPoolExecutor(max(args.jobs, 1)) as ex:
            sets = list(ex.map(run_seed_set, ks, [args.experiment] * len(ks)))
        print_seed_sets(sets)
    jobs = [(f, s) for f in fams for s in seeds]
    results: list[dict] = []
    for res in each_done(run_family_rig, [(f, s, sizes, methods) for f, s in jobs], args.jobs):
        results.append(res)
        print(f"  {res['family']} rig {res['seed']} done ({time.perf_counter() - t0:.0f} s)", file=sys.stderr)
        if args.json:  # partial results survive an interrupted run
            Path(args.json).write_text(json.dumps({"rigs": results}, indent=1, default=float))
    table = family_tables(results, fams, sizes, methods)
    print_families(table, results)
    wall = time.perf_counter() - t0
    print(f"wall time {wall:.0f} s")
    if args.markdown:
        Path(args.markdown).write_text(families_markdown(table, results, header, wall, sets, args.experiment))
    if args.json:
        Path(args.json).write_text(json.dumps({"summary": table, "rigs": results, "seed_sets": sets}, indent=1,
                                              default=float))
    return 0


if __name__ == "__main__":
    sys.exit(main())
