"""report.json / report.md / extended.yaml of a diagnosis, and what separates equivalent causes."""

from __future__ import annotations

from pathlib import Path

from microctl.commands._common import to_jsonable, write_json

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
            "class": [e["cause"] + _act(e)] + [q["cause"] + _act(q) for q in e["equivalent"]],
            "causes": names,
            "why": ("with one scalar gauge these causes predict the same readings within the noise "
                    "(same likelihood within 2Δℓ < 6)"),
            "separate_by": seps,
        })
    report["identifiability"] = out


def _act(e: dict) -> str:
    a = e.get("params", {}).get("actuator")
    return "" if a is None else f"[{a}]"


def _num(x, fmt: str) -> str:
    return "—" if x is None else format(x, fmt)


def _fmt_params(e: dict) -> str:
    parts = []
    for k, v in e.get("params", {}).items():
        if k == "actuator":
            parts.append(f"actuator {v}")
            continue
        se = e.get("stderr", {}).get(k)
        parts.append(f"{k} = {v:.5g}" + (f" ± {se:.2g}" if isinstance(se, (int, float)) else ""))
    return ", ".join(parts) if parts else "—"


def render_markdown(report: dict) -> str:
    """report.md: the four questions in order, short tables, figure links."""
    d = report["discrepancy"]
    L = ["# Model-discrepancy diagnosis", "", f"Data: `{report.get('source', '')}`, {report['rows']} moves.", ""]
    L += ["## 1. What does the model get wrong?", ""]
    L += [f"- AFM residual RMSE: **{d['afm_rmse_um']:.4g} µm** (configured model through the contact physics: "
          f"{d['model_rmse_um']:.4g} µm; after the accepted causes: {d['extended_rmse_um']:.4g} µm).",
          f"- Noise level (fitted base std): {d['noise_std_um']:.4g} µm.",
          f"- Discrepancy significant: **{'yes' if d['significant'] else 'no'}** (p = {d['p_value']:.3g}; "
          f"{d['test']}; level {d['alpha']:g}).", ""]
    L += ["| test | statistic | p-value |", "|---|---|---|"]
    for t in d["tests"]:
        L.append(f"| {t['test']} | {_num(t['statistic'], '.4g')} | {_num(t['p_value'], '.3g')} |")
    L += ["", "Where the AFM residual grows (smallest p first):", "", "| variable | test | effect (µm) | p-value |",
          "|---|---|---|---|"]
    for w in sorted(d["where"], key=lambda w: w["p_value"])[:8]:
        L.append(f"| {w['variable']} | {w['test']} | {w['effect_um']:.3g} | {w['p_value']:.3g} |")
    L += ["", "![residuals](residuals.png)", ""]
    L += ["## 2. What is the cause?", ""]
    acc = report["accepted"]
    L.append(f"Accepted mean causes: **{', '.join(acc['mean']) or 'none'}**; noise: **{', '.join(acc['noise'])}** "
             f"(selection stopped: {report['selection']['stop_reason']}).")
    L += ["", "| cause | parameters (± std. error) | ΔBIC | accepted |", "|---|---|---|---|"]
    for e in report["mean_causes"][:12]:
        L.append(f"| {e['cause']} | {_fmt_params(e)} | {e.get('delta_bic', 0):.1f} | {'yes' if e.get('accepted') else ''} |")
    for item in report.get("identifiability", []):
        L += ["", f"**Equivalent to the accepted `{item['cause']}`** on this data: {', '.join(item['class'][1:])}. "
              f"{item['why']}. Separate them with: " + "; ".join(item["separate_by"]) + "."]
        for e in report["mean_causes"]:
            if e.get("accepted") and e["cause"] == item["cause"]:
                for q in e["equivalent"]:
                    L.append(f"  - {q['cause']}: {_fmt_params(q)}")
    if report["unexplained"]["significant"]:
        L += ["", f"A structured residual is left that no vocabulary cause explains (`unexplained`, "
              f"p = {report['unexplained']['p_value']:.3g})."]
    L += ["", "| noise cause | parameters | ΔBIC | accepted |", "|---|---|---|---|"]
    for e in report["noise_causes"]:
        L.append(f"| {e['cause']} | {_fmt_params(e)} | {e.get('delta_bic', 0):.1f} | {'yes' if e.get('accepted') else ''} |")
    L += ["", "![causes](causes.png)", ""]
    L += ["## 3. Extended model", "", "`extended.yaml` is the input config with these corrections in `stage.corrections`:",
          "", "```", str(report.get("corrections") or "{}"), "```", ""]
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
    (out / "extended.yaml").write_text(diagnosis.extended_config.dump_yaml())
    report["extended_config"] = str(out / "extended.yaml")
    write_json(out / "report.json", report)
    (out / "report.md").write_text(render_markdown(report))
    return report
