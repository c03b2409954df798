"""report.json / report.md / extended.yaml of a diagnosis, and what separates equivalent causes."""

from __future__ import annotations

from pathlib import Path

from microctl.diagnosis.selection import cause_label
from microctl.util.atomic import write_text_atomic
from microctl.util.io import to_jsonable, write_json

#: Extra measurement that tells apart causes a single scalar gauge cannot (docs/diagnosis.md).
SEPARATING_MEASUREMENT = {
    frozenset({"tool_offset", "contact_offset"}): (
        "a second gauge at another tool point: a tool offset moves only the measured point, a "
        "contact offset tilts the whole platform, so the two gauges disagree"
    ),
    frozenset({"contact_offset"}): (
        "the full platform pose (three gauges, or one gauge moved to two more tool points): a contact "
        "offset at ball i rotates the platform along pinv(K) e_i, a different direction for every ball"
    ),
    frozenset({"actuator_gain", "sensor_scale"}): (
        "a second tool point (a gain error tilts the platform, a scale error does not) or a pure z move"
    ),
    frozenset({"backlash", "drift"}): "a dwell: holding a pose, drift keeps moving the reading, backlash does not",
    frozenset({"backlash", "hysteresis"}): (
        "incremental moves with reversals of several lengths on the suspected actuator: a backlash switches "
        "fully on any reversal, a hysteresis loop only part-way on reversals shorter than twice its range"
    ),
    frozenset({"contact_loss", "actuator_gain"}): (
        "moves that load and unload the suspected ball (a kink only appears where it lifts off)"
    ),
}

_DEFAULT_SEPARATION = (
    "more moves over a larger part of the workspace, incremental moves in both directions, or a dwell "
    "(whichever the two causes predict differently)"
)


def separating_measurement(a: str, b: str) -> str:
    """The measurement that would separate cause ``a`` from cause ``b`` (plain text)."""
    return SEPARATING_MEASUREMENT.get(frozenset({a, b}), _DEFAULT_SEPARATION)


def add_identifiability(report: dict) -> None:
    """Add ``identifiability`` (per accepted cause: its class and the separating measurement)."""
    out = []
    for e in report["mean_causes"]:
        if not e.get("accepted") or not e.get("equivalent"):
            continue
        names = sorted({q["cause"] for q in e["equivalent"]} | {e["cause"]})
        seps = sorted({separating_measurement(e["cause"], q["cause"]) for q in e["equivalent"]})
        out.append({
            "cause": e["cause"],
            "key": cause_label(e),
            "params": e["params"],
            "class": [cause_label(e)] + [cause_label(q) for q in e["equivalent"]],
            "causes": names,
            "why": ("with one scalar gauge these causes predict the same readings within the noise "
                    "(same likelihood within 2Δℓ < 6)"),
            "separate_by": seps,
            "carried_in_extended_yaml": cause_label(e),
            "chosen": e.get("chosen"),
            "recommended_runs": [r for r in report.get("separation", []) if r["cause"] == cause_label(e)],
        })
    report["identifiability"] = out


def _num(x, fmt: str) -> str:
    return "—" if x is None else format(x, fmt)


def _fmt_params(e: dict) -> str:
    parts = []
    for k, v in e.get("params", {}).items():
        if k == "actuator":
            continue
        se = e.get("stderr", {}).get(k)
        parts.append(f"{k} = {v:.5g}" + (f" ± {se:.2g}" if isinstance(se, (int, float)) else ""))
    for k, v in (e.get("nuisance") or {}).items():
        parts.append(f"{k} = {v:.4g} (nuisance)")
    return ", ".join(parts) if parts else "—"


def accepted_labels(report: dict, kind: str = "mean") -> list[str]:
    """Accepted causes with their actuators, in acceptance order (``unexplained`` included)."""
    entries = report["mean_causes"] if kind == "mean" else report["noise_causes"]
    acc = [cause_label(e) for e in entries if e.get("accepted")]
    order = report["accepted"][kind]
    # keep the acceptance order of ``accepted`` (entries are ranked; the names repeat per actuator)
    out, pool = [], list(acc)
    for name in order:
        hit = next((x for x in pool if x == name or x.startswith(name + "[")), name)
        out.append(hit)
        if hit in pool:
            pool.remove(hit)
    return out


def gauge_zero_note(report: dict) -> str:
    """One sentence on the gauge-zero offset the "configured model" RMSE is taken after."""
    nz = report["nuisance"]
    return (f"after its one fitted constant, the gauge-zero offset {nz['gauge_zero_um']:.3g} ± "
            f"{nz['stderr']['gauge_zero_um']:.2g} µm (readings are relative to one noisy gauge reading at the zero "
            "state: a nuisance of the data, not a cause, not written to extended.yaml)")


def noise_line(report: dict) -> str:
    """The noise level and the dominant noise cause, one line."""
    d, ns = report["discrepancy"], report.get("noise_summary", {})
    dom = ns.get("dominant", "homoscedastic")
    share = ns.get("variance_share", {}).get(dom)
    extra = f"; dominant noise cause {dom}" + (f" ({100 * share:.0f} % of the mean variance)" if share is not None else "")
    return f"noise: base std {d['noise_std_um']:.3g} µm{extra}"


def outlier_line(report: dict) -> str:
    """Outlying rows, one line."""
    o = report.get("outliers", {})
    rows = o.get("rows", [])
    if not rows:
        return "outlying rows: none"
    parts = []
    for r in rows:
        where = f"line {r['line']}" if r.get("line") is not None else f"row {r['index']}"
        parts.append(f"{where} (seq {r['seq']}, {'/'.join(r['columns'])})")
    return f"outlying rows (left out of every fit): {', '.join(parts)}"


def summary_lines(report: dict) -> list[str]:
    """The command's printed summary."""
    d = report["discrepancy"]
    L = [f"rows {report['rows']}  AFM RMSE {d['afm_rmse_um']:.4g} µm  {noise_line(report)}  "
         f"significant {'yes' if d['significant'] else 'no'} (p = {d['p_value']:.3g})",
         f"configured model RMSE {d['model_rmse_um']:.4g} µm, {gauge_zero_note(report)}",
         outlier_line(report),
         f"accepted mean causes: {', '.join(accepted_labels(report, 'mean')) or 'none'};  "
         f"noise: {', '.join(accepted_labels(report, 'noise'))}"]
    wd = [cause_label(e) for e in report["mean_causes"] if e.get("withdrawn")]
    if wd:
        L.append(f"withdrawn (fitted, but the data do not support them): {', '.join(wd)}")
    if "gain" in report:
        g = report["gain"]["rmse_um"]
        L.append("held-out RMSE (µm): " + "  ".join(f"{k} {v:.4g}" for k, v in g.items()))
    if "control" in report:
        L.append(control_line(report["control"]))
    return L


def control_line(c: dict) -> str:
    """One printed line: the scatter at the poses the plain and the extended EAFM controllers choose."""
    key = "true_std_um" if c["truth"] else "predicted_std_um"
    what = "true" if c["truth"] else "predicted"
    pl = ", ".join(f"{r[key]:.3f}" for r in c["models"]["plain"])
    ex = ", ".join(f"{r[key]:.3f}" for r in c["models"]["extended"])
    return (f"control at {', '.join(f'{t:.3g}' for t in c['targets_um'])} µm: {what} std at the chosen poses "
            f"plain EAFM [{pl}] µm, extended [{ex}] µm; verdict: {control_verdict(c)}")


#: Relative difference of the std below which ``control_verdict`` calls two controllers alike.
VERDICT_TOLERANCE = 0.05


def control_verdict(c: dict) -> str:
    """One phrase: is the extended controller's scatter lower than the plain one's at every target?"""
    key = "true_std_um" if c["truth"] else "predicted_std_um"
    ratios = [e[key] / p[key] for p, e in zip(c["models"]["plain"], c["models"]["extended"]) if p[key] > 0]
    if not ratios:
        return "undetermined (no std to compare)"
    shown = "/".join(f"{r:.3f}" for r in ratios)
    if all(r < 1 - VERDICT_TOLERANCE for r in ratios):
        return f"the extended controller is better (std ratio extended/plain {shown})"
    if all(r > 1 + VERDICT_TOLERANCE for r in ratios):
        return f"the plain controller is better (std ratio extended/plain {shown})"
    if all(abs(r - 1) <= VERDICT_TOLERANCE for r in ratios):
        return (f"no clear difference (std ratio extended/plain {shown}, within "
                f"±{VERDICT_TOLERANCE:.0%} at every target)")
    return f"mixed (std ratio extended/plain {shown}: better at some targets, worse at others)"


def control_markdown(c: dict) -> list[str]:
    """The gain section's control table (microctl.diagnosis.control)."""
    L = ["### What the extension changes in control terms", "",
         "The plain and the extended EAFM (each the default residual model trained on this log; the extended "
         "one on the AFM with the accepted corrections and a noise model restricted to the diagnosed stick-slip "
         "actuators) drive the default optimal controller (eq. 4) to the same targets in sequence from the zero "
         "state." + (" Scatter and error at the chosen poses from the simulated stage's truth; the oracle is the "
                     "quietest pose that truly reaches the target exactly (found on a grid), so a chosen pose that "
                     "misses the target (true error ≠ 0) can be quieter than it: such a true std is marked *, "
                     "and it is bought with the error beside it." if c["truth"] else
                     " No simulator here: only predictions (the true scatter needs the stage)."), ""]
    head = "| target (µm) | model | q (µm) | predicted std (µm) |"
    sep = "|---|---|---|---|"
    if c["truth"]:
        head += " true std (µm) | true error (µm) | oracle std (µm) |"
        sep += "---|---|---|"
    L += [head, sep]
    for j, t in enumerate(c["targets_um"]):
        for label in ("plain", "extended"):
            r = c["models"][label][j]
            row = (f"| {t:.3g} | {label} | [{', '.join(f'{v:.2f}' for v in r['q_um'])}] | "
                   f"{r['predicted_std_um']:.4f} |")
            if c["truth"]:
                star = "*" if r["true_std_um"] < r["oracle_std_um"] else ""
                row += f" {r['true_std_um']:.4f}{star} | {r['true_error_um']:+.4f} | {r['oracle_std_um']:.4f} |"
            L.append(row)
    return L + [""]


def _identifiability_markdown(report: dict) -> list[str]:
    """report.md lines on each class of equivalent causes: members, the one carried, the runs that separate."""
    L: list[str] = []
    for item in report.get("identifiability", []):
        L += ["", f"**Equivalent to the accepted `{item['key']}` ({_fmt_params(item)})** on this data: "
              f"{', '.join(item['class'][1:])}. {item['why']}. Separate them with: " + "; ".join(item["separate_by"]) + "."]
        ch = item.get("chosen") or {}
        if ch:
            L += ["", f"`extended.yaml` carries `{item['key']}`, chosen by {ch['by']}"
                  + (f" (the lowest BIC was `{ch['lowest_bic']}`)" if ch["lowest_bic"] != item["key"] else "") + "."]
        for run in item.get("recommended_runs", []):
            if run.get("command"):
                L += ["", f"To tell `{item['key']}` from `{run['against']}`: `{run['command']}` ({run['note']})."]
        for e in report["mean_causes"]:
            if e.get("accepted") and cause_label(e) == item["key"]:
                for q in e["equivalent"]:
                    L.append(f"  - {cause_label(q)}: {_fmt_params(q)}")
    return L


def render_markdown(report: dict) -> str:
    """report.md: the four questions in order, short tables, figure links."""
    from microctl.diagnosis.selection import DELTA_BIC

    d = report["discrepancy"]
    L = ["# Model-discrepancy diagnosis", "",
         f"Data: `{report.get('source', '')}`, {report['rows']} moves ({report.get('outliers', {}).get('count', 0)} "
         "outlying rows left out of every fit and of the numbers below).", ""]
    L += ["## 1. What does the model get wrong?", ""]
    L += [f"- AFM residual RMSE: **{d['afm_rmse_um']:.4g} µm**.",
          f"- Configured model through the contact physics: {d['model_rmse_um']:.4g} µm, {gauge_zero_note(report)}; "
          f"after the accepted causes: {d['extended_rmse_um']:.4g} µm.",
          f"- Noise: {noise_line(report)[len('noise: '):]}.",
          f"- Discrepancy significant: **{'yes' if d['significant'] else 'no'}** (p = {d['p_value']:.3g}; "
          f"{d['test']}; level {d['alpha']:g}).",
          f"- {outlier_line(report).capitalize()}.", ""]
    L += ["| test | statistic | p-value |", "|---|---|---|"]
    for t in d["tests"]:
        L.append(f"| {t['test']} | {_num(t['statistic'], '.4g')} | {_num(t['p_value'], '.3g')} |")
    L += ["", "Where the AFM residual grows (smallest p first):", "", "| variable | test | effect (µm) | p-value |",
          "|---|---|---|---|"]
    for w in sorted(d["where"], key=lambda w: w["p_value"])[:8]:
        L.append(f"| {w['variable']} | {w['test']} | {w['effect_um']:.3g} | {w['p_value']:.3g} |")
    L += ["", "![residuals](residuals.png)", ""]
    L += ["## 2. What is the cause?", ""]
    L.append(f"Accepted mean causes: **{', '.join(accepted_labels(report, 'mean')) or 'none'}**; noise: "
             f"**{', '.join(accepted_labels(report, 'noise'))}** (selection stopped: {report['selection']['stop_reason']}).")
    L += ["", f"{DELTA_BIC}.", "", "| cause | parameters (± std. error) | ΔBIC | accepted |", "|---|---|---|---|"]
    for e in report["mean_causes"][:12]:
        acc = "yes" if e.get("accepted") else ("withdrawn" if e.get("withdrawn") else "")
        L.append(f"| {cause_label(e)} | {_fmt_params(e)} | {_num(e.get('delta_bic'), '.1f')} | {acc} |")
    for e in report["mean_causes"]:
        if e.get("withdrawn"):
            L += ["", f"`{cause_label(e)}` was fitted but withdrawn: {e['withdrawn']}."]
    L += _identifiability_markdown(report)
    if report["unexplained"]["significant"]:
        L += ["", f"A structured residual is left that no vocabulary cause explains (`unexplained`, "
              f"p = {report['unexplained']['p_value']:.3g}); the causes above still pay alongside a flexible term "
              "(generic basis + GP) fitted to it."]
        if report["unexplained"].get("depends_on"):
            L += ["", report["unexplained"]["depends_on"]]
    L += ["", "| noise cause | parameters | ΔBIC | accepted |", "|---|---|---|---|"]
    for e in report["noise_causes"]:
        L.append(f"| {cause_label(e)} | {_fmt_params(e)} | {_num(e.get('delta_bic'), '.1f')} | "
                 f"{'yes' if e.get('accepted') else ''} |")
    L += ["", "![causes](causes.png)", ""]
    L += ["## 3. Extended model", "", "`extended.yaml` is the input config with these corrections in `stage.corrections`:",
          "", "```", str(report.get("corrections") or "{}"), "```", ""]
    phys = report.get("physics_nuisance")
    if phys:
        L += [f"and the stage physics fitted with them: {phys} (in `stage.physics`).", ""]
    if "gain" in report:
        g = report["gain"]
        L += ["## 4. Gain", "", f"Method: {g['method']} ({g['held_out_moves']} held-out moves).", "",
              "| model | RMSE (µm) | NLPD |", "|---|---|---|"]
        for k, v in g["rmse_um"].items():
            nl = g["nlpd"].get(k)
            L.append(f"| {k} | {v:.4g} | {'' if nl is None else f'{nl:.3f}'} |")
        L += ["", "| comparison (one-sided paired t-test on squared errors) | p-value |", "|---|---|"]
        for k, v in g["p_value"].items():
            L.append(f"| {k} | {v:.3g} |")
        L += ["", "![gain](gain.png)", ""]
    if "control" in report:
        L += control_markdown(report["control"])
    figs = report.get("figures", {})
    if figs.get("skipped"):
        L += ["", f"_Figures skipped: {figs['skipped']}._"]
    return "\n".join(L) + "\n"


def write_outputs(diagnosis, out_dir: str | Path, *, figures: bool = True) -> dict:
    """Write report.json, report.md, extended.yaml and the figures into ``out_dir``.

    Returns
    -------
    dict
        The report as written.
    """
    from microctl.diagnosis.figures import write_figures

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    report = to_jsonable(diagnosis.report)
    add_identifiability(report)
    report["figures"] = write_figures(diagnosis, out) if figures else {"files": [], "skipped": "not requested"}
    write_text_atomic(out / "extended.yaml", diagnosis.extended_config.dump_yaml())
    report["extended_config"] = str(out / "extended.yaml")
    write_json(out / "report.json", report)
    write_text_atomic(out / "report.md", render_markdown(report))
    return report
