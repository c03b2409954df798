"""Statistics of the experiments (paper IV-B), results.json and report.md.

Incremental movement (IV-D): e_s = t_d − t_f per trial and target; MSSE (mean) and VSSE
(sample variance, ddof 1) per target and controller (Table II); the paper's Student
two-sample t-tests on the per-target |MSSE| and VSSE values of AFM vs EAFM; per target the
Brown–Forsythe test of equal SSE variances (robust to the heavy-tailed stick-slip scatter,
unlike the F-test; :mod:`microctl.util.stats`) and Welch's t-test on |e_s|.

Absolute movement (IV-C): PE = |t' − prediction| per move for AFM and EAFM (eq. of IV-B.1),
averaged over the trials per point; the paper's two-sample t-test plus the paired t-test and
Wilcoxon signed-rank test (the same moves are predicted by both models); the fraction of
measurements inside the EAFM's ±2σ band. On a simulated stage also the models' errors from the
true mean, and whether the EAFM's predicted bias uncertainty (f's std, eq. 1's epistemic part)
covers its own error from the true mean: the fraction of moves with |mean − true mean| <= 2 std
(95.4 % for a calibrated f) and the median of |mean − true mean| / std.
"""

from __future__ import annotations

import math
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from scipy.special import ndtr

import microctl.experiments.controllers as registry
from microctl.control.controller import returned_least_motion
from microctl.control.noise_summaries import R_E_SUMMARIES
from microctl.experiments.bars import evaluate_bars, incremental_ratios, within_2se
from microctl.experiments.config import ExperimentConfig
from microctl.models.floor_check import ADVICE, CONSEQUENCE, finding_of
from microctl.util import stats
from microctl.util.atomic import write_text_atomic
from microctl.util.io import to_jsonable, write_json

#: The paper's Table II (µm, µm²) at 7, 14, 21, 28 µm.
PAPER_TABLE_II = {
    "targets_um": [7.0, 14.0, 21.0, 28.0],
    "msse_um": {"afm": [1.2, 3.1, 3.0, 5.2], "eafm": [0.3, 0.7, 0.6, 0.9]},
    "vsse_um2": {"afm": [0.3, 3.1, 4.5, 8.0], "eafm": [0.14, 0.15, 0.5, 3.5]},
    "p_value": {"msse": 0.01, "vsse": 0.07, "absolute_pe": 1e-6},
}


def write_config(path: Path, cfg: ExperimentConfig) -> None:
    """``config.yaml``: the resolved experiment and the stage config (for reproduction)."""
    doc = {"experiment": cfg.to_dict(), "stage_config": cfg.stage_config.to_dict()}
    write_text_atomic(path, yaml.safe_dump(to_jsonable(doc), sort_keys=False))


def _test(fn, *args) -> dict | None:
    """A test's dict, or None when it is undefined (e.g. zero variance, too few values)."""
    try:
        with np.errstate(all="ignore"):
            r = fn(*args)
    except (ValueError, ZeroDivisionError, FloatingPointError):
        return None
    d = r.to_dict()
    return d if math.isfinite(d["p_value"]) else {**d, "p_value": None}


def _ratio(x: float, y: float) -> float | None:
    """x / y, or None when y is zero or either is not finite."""
    x, y = float(x), float(y)
    return x / y if y != 0 and math.isfinite(x) and math.isfinite(y) else None


def least_motion_trials(choice: Any) -> list[int] | None:
    """Per target, in how many trials the controller's least-motion rule returned the least motion
    instead of eq. 4's optimum (:func:`~microctl.control.controller.returned_least_motion`).

    Parameters
    ----------
    choice : list of list of str, shape (trials, targets), or None
        Each result's ``choice`` (empty for a controller without the rule).

    Returns
    -------
    list of int, length targets, or None
        None when no result has a choice (a controller without the rule, or a results file
        written before the choices were kept).
    """
    if not choice or not any(c for row in choice for c in row):
        return None
    return [sum(returned_least_motion(row[j]) for row in choice) for j in range(len(choice[0]))]


def incremental_stats(inc: dict) -> dict:
    """Table II and the tests from the incremental run (see the module docstring)."""
    targets = np.asarray(inc["targets_um"], dtype=float)
    ctrls: dict[str, Any] = {}
    sse: dict[str, np.ndarray] = {}
    for name, r in inc["controllers"].items():
        e = stats.steady_state_errors(targets[None, :], r["reached_um"])  # (trials, targets)
        sse[name] = e
        c = {
            "msse_um": stats.msse(e), "vsse_um2": stats.vsse(e), "msse_stderr_um": stats.msse_stderr(e),
            "sse_um": e, "reached_um": r["reached_um"], "predicted_um": r["predicted_um"],
            "predicted_std_um": r["predicted_std_um"], "q_um": r["q_um"],
            "solve_time_s": {"mean": float(np.nanmean(r["solve_time_s"])), "max": float(np.nanmax(r["solve_time_s"]))},
            "fallbacks_to_afm": int(r["fallbacks"]),
        }
        least = least_motion_trials(r.get("choice"))
        if least is not None:  # each result's choice (trials x targets) and the count per target
            c["choice"], c["least_motion_trials"] = r["choice"], least
        if np.any(np.isfinite(r["prob_quieter_than_afm"])):
            # P(noise at the chosen pose < at the AFM baseline's), per trial and target (the EAFM's posterior)
            c["prob_quieter_than_afm"] = r["prob_quieter_than_afm"]
            c["credibly_quieter_than_afm"] = int(np.nansum(r["credibly_quieter_than_afm"]))  # at credible_level
        if np.any(np.isfinite(r["true_mean_um"])):
            c["true_mean_um"] = r["true_mean_um"]
            c["true_std_um"] = r["true_std_um"]
            # the expected SSE of the commands actually sent (noise-free accuracy)
            c["expected_msse_um"] = np.mean(targets[None, :] - r["true_mean_um"], axis=0)
            c["expected_vsse_um2"] = np.mean(r["true_std_um"] ** 2, axis=0)
        ctrls[name] = c
    a, e = ctrls["afm"], ctrls["eafm"]
    t_msse = _test(stats.two_sample_t, np.abs(a["msse_um"]), np.abs(e["msse_um"]))
    t_vsse = _test(stats.two_sample_t, a["vsse_um2"], e["vsse_um2"])
    zero = within_2se(e["msse_um"], e["msse_stderr_um"])
    per_target = []
    for j, t in enumerate(targets):
        row: dict[str, Any] = {
            "target_um": float(t),
            "brown_forsythe_afm_vs_eafm": _test(stats.brown_forsythe, sse["afm"][:, j], sse["eafm"][:, j]),
            "welch_abs_sse_afm_vs_eafm": _test(lambda x, y: stats.two_sample_t(x, y, equal_var=False),
                                               np.abs(sse["afm"][:, j]), np.abs(sse["eafm"][:, j])),
            "eafm_msse_within_2se": bool(zero[j]),
            "eafm_msse_over_se": _ratio(e["msse_um"][j], e["msse_stderr_um"][j]),
        }
        if "oracle" in sse:
            row["brown_forsythe_oracle_vs_eafm"] = _test(stats.brown_forsythe, sse["oracle"][:, j], sse["eafm"][:, j])
        per_target.append(row)
    ratios = incremental_ratios(ctrls)
    return {
        "targets_um": targets.tolist(),
        "trials": int(inc["trials"]),
        "controllers": ctrls,
        "p_value": {"msse": None if t_msse is None else t_msse["p_value"],
                    "vsse": None if t_vsse is None else t_vsse["p_value"]},
        "tests": {"msse": t_msse, "vsse": t_vsse, "per_target": per_target,
                  "msse_note": "Student two-sample t-test on the per-target |MSSE| of AFM vs EAFM (the paper's); "
                               "p_value is two-sided, p_one_sided is for 'EAFM smaller'",
                  "vsse_note": "Student two-sample t-test on the per-target VSSE of AFM vs EAFM (the paper's)"},
        "ratios": ratios,
        "paper_table_ii": PAPER_TABLE_II,
    }


def mean_errors_vs_truth(true_mean_um: np.ndarray, afm_um: np.ndarray,
                         model_um: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each absolute point's mean error against the simulator's truth, for the AFM and a model.

    Parameters
    ----------
    true_mean_um, model_um : ndarray, shape (trials, points)
        The true mean of each move and the model's mean prediction (µm).
    afm_um : ndarray, shape (points,)
        The AFM's prediction (the same every trial).

    Returns
    -------
    err_afm, err_model : ndarray, shape (points,)
        The mean over the trials of |true mean - prediction|; the ``absolute_pe`` bar counts the
        points where ``err_model < err_afm``.
    """
    tm = np.asarray(true_mean_um, dtype=float)
    return (np.abs(tm - np.asarray(afm_um, dtype=float)[None, :]).mean(axis=0),
            np.abs(tm - np.asarray(model_um, dtype=float)).mean(axis=0))


#: Draws and seed of :func:`calibrated_below_afm` (fixed: the same results give the same count;
#: the standard error of a point's probability is <= 0.5 / sqrt(draws) = 0.008).
CALIBRATED_DRAWS, CALIBRATED_SEED = 4000, 20_261_202


def calibrated_below_afm(true_mean_um: np.ndarray, afm_um: np.ndarray, bias_std_um: np.ndarray) -> float:
    """How many points the ``absolute_pe`` bar could expect to count for a mean prediction whose
    errors from the true mean were exactly as wide as its predicted bias uncertainty says.

    Each move's error is drawn from N(0, bias_std^2) (independent), averaged over a point's
    trials as the bar averages them (:func:`mean_errors_vs_truth`), and compared with the AFM's
    error there; the count is the sum over the points of that probability (Monte Carlo with
    :data:`CALIBRATED_DRAWS` fixed draws). Below the bar's share, even a mean that states its
    uncertainty correctly could not be expected to pass: the bar asks for a smaller uncertainty
    of f than the model has (more data or a better-shaped mean). At or above it while the
    measured count is below, f understates its uncertainty. The bar itself is not changed by it.

    Parameters
    ----------
    true_mean_um, bias_std_um : ndarray, shape (trials, points)
    afm_um : ndarray, shape (points,)

    Returns
    -------
    float
        Expected number of points, in [0, points].
    """
    tm = np.asarray(true_mean_um, dtype=float)
    s = np.asarray(bias_std_um, dtype=float)
    err_afm = np.abs(tm - np.asarray(afm_um, dtype=float)[None, :]).mean(axis=0)
    z = np.random.default_rng(CALIBRATED_SEED).standard_normal((CALIBRATED_DRAWS,) + tm.shape)
    err = np.abs(z * s[None, :, :]).mean(axis=1)  # (draws, points)
    return float(np.mean(err < err_afm[None, :], axis=0).sum())


def absolute_stats(ab: dict) -> dict:
    """PE per point, the tests, and the 2σ coverage (see the module docstring)."""
    meas = ab["measured_um"]  # (trials, points)
    pe_afm_moves = np.abs(meas - ab["afm_um"][None, :])
    pe_eafm_moves = np.abs(meas - ab["eafm_mean_um"])
    pe_afm, pe_eafm = pe_afm_moves.mean(axis=0), pe_eafm_moves.mean(axis=0)
    out: dict[str, Any] = {
        "points": int(meas.shape[1]), "trials": int(meas.shape[0]),
        "pe_um": {"afm": pe_afm, "eafm": pe_eafm},
        "pe_per_move_um": {"afm": pe_afm_moves, "eafm": pe_eafm_moves},
        "mean_pe_um": {"afm": float(pe_afm.mean()), "eafm": float(pe_eafm.mean())},
        "eafm_below_afm_points": int(np.sum(pe_eafm < pe_afm)),
        "u": ab["u"], "measured_um": meas, "afm_um": ab["afm_um"],
        "eafm_mean_um": ab["eafm_mean_um"], "eafm_std_um": ab["eafm_std_um"],
        "fraction_within_2sigma": stats.fraction_within(meas, ab["eafm_mean_um"], ab["eafm_std_um"], 2.0),
        "fraction_within_1sigma": stats.fraction_within(meas, ab["eafm_mean_um"], ab["eafm_std_um"], 1.0),
    }
    bias = ab.get("eafm_bias_std_um")  # f's std per move (runs before it was recorded have none)
    if bias is not None:
        out["eafm_bias_std_um"] = bias
    t = _test(stats.two_sample_t, pe_afm, pe_eafm)
    out["p_value"] = None if t is None else t["p_value"]
    out["tests"] = {"two_sample_t": t, "paired_t": _test(stats.paired_t, pe_afm, pe_eafm),
                    "wilcoxon": _test(stats.wilcoxon_signed_rank, pe_afm, pe_eafm)}
    if np.any(np.isfinite(ab["true_mean_um"])):
        # noise-free accuracy of the two means (simulator truth): model error without the gauge/friction scatter
        tm = ab["true_mean_um"]
        err_afm, err_eafm = mean_errors_vs_truth(tm, ab["afm_um"], ab["eafm_mean_um"])
        # the PE a perfect model would have (the true mean's): how much of the measured PE is scatter
        pe_truth = np.abs(meas - tm).mean(axis=0)
        out["mean_error_vs_truth_um"] = {"afm": err_afm, "eafm": err_eafm,
                                         "eafm_below_afm_points": int(np.sum(err_eafm < err_afm)),
                                         "truth_pe_below_afm_points": int(np.sum(pe_truth < pe_afm))}
        out["true_std_um"] = ab["true_std_um"]
        # coverage expected under the truth: P(|t - mean| <= 2 std) for t ~ N(true mean, true std^2),
        # free of the sampling noise of a few dozen measurements (binomial sd ~3 % at 60)
        lo = (ab["eafm_mean_um"] - 2 * ab["eafm_std_um"] - tm) / ab["true_std_um"]
        hi = (ab["eafm_mean_um"] + 2 * ab["eafm_std_um"] - tm) / ab["true_std_um"]
        out["expected_fraction_within_2sigma"] = float(np.mean(ndtr(hi) - ndtr(lo)))
        out["tests"]["paired_t_mean_error_vs_truth"] = _test(stats.paired_t, err_afm, err_eafm)
        out["true_mean_um"] = tm
        if bias is not None:  # is the predicted uncertainty of the mean (f's std) its actual error's size?
            dev = np.abs(ab["eafm_mean_um"] - tm)
            out["bias_vs_truth"] = {"within_2sigma": float(np.mean(dev <= 2 * bias)),
                                    "median_error_over_std": float(np.median(dev / np.maximum(bias, 1e-12))),
                                    "calibrated_below_afm_points": calibrated_below_afm(tm, ab["afm_um"], bias)}
    return out


def build_results(cfg: ExperimentConfig, train_info: dict, absolute: dict | None, incremental: dict | None,
                  timings_s: dict, logs: dict) -> dict:
    """The content of results.json (field names per shared/spec/cli.md, plus more)."""
    res: dict[str, Any] = {
        "experiment": cfg.source,
        "stage": str(cfg.stage_path),
        "backend": "emulated serial" if cfg.emulate else cfg.stage_config.backend.kind,
        "common_random_numbers": cfg.stage_config.backend.kind == "simulated",
        "training": train_info,
        "timings_s": timings_s,
        "logs": logs,
        "model": "model.npz",
    }
    if cfg.simulated:
        sim = cfg.stage_config.backend.simulated
        res["rig"] = {"gauge_noise_std_um": sim.gauge_noise_std_um, "driver_accuracy_um": sim.driver_accuracy_um,
                      "effects": sim.effects.to_dict(), "physics": asdict(cfg.stage_config.stage.physics)}
    if incremental is not None:
        res["incremental"] = incremental_stats(incremental)
    if absolute is not None:
        res["absolute"] = absolute_stats(absolute)
    res = to_jsonable(res)
    res["bars"] = evaluate_bars(res)
    return res


def _f(x: Any, nd: int = 3) -> str:
    if x is None:
        return "–"
    x = float(x)
    if not math.isfinite(x):
        return "–"
    if x != 0 and (abs(x) < 10 ** -nd or abs(x) >= 1e5):
        return f"{x:.2e}"
    return f"{x:.{nd}f}"


def _cell(text: str) -> str:
    """Text for a Markdown table cell: a literal ``|`` (as in |MSSE|) would split the cell."""
    return str(text).replace("|", "\\|")


def _g(x: float, digits: int = 2) -> str:
    """A ratio with ``digits`` significant digits, no exponent for ordinary sizes."""
    x = float(x)
    if not math.isfinite(x):
        return "–"
    return f"{x:.{digits}g}" if 1e-4 <= abs(x) < 1e4 or x == 0 else f"{x:.1e}"


def _p(t: dict | None) -> str:
    if t is None or t.get("p_value") is None:
        return "– (undefined)"
    one = t.get("p_one_sided")
    return f"p = {_f(t['p_value'], 4)} (two-sided), {_f(one, 4)} (one-sided, {t['alternative']})"


def _accuracy_lines(inc: dict) -> list[str]:
    """Whether the EAFM's MSSE is distinguishable from zero (|MSSE| >= 2 SE), target by target,
    and the VSSE ratios (variances are positive estimates: their ratios are meaningful). No
    ratio over an MSSE that is statistically zero is printed."""
    T = inc["targets_um"]
    c = inc["controllers"]
    e = c["eafm"]
    zero = within_2se(e["msse_um"], e["msse_stderr_um"])
    per = ", ".join(f"{t:g} µm: {m:+.3f} ± {se:.3f} µm" for t, m, se in zip(T, e["msse_um"], e["msse_stderr_um"]))
    dist = [f"{t:g} µm" for t, z in zip(T, zero) if not z]
    same = [f"{t:g} µm" for t, z in zip(T, zero) if z]
    if not dist:
        verdict = f"not distinguishable from zero at any target (|MSSE| < 2 SE at {', '.join(same)})"
    elif not same:
        verdict = f"distinguishable from zero at every target (|MSSE| >= 2 SE at {', '.join(dist)})"
    else:
        verdict = (f"distinguishable from zero at {', '.join(dist)} (|MSSE| >= 2 SE), not at {', '.join(same)}")
    a = c["afm"]
    afm_se = ", ".join(f"{abs(m) / se:.0f}" if se > 0 else "–" for m, se in zip(a["msse_um"], a["msse_stderr_um"]))
    r = inc["ratios"]
    out = [f"Accuracy: the EAFM's MSSE (± its standard error, SE) is {verdict}; per target {per}. "
           f"The AFM's |MSSE| is {afm_se} SE from zero.", "",
           "Repeatability: AFM/EAFM VSSE " + ", ".join(_f(v, 1) for v in r["vsse_afm_over_eafm"])
           + ("; EAFM/oracle VSSE " + ", ".join(_f(v, 2) for v in r["vsse_eafm_over_oracle"])
              if "vsse_eafm_over_oracle" in r else "") + ".", ""]
    return out + _sequence_lines(c)


def _sequence_lines(c: dict) -> list[str]:
    """Greedy against sequence control (the paper's future work): the cumulative VSSE over the
    targets, measured and, on a simulated stage, expected under the simulator's true scatter
    (the VSSE of 10 trials is itself uncertain by about ±45 % (1σ), the expected one is not)."""
    pairs = [(g, s) for g, s in registry.sequence_pairs() if g in c and s in c]
    if not pairs:
        return []
    parts = []
    for g, s in pairs:
        line = (f"{registry.label(g)} {_f(sum(c[g]['vsse_um2']), 4)} µm², {registry.label(s)} "
                f"{_f(sum(c[s]['vsse_um2']), 4)} µm² measured")
        if "expected_vsse_um2" in c[g] and "expected_vsse_um2" in c[s]:
            eg, es = sum(c[g]["expected_vsse_um2"]), sum(c[s]["expected_vsse_um2"])
            line += (f"; expected under the simulator's truth {_f(eg, 4)} and {_f(es, 4)} µm² "
                     f"(sequence / greedy {_f(es / eg, 3) if eg > 0 else '–'})")
        parts.append(line)
    return ["Sequence control (one plan over the whole target list, re-planned after each move; "
            "docs/controller.md): cumulative VSSE over the targets, " + "; ".join(parts) + ".", ""]


def _scale_lines(results: dict, level: int = 3) -> list[str]:
    """How the rig's AFM errors compare in size with the paper's Table II, and whether its
    VSSE grows with the target as the paper's does (empty when the targets differ)."""
    inc = results["incremental"]
    T = [float(t) for t in inc["targets_um"]]
    if T != PAPER_TABLE_II["targets_um"]:
        return []
    c = inc["controllers"]
    P = PAPER_TABLE_II
    rows = [("AFM MSSE", c["afm"]["msse_um"], P["msse_um"]["afm"]),
            ("AFM VSSE", c["afm"]["vsse_um2"], P["vsse_um2"]["afm"]),
            ("EAFM VSSE", c["eafm"]["vsse_um2"], P["vsse_um2"]["eafm"])]
    L = [_h(level, "Scale against the paper"), "",
         "Measured value / the paper's Table II value, per target (1 = the paper's size):", "",
         "<!-- table: scale -->",
         "| quantity | " + " | ".join(f"{t:g} µm" for t in T) + " |", "|" + "---|" * (len(T) + 1)]
    for name, ours, paper in rows:
        L.append(f"| {name} / paper | " + " | ".join(_g(float(o) / p) for o, p in zip(ours, paper)) + " |")
    v = [float(x) for x in c["afm"]["vsse_um2"]]
    pv = P["vsse_um2"]["afm"]
    grows = all(b > a for a, b in zip(v, v[1:]))
    ratio = v[-1] / v[0] if v[0] > 0 else float("nan")
    rig = results.get("rig") or {}
    gauge = (f" The rig's gauge noise std is {rig['gauge_noise_std_um']:g} µm; the paper's gauge repeatability "
             "was ±1 µm." if "gauge_noise_std_um" in rig else "")
    L += ["", f"The AFM's VSSE {'grows' if grows else 'does not grow'} with the target here "
          f"({_f(v[0])} → {_f(v[-1])} µm², × {_f(ratio, 1)}); the paper's grows {pv[0]:g} → {pv[-1]:g} µm² "
          f"(× {pv[-1] / pv[0]:.0f}).{gauge}"]
    return L


def _h(level: int, text: str) -> str:
    return "#" * level + " " + text


def bars_section(results: dict, level: int = 2) -> list[str]:
    """The bars table (Markdown lines; empty when no bar could be decided).

    Parameters
    ----------
    results : dict
        The content of results.json.
    level : int
        Heading level of the section.
    """
    bars = results.get("bars") or {}
    if not bars:
        return []
    L = [_h(level, "Bars"), "", f"{sum(b['passed'] for b in bars.values())} of {len(bars)} met "
         "(definitions: docs/experiments.md, microctl/experiments/bars.py).", "",
         "<!-- table: bars -->", "| bar | met | detail |", "|---|---|---|"]
    L += [f"| {k} | {'yes' if b['passed'] else 'NO'} | {_cell(b['detail'])} |" for k, b in bars.items()]
    return L + [""]


def table_ii_lines(inc: dict) -> list[str]:
    """Table II analogue: MSSE, its SE and VSSE per controller and target, and the paper's rows."""
    T = inc["targets_um"]
    L = ["<!-- table: table_ii -->",
         "| metric | controller | " + " | ".join(f"{t:g} µm" for t in T) + " | unit |", "|" + "---|" * (len(T) + 3)]
    for metric, key, unit in (("MSSE", "msse_um", "µm"), ("SE of MSSE", "msse_stderr_um", "µm"),
                              ("VSSE", "vsse_um2", "µm²")):
        for name, c in inc["controllers"].items():
            L.append(f"| {metric} | {registry.label(name)} | "
                     + " | ".join(_f(v) for v in c[key]) + f" | {unit} |")
    if [float(t) for t in T] == PAPER_TABLE_II["targets_um"]:
        for metric, key, unit in (("MSSE", "msse_um", "µm"), ("VSSE", "vsse_um2", "µm²")):
            for name in ("afm", "eafm"):
                L.append(f"| {metric} (paper) | {registry.label(name)} | "
                         + " | ".join(_f(v, 2) for v in PAPER_TABLE_II[key][name]) + f" | {unit} |")
    return L


def least_motion_lines(inc: dict) -> list[str]:
    """Per controller with the least-motion rule, how often it returned the least motion (target by
    target): where its VSSE exceeds the oracle's, this says whether the rule or eq. 4's optimum chose."""
    L = []
    for name, c in inc["controllers"].items():
        least = c.get("least_motion_trials")
        if least is None:
            continue
        per = ", ".join(f"{t:g} µm: {k}" for t, k in zip(inc["targets_um"], least))
        L.append(f"{registry.label(name)} returned the least motion instead of eq. 4's optimum (not better by the "
                 f"least-motion rule's test, docs/controller.md) in this many of the {inc['trials']} trials per target: "
                 f"{per}.")
    return ([""] + L) if L else []


def incremental_section(results: dict, level: int = 2) -> list[str]:
    """The incremental experiment: Table II, accuracy against zero, scale against the paper, tests."""
    inc = results.get("incremental")
    if inc is None:
        return []
    T = inc["targets_um"]
    L = [_h(level, "Incremental movement (IV-D): Table II"), "",
         f"{inc['trials']} trials; targets reached in sequence from the zero state; e_s = t_d − t_f.", ""]
    L += table_ii_lines(inc) + [""]
    L += _accuracy_lines(inc)
    scale = _scale_lines(results, level + 1)
    L += scale + ([""] if scale else [])
    L += [_h(level + 1, "Tests"), "",
          f"- |MSSE|, AFM vs EAFM (the paper's Student two-sample t-test over the {len(T)} targets): "
          + _p(inc["tests"]["msse"]),
          f"- VSSE, AFM vs EAFM (the paper's Student two-sample t-test over the {len(T)} targets): "
          + _p(inc["tests"]["vsse"]), "",
          "Per target, the spread of the SSE is compared with the Brown–Forsythe test (Levene's test centred "
          "on the median). The paper's t-test on the four VSSE values asks whether the *average* variance "
          "differs across targets, with 3 + 3 degrees of freedom; whether one controller is more repeatable "
          f"at a given target is a test of equal variances on the {inc['trials']} + {inc['trials']} SSE "
          "values. The classical F-test for that is exact only for normal errors and badly anti-conservative "
          "otherwise; stick-slip scatter is heavy-tailed and mixes zero and large steps, so the robust "
          "Brown–Forsythe test is used.", "",
          "<!-- table: per_target_tests -->",
          "| target | B–F AFM vs EAFM p | Welch on abs(e_s) p | B–F oracle vs EAFM p | EAFM MSSE / SE | "
          "EAFM MSSE distinguishable from 0 |",
          "|---|---|---|---|---|---|"]
    for row in inc["tests"]["per_target"]:
        bf = row["brown_forsythe_afm_vs_eafm"]
        we = row["welch_abs_sse_afm_vs_eafm"]
        bo = row.get("brown_forsythe_oracle_vs_eafm")
        L.append(f"| {row['target_um']:g} µm | {_f(bf and bf['p_value'], 4)} | {_f(we and we['p_value'], 4)} | "
                 f"{_f(bo and bo['p_value'], 4)} | {_f(row.get('eafm_msse_over_se'), 2)} | "
                 f"{'no (within 2 SE)' if row['eafm_msse_within_2se'] else 'yes (beyond 2 SE)'} |")
    L += least_motion_lines(inc)
    fb = {n: c["fallbacks_to_afm"] for n, c in inc["controllers"].items() if c["fallbacks_to_afm"]}
    if fb:
        L += ["", f"Solver failures replaced by the AFM command: {fb}."]
    return L + [""]


def absolute_section(results: dict, level: int = 2) -> list[str]:
    """The absolute experiment: PE of both models, ±2σ coverage, the tests."""
    ab = results.get("absolute")
    if ab is None:
        return []
    L = [_h(level, "Absolute movement (IV-C)"), "",
         f"{ab['points']} control signals covering the workspace, each from the zero state "
         f"(u0, u1, u0, u2, …), {ab['trials']} trials; PE = |t' − prediction| averaged over the trials.", "",
         f"- mean PE: AFM {_f(ab['mean_pe_um']['afm'])} µm, EAFM {_f(ab['mean_pe_um']['eafm'])} µm; "
         f"EAFM below AFM at {ab['eafm_below_afm_points']} of {ab['points']} points",
         f"- measurements inside the EAFM's ±2σ band: {100 * ab['fraction_within_2sigma']:.1f} % "
         f"(±1σ: {100 * ab['fraction_within_1sigma']:.1f} %)"
         + (f"; expected under the simulator's true mean and scatter: "
            f"{100 * ab['expected_fraction_within_2sigma']:.1f} % (95.4 % for a calibrated prediction)"
            if "expected_fraction_within_2sigma" in ab else ""),
         "- two-sample t-test (the paper's): " + _p(ab["tests"]["two_sample_t"]),
         "- paired t-test: " + _p(ab["tests"]["paired_t"]),
         "- Wilcoxon signed-rank test: " + _p(ab["tests"]["wilcoxon"])]
    if "mean_error_vs_truth_um" in ab:
        mt = ab["mean_error_vs_truth_um"]
        L.append(f"- against the simulator's noise-free mean: mean error AFM {_f(np.mean(mt['afm']))} µm, EAFM "
                 f"{_f(np.mean(mt['eafm']))} µm; EAFM below AFM at {mt['eafm_below_afm_points']} of "
                 f"{ab['points']} points")
    if "bias_vs_truth" in ab:
        bt = ab["bias_vs_truth"]
        L.append(f"- the EAFM's predicted bias uncertainty (f's std) against its error from the true mean: "
                 f"the true mean inside the ±2 std band at {100 * bt['within_2sigma']:.1f} % of the moves "
                 f"(95.4 % for a calibrated f), median error / std {_g(bt['median_error_over_std'])} "
                 f"(0.67 for a calibrated f)"
                 + (f"; a mean whose errors were as wide as that std says would be nearer the true mean than "
                    f"the AFM's at {bt['calibrated_below_afm_points']:.1f} of {ab['points']} points (expected)"
                    if "calibrated_below_afm_points" in bt else ""))
    return L + [""]


def report_markdown(cfg: ExperimentConfig, results: dict) -> str:
    """report.md: the bars, Table II, the tests, the absolute experiment, timings and notes."""
    L: list[str] = [f"# Experiment report: {Path(cfg.source).name}", ""]
    tr = cfg.training
    L.append(f"Stage config: `{cfg.stage_path}` (backend: {results['backend']}). "
             f"Training: design `{tr.design}`, {results['training']['rows']} moves "
             f"({tr.moves} designed + {tr.refine_rounds} refinement rounds, strategy `{tr.refine_strategy}`), "
             f"noise model `{tr.noise_model}`, linear trend {'on' if tr.linear_trend else 'off'}, "
             f"{tr.restarts} VHGPR restarts; controller r_e = `{cfg.controller.r_e}`"
             + (f" (kappa {cfg.controller.kappa:g})" if R_E_SUMMARIES[cfg.controller.r_e].uses_kappa else "") + "."
             + (f" Seeds offset by {cfg.seed_offset} from the file's." if cfg.seed_offset else ""))
    L.append("")
    floor = ((results.get("training") or {}).get("rounds") or [{}])[-1].get("floor_check")
    if floor:  # microctl.models.floor_check, as `microctl train` warns
        finding = finding_of(floor)
        L += [f"**Warning: the final model's noise floor is not an estimate.** In the final model {finding} (floor "
              f"std {floor['floor_std_um']:.3g} µm; results.json, training.rounds[-1].floor_check): {CONSEQUENCE}, "
              f"and so can the EAFM's choices and bands. {ADVICE} and run again.", ""]
    L += bars_section(results)
    if results["common_random_numbers"]:
        L.append("Common random numbers: every trial k of every controller ran on a fresh simulated stage "
                 "seeded identically (incremental seed "
                 f"{cfg.seeds.incremental_stage} + k), so all controllers met the same noise draws move by move; "
                 "differences between controllers come from the controllers.")
    else:
        L.append("The stage could not be reseeded (serial backend): one stage served the whole run, so the "
                 "controllers met different noise.")
    L.append("")
    L += incremental_section(results)
    L += absolute_section(results)
    tm = results["timings_s"]
    L += ["## Timings", "", ", ".join(f"{k}: {v:.1f} s" for k, v in tm.items()), ""]
    if results.get("figures"):
        L += ["## Figures", ""] + [f"![{f}]({f})" for f in results["figures"]] + [""]
    L += ["Logs (one row per move, written as it completed): "
          + ", ".join(f"`{v}`" for v in results["logs"].values()) + "; model: `model.npz`; "
          "resolved configs: `config.yaml`.", ""]
    return "\n".join(L)


def write_outputs(out: Path, cfg: ExperimentConfig, results: dict) -> None:
    """Write results.json and report.md into ``out``."""
    write_json(Path(out) / "results.json", results)
    write_text_atomic(Path(out) / "report.md", report_markdown(cfg, results))
