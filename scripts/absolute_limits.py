"""What limits the EAFM's absolute-movement accuracy on a simulated rig: scatter, moves or model?

The absolute bar (docs/experiments.md, ``absolute_pe``) asks the EAFM's mean prediction to be
nearer the simulator's true mean than the AFM's at >= 90 % of the experiment's points. When it
is missed, four things may be at fault: the noise model's weighting of the readings, their
scatter (the actuators' stick-slip on top of the gauge noise), the training moves (where they
put the data), or the mean correction's model class (f: a linear trend plus an SE-ARD GP in
x = [s; u], eq. 3). This script separates them by training the experiment's own residual model
again, with the experiment's settings, on four data sets (and re-weighting one of them with the
truth's noise), and scoring each mean prediction against the truth at the experiment's absolute
points (each from the zero state, IV-C):

``logged``
    The run's training log as measured, fitted with the seed of the run's last fit: the run's
    EAFM again (its count is the run's ``absolute_pe`` count unless the refit differs).
``zero_state``
    The ``logged`` model read from the exact zero state instead of each trial's recorded state:
    f reads the state's pose as the previous *reading* (x = [s; u], eq. 3), which after the
    return to zero carries that move's scatter; the difference to ``logged`` is what that costs.
``told_noise``
    The ``logged`` fit's f (its hyperparameters) with the truth's noise variance of each
    training reading in place of the learned ``exp(g)``: the weighting a perfect noise model
    would give, with the fit's own kernel, so a count here near ``logged``'s says the noise model
    is not the limit.
``gauge``
    The same moves; each reading replaced by the true mean plus the gauge's noise alone
    (``gauge_noise_std_um``): the actuators' scatter removed.
``exact``
    The same moves; readings = true mean plus ``--exact-noise`` times the gauge's std (the
    VHGPR needs some noise): what the moves and f's model class allow.
``covering``
    A fresh ``covering`` design (:mod:`microctl.measurement.design`) of as many moves as the
    log, readings as in ``exact``: the same model class with moves spread over the workspace
    instead of the refinement rounds' moves.

Every reference but ``zero_state`` is read, like the run's EAFM, from the state each trial
recorded before the point (absolute_log.csv), and its error is the mean over the trials of
|prediction - true mean|, as the experiment's report computes it. Each reference is printed as:
points nearer the truth than the AFM, the median and largest |error| (µm), and the share of
moves (every trial's) whose true mean lies within twice f's predicted std (95.4 % for a
calibrated f: is the predicted bias uncertainty its error's size?). Beside them it prints the
AFM's smallest errors at the points: a point where the AFM is right by chance to a few
hundredths of a µm is one that no model learned from noisy readings can be expected to beat,
whatever its accuracy elsewhere.

Usage::

    microctl experiment configs/experiments/paper_scale.yaml --out runs/paper_scale
    python scripts/absolute_limits.py runs/paper_scale [more run folders ...]

Only simulated stages (``backend.kind: simulated``) have a truth to score against.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

import numpy as np
import scipy.linalg as sla

from microctl.backends.simulated import SimulatedStage
from microctl.errors import ConfigError
from microctl.experiments.config import parse_experiment_config
from microctl.experiments.report import mean_errors_vs_truth
from microctl.measurement.design import training_moves
from microctl.measurement.log import read_log
from microctl.models.afm import AnalyticForwardModel
from microctl.models.eafm import EAFM
from microctl.models.training import ResidualData, residual_dataset, train_residual_model
from microctl.stage.config import load_yaml

__all__ = ["REFERENCES", "nearer_than_afm", "true_means", "truth_readings", "with_noise_variances", "run_references", "main"]

#: The data sets the residual model is trained on (module docstring), in the order printed.
REFERENCES = ("logged", "zero_state", "told_noise", "gauge", "exact", "covering")

#: Default noise of the ``exact`` and ``covering`` readings, as a fraction of the gauge's std.
EXACT_NOISE_FRACTION = 0.1


def nearer_than_afm(pred_um: np.ndarray, truth_um: np.ndarray, afm_um: np.ndarray) -> dict:
    """How a mean prediction compares with the AFM's against the truth, point by point.

    As the experiment's report does (:func:`microctl.experiments.report.mean_errors_vs_truth`):
    each error is the mean over the trials of |prediction - true mean|.

    Parameters
    ----------
    pred_um, truth_um : ndarray, shape (n,) or (trials, n)
        The model's mean prediction and the true mean at n points (µm), per trial.
    afm_um : ndarray, shape (n,)
        The AFM's prediction (the same every trial).

    Returns
    -------
    dict
        ``nearer`` (points where the model's error is below the AFM's), ``points``, ``median_um``
        and ``max_um`` of the model's error.
    """
    err_afm, err = mean_errors_vs_truth(np.atleast_2d(truth_um), afm_um, np.atleast_2d(pred_um))
    return {"nearer": int(np.sum(err < err_afm)), "points": int(err.size),
            "median_um": float(np.median(err)), "max_um": float(np.max(err))}


def true_means(stage, s_prev: np.ndarray, moves: np.ndarray) -> np.ndarray:
    """The truth's mean reading of each move from its state (readings are drawn around it).

    Parameters
    ----------
    stage : SimulatedStage
        Gives ``true_mean(s, u)``.
    s_prev : ndarray, shape (n, n_s)
        The state before each move ([t_prev, q_prev]).
    moves : ndarray, shape (n, n_p)

    Returns
    -------
    ndarray, shape (n,)
    """
    return np.array([stage.true_mean(s, u) for s, u in zip(s_prev, moves)])


def truth_readings(mean_um: np.ndarray, noise_std_um: float, rng: np.random.Generator) -> np.ndarray:
    """Readings drawn around the truth's means (:func:`true_means`): mean + N(0, std²), shape (n,)."""
    mean = np.asarray(mean_um, dtype=float)
    return mean + noise_std_um * rng.standard_normal(mean.size)


def _run_config(path: Path):
    """The experiment a run folder's ``config.yaml`` records (its seeds already offset)."""
    raw = load_yaml(path)
    if not isinstance(raw, dict) or not isinstance(raw.get("experiment"), dict):
        raise ConfigError(f"{path}: no 'experiment' section (a config.yaml written by `microctl experiment`)")
    section = {k: v for k, v in raw["experiment"].items() if k != "seed_offset"}
    return parse_experiment_config(section, str(path), path.parent)


def _covering_run(stage, afm: AnalyticForwardModel, moves: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The states a run of ``moves`` from the zero state passes through on the truth's mean, and
    that mean reading of each move: shapes (n, n_s) and (n,)."""
    s = np.zeros(afm.n_s)
    states, means = np.zeros((len(moves), afm.n_s)), np.zeros(len(moves))
    for k, u in enumerate(moves):
        states[k] = s
        means[k] = stage.true_mean(s, u)
        s = np.concatenate([[means[k]], afm.K @ u])
    return states, means


def with_noise_variances(model, var_um2: np.ndarray):
    """``model`` with f's posterior recomputed for given noise variances of its training rows.

    f's kernel, hyperparameters and training targets are kept; ``R = diag(var / y_scale²)``
    replaces the VHGPR's ``diag(exp(mu - Sigma / 2))`` (:mod:`microctl.gp.bound`), so the mean
    becomes ``k^T (K_f + R)^-1 ys``. Exact posterior form only.

    Parameters
    ----------
    model : FittedVHGPR
    var_um2 : ndarray, shape (n,)
        Noise variance of each of the model's training rows (``model.X``'s order), µm².

    Returns
    -------
    FittedVHGPR
    """
    if model.posterior_form != "exact":
        raise ConfigError(f"the noise variances can be replaced only in an exact posterior, not a "
                          f"{model.posterior_form} one")
    K = model.f_kernel.matrix(model.X, model.X)
    ys = model.f_chol @ (model.f_chol.T @ model.f_alpha)  # f_alpha = (K_f + R)^-1 ys
    L = np.linalg.cholesky(K + np.diag(np.asarray(var_um2, float) / model.y_scale**2))
    return dataclasses.replace(model, f_chol=L, f_alpha=sla.cho_solve((L, True), ys))


def _true_variances(stage, afm, model) -> np.ndarray:
    """The truth's noise variance at each of ``model``'s training rows (µm²)."""
    X = model.X * model.x_scale + model.x_mean
    return np.array([stage.true_var(x[:afm.n_s], x[afm.n_s:afm.n_s + afm.n_p]) for x in X])


def _absolute_states(run_dir: Path, stage, trials: int, points: int) -> np.ndarray:
    """The state before each absolute point's move, per trial, from absolute_log.csv: the zero
    pose's reading (t_prev, with the return move's scatter) and commands; shape (trials, points, n_s)."""
    log = read_log(run_dir / "absolute_log.csv", stage)
    point = np.asarray(log.extra["point"], float)
    trial = np.asarray(log.extra["trial"], float)
    S = np.full((trials, points, log.s_prev.shape[1]), np.nan)
    rows = point >= 0
    S[trial[rows].astype(int), point[rows].astype(int)] = log.s_prev[rows]
    if np.isnan(S).any():
        raise ConfigError(f"{run_dir / 'absolute_log.csv'}: not every (trial, point) of results.json has a row")
    return S


def _score(afm, model, U: np.ndarray, truth: np.ndarray, states: np.ndarray) -> dict:
    """The model's mean prediction at each point from each trial's state, against the truth."""
    eafm = EAFM(afm, model)
    preds = [[eafm.predict(s, u) for s, u in zip(states_k, U)] for states_k in states]
    pred = np.array([[float(p.t_mean[0]) for p in row] for row in preds])
    f_std = np.sqrt(np.maximum([[float(p.f_var[0]) for p in row] for row in preds], 0.0))
    out = nearer_than_afm(pred, truth, np.asarray(afm.t_of(U), float))
    # is f's own uncertainty the size of its error? (95.4 % for a calibrated f; all trials' moves)
    out["within_2_f_std"] = float(np.mean(np.abs(pred - truth) <= 2.0 * f_std))
    out["selected"] = list((model.info.get("noise_selection") or {}).get("selected") or [])
    return out


def run_references(run_dir: Path, *, exact_fraction: float = EXACT_NOISE_FRACTION, seed: int = 0) -> dict:
    """Train the run's residual model on each of :data:`REFERENCES` and score it (module docstring).

    Parameters
    ----------
    run_dir : Path
        A ``microctl experiment`` output folder (results.json, config.yaml, training_log.csv).
    exact_fraction : float
        Noise of the ``exact`` and ``covering`` readings, as a fraction of the gauge's std.
    seed : int
        Seed of the replacement readings' noise.

    Returns
    -------
    dict
        ``references`` (name -> :func:`nearer_than_afm`'s dict plus ``selected`` and
        ``within_2_f_std``, the share of the moves (every trial's) whose true mean is within twice
        f's std),
        ``afm_smallest_um`` (the AFM's four smallest errors at the points), ``rows``.
    """
    results = json.loads((run_dir / "results.json").read_text())
    cfg = _run_config(run_dir / "config.yaml")
    stage_cfg = cfg.stage_config
    if stage_cfg.backend.kind != "simulated":
        raise ConfigError(f"{run_dir / 'config.yaml'}: experiment.stage: backend.kind is "
                          f"'{stage_cfg.backend.kind}'; only a simulated stage has a truth to score against")
    afm = AnalyticForwardModel(stage_cfg.stage)
    stage = SimulatedStage(stage_cfg, seed=cfg.seeds.training_stage)
    gauge = float(stage_cfg.backend.simulated.gauge_noise_std_um)
    ab = results["absolute"]
    U = np.asarray(ab["u"], float)
    truth = np.asarray(ab["true_mean_um"], float)  # (trials, points)
    states = _absolute_states(run_dir, stage_cfg.stage, *truth.shape)
    log = read_log(run_dir / "training_log.csv", stage_cfg.stage)
    data = residual_dataset(log, afm)
    t_afm = np.asarray(log.t, float).ravel() - data.y  # the AFM's reading of each logged move
    # the seed of the run's last fit (microctl.experiments.runner: the fit of round r uses gp + r)
    settings = cfg.training.model_settings(seed=cfg.seeds.gp + cfg.training.refine_rounds)
    rng = np.random.default_rng(seed)
    small = exact_fraction * gauge
    s_prev, moves = data.X[:, :afm.n_s], data.X[:, afm.n_s:]
    cov_moves = training_moves(afm, "covering", len(data.y), cfg.seeds.design)
    cov_states, cov_mean = _covering_run(stage, afm, cov_moves)
    cov_X = np.hstack([cov_states, cov_moves])
    cov_y = truth_readings(cov_mean, small, rng) - np.asarray(afm.t_of(cov_moves), float).ravel()
    mean = true_means(stage, s_prev, moves)  # once for both readings of the logged moves
    sets = {
        "logged": data,
        "gauge": dataclasses.replace(data, y=truth_readings(mean, gauge, rng) - t_afm),
        "exact": dataclasses.replace(data, y=truth_readings(mean, small, rng) - t_afm),
        "covering": ResidualData(X=cov_X, y=cov_y, x_names=data.x_names),
    }
    models = {name: train_residual_model(d, afm, settings) for name, d in sets.items()}
    models["told_noise"] = with_noise_variances(models["logged"], _true_variances(stage, afm, models["logged"]))
    refs = {name: _score(afm, models[name], U, truth, states) for name in models}
    # the logged model read at the noise-free zero state: what the previous reading's scatter costs
    refs["zero_state"] = _score(afm, models["logged"], U, truth, np.zeros_like(states))
    smallest = np.sort(np.abs(np.asarray(afm.t_of(U), float)[None, :] - truth).mean(axis=0))[:4]
    return {"references": refs, "afm_smallest_um": smallest.tolist(), "rows": int(len(data.y))}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", nargs="+", type=Path, help="microctl experiment output folders")
    ap.add_argument("--exact-noise", type=float, default=EXACT_NOISE_FRACTION,
                    help="noise of the exact and covering readings, as a fraction of the gauge's std "
                         f"(default {EXACT_NOISE_FRACTION})")
    ap.add_argument("--seed", type=int, default=0, help="seed of the replacement readings' noise")
    ap.add_argument("--json", type=Path, help="also write the results here")
    args = ap.parse_args(argv)
    if not args.exact_noise > 0:
        ap.error(f"--exact-noise must be > 0 (the VHGPR needs some noise), got {args.exact_noise}")
    for run in args.runs:
        if not (run / "results.json").is_file():
            ap.error(f"{run}: no results.json (a folder written by `microctl experiment --out`)")
    print("| run | rows | " + " | ".join(f"{r}: nearer / median / max (µm) / within 2 f std" for r in REFERENCES)
          + " | AFM's smallest errors (µm) |")
    print("|---|---|" + "---|" * len(REFERENCES) + "---|")
    out = {}
    for run in args.runs:
        t0 = time.perf_counter()
        res = run_references(run, exact_fraction=args.exact_noise, seed=args.seed)
        out[str(run)] = res
        cells = [f"{v['nearer']}/{v['points']} / {v['median_um']:.3f} / {v['max_um']:.2f} / {v['within_2_f_std']:.0%}"
                 for v in (res["references"][r] for r in REFERENCES)]
        print(f"| {run} | {res['rows']} | " + " | ".join(cells) + " | "
              + ", ".join(f"{e:.3f}" for e in res["afm_smallest_um"]) + " |", flush=True)
        print(f"  ({time.perf_counter() - t0:.0f} s; selected: "
              + "; ".join(f"{r} {res['references'][r]['selected']}" for r in REFERENCES) + ")",
              file=sys.stderr, flush=True)
    if args.json:
        args.json.write_text(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
