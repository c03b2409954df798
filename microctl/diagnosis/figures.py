"""Figures of a diagnosis (matplotlib, optional: without it the report says they were skipped)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from microctl.diagnosis.selection import cause_label
from microctl.util.atomic import save_figure


def write_figures(diagnosis, out: Path) -> dict:
    """Write residuals.png, causes.png and gain.png.

    Returns
    -------
    dict
        ``{"files": [...], "skipped": None or reason}``.
    """
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:  # pragma: no cover - depends on the environment
        return {"files": [], "skipped": "matplotlib is not installed"}
    files = []
    files.append(_residuals(plt, diagnosis, out / "residuals.png"))
    files.append(_causes(plt, diagnosis, out / "causes.png"))
    if diagnosis.gain is not None:
        files.append(_gain(plt, diagnosis, out / "gain.png"))
    return {"files": [f.name for f in files], "skipped": None}


def _residuals(plt, dg, path: Path) -> Path:
    """AFM residual against each input, previous state, time and direction of approach."""
    from microctl.diagnosis.residuals import where_units, where_variables

    data = dg.data
    stage = dg.extended_config.stage
    vars_ = where_variables(data, stage.actuator_names, stage.dof, stage.tool.name)
    n_panels = len(vars_) + 1
    cols = 4
    rows = int(np.ceil(n_panels / cols))
    fig, axes = plt.subplots(rows, cols, figsize=(3.2 * cols, 2.6 * rows), squeeze=False)
    ax_list = axes.ravel()
    units = where_units(stage.dof, stage.actuator_names, stage.tool.name)
    for ax, (name, v) in zip(ax_list, vars_.items()):
        ax.plot(v, dg.afm_residual, ".", ms=3, alpha=0.6, label="AFM")
        ax.plot(v, dg.final_residual, ".", ms=3, alpha=0.6, label="extended")
        ax.set_xlabel(f"{name} ({units.get(name, '')})")
        ax.set_ylabel("residual (µm)")
    ax = ax_list[len(vars_)]
    n_q = data.direction.shape[1]
    for i in range(n_q):
        for s, x, color, label in ((1, i + 0.15, "tab:red", "up"), (-1, i - 0.15, "tab:purple", "down")):
            r = dg.afm_residual[data.direction[:, i] == s]
            if r.size:
                ax.errorbar([x], [r.mean()], yerr=[r.std() / np.sqrt(r.size) * 2], fmt="^" if s > 0 else "v",
                            color=color, label=label if i == 0 else None)
    ax.legend(fontsize=7, title="approached", title_fontsize=7, loc="best", framealpha=0.6)
    ax.set_xticks(range(n_q))
    ax.set_xticklabels(stage.actuator_names)
    ax.set_xlabel("actuator: mean by direction of approach (▲ up, ▼ down), ±2 s.e.")
    ax.set_ylabel("mean AFM residual (µm)")
    for ax in ax_list[n_panels:]:
        ax.axis("off")
    ax_list[0].legend(fontsize=7)
    fig.suptitle("Residual against inputs, previous state, time, direction")
    fig.tight_layout()
    save_figure(fig, path, dpi=90)
    plt.close(fig)
    return path


def _causes(plt, dg, path: Path) -> Path:
    """ΔBIC (the report's one definition) of the mean candidates and the noise causes."""
    rep = dg.report
    entries = [e for e in rep["mean_causes"] + rep["noise_causes"]
               if e.get("delta_bic") is not None and e["cause"] != "homoscedastic"]
    labels = [cause_label(e) + (" (withdrawn)" if e.get("withdrawn") else "") for e in entries]
    vals = [e["delta_bic"] for e in entries]
    fig, ax = plt.subplots(figsize=(7, 0.25 * max(len(labels), 4) + 1.2))
    colors = ["tab:green" if e.get("accepted") else ("tab:orange" if e.get("withdrawn") else "tab:gray")
              for e in entries]
    ax.barh(range(len(vals)), vals, color=colors)
    ax.set_yticks(range(len(vals)))
    ax.set_yticklabels(labels, fontsize=7)
    ax.invert_yaxis()
    ax.axvline(0, color="k", lw=0.5)
    ax.set_xlabel("ΔBIC (dimensionless; symmetric log axis, linear within ±10):\n"
                  "model with the cause − model it was added to; negative: the cause pays")
    ax.set_ylabel("cause (green: accepted, orange: withdrawn)")
    ax.set_xscale("symlog", linthresh=10)
    ax.set_title("Which cause pays: ΔBIC of each candidate")
    fig.tight_layout()
    save_figure(fig, path, dpi=90)
    plt.close(fig)
    return path


#: Display names of the gain's models (the report's keys stay as the spec names them).
GAIN_LABELS = {"afm": "AFM", "afm_gp": "AFM + GP\n(the EAFM)", "extended": "extended", "extended_gp": "extended\n+ GP"}


def _gain(plt, dg, path: Path) -> Path:
    """Held-out RMSE of the four models and the error distributions."""
    g = dg.gain
    names = list(g.rmse_um)
    labels = [GAIN_LABELS.get(k, k) for k in names]
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(10, 3.8))
    # a dot per model on a log axis (a bar's length from an arbitrary log baseline means nothing)
    vals = [g.rmse_um[k] for k in names]
    a1.plot(range(len(names)), vals, "o", color="tab:blue", ms=8)
    for i, v in enumerate(vals):
        a1.annotate(f"{v:.3g}", (i, v), textcoords="offset points", xytext=(8, 0), va="center", fontsize=8)
    a1.set_xticks(range(len(names)))
    a1.set_xticklabels(labels)
    a1.set_xlim(-0.5, len(names) - 0.3)
    a1.set_xlabel("model")
    a1.set_ylabel("held-out RMSE (µm, log axis)")
    a1.set_yscale("log")
    a1.set_title(f"Held-out RMSE ({g.method})")
    a2.boxplot([np.abs(g.errors[k]) for k in names], showfliers=False)
    a2.set_xticks(range(1, len(names) + 1))
    a2.set_xticklabels(labels)
    a2.set_xlabel("model")
    a2.set_ylabel("held-out abs(error) (µm, log axis)")
    a2.set_yscale("log")
    a2.set_title("Per-move held-out errors (box: quartiles)")
    fig.tight_layout()
    save_figure(fig, path, dpi=90)
    plt.close(fig)
    return path
