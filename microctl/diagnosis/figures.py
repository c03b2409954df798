"""Figures of a diagnosis (matplotlib, optional: without it the report says they were skipped)."""

from __future__ import annotations

from pathlib import Path

import numpy as np


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
        for s, x in ((1, i + 0.15), (-1, i - 0.15)):
            r = dg.afm_residual[data.direction[:, i] == s]
            if r.size:
                ax.errorbar([x], [r.mean()], yerr=[r.std() / np.sqrt(r.size) * 2], fmt="^" if s > 0 else "v")
    ax.set_xticks(range(n_q))
    ax.set_xticklabels(stage.actuator_names)
    ax.set_xlabel("actuator: mean by direction of approach (▲ up, ▼ down), ±2 s.e.")
    ax.set_ylabel("mean AFM residual (µm)")
    for ax in ax_list[n_panels:]:
        ax.axis("off")
    ax_list[0].legend(fontsize=7)
    fig.suptitle("Residual against inputs, previous state, time, direction")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def _causes(plt, dg, path: Path) -> Path:
    """ΔBIC (the report's one definition) of the mean candidates and the noise causes."""
    rep = dg.report
    entries = [e for e in rep["mean_causes"] + rep["noise_causes"]
               if e.get("delta_bic") is not None and e["cause"] != "homoscedastic"]
    labels = [e["cause"] + (f"[{e['params']['actuator']}]" if "actuator" in e["params"] else "")
              + (" (withdrawn)" if e.get("withdrawn") else "") for e in entries]
    vals = [e["delta_bic"] for e in entries]
    fig, ax = plt.subplots(figsize=(7, 0.25 * max(len(labels), 4) + 1.2))
    colors = ["tab:green" if e.get("accepted") else ("tab:orange" if e.get("withdrawn") else "tab:gray")
              for e in entries]
    ax.barh(range(len(vals)), vals, color=colors)
    ax.set_yticks(range(len(vals)))
    ax.set_yticklabels(labels, fontsize=7)
    ax.invert_yaxis()
    ax.axvline(0, color="k", lw=0.5)
    ax.set_xlabel("ΔBIC (dimensionless): model with the cause − model it was added to; negative: the cause pays")
    ax.set_ylabel("cause (green: accepted)")
    ax.set_xscale("symlog", linthresh=10)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def _gain(plt, dg, path: Path) -> Path:
    """Held-out RMSE of the four models and the error distributions."""
    g = dg.gain
    names = list(g.rmse_um)
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(10, 3.5))
    a1.bar(names, [g.rmse_um[k] for k in names], color="tab:blue")
    a1.set_xlabel("model")
    a1.set_ylabel("held-out RMSE (µm)")
    a1.set_yscale("log")
    a1.set_title(g.method)
    a2.boxplot([np.abs(g.errors[k]) for k in names], showfliers=False)
    a2.set_xticks(range(1, len(names) + 1))
    a2.set_xticklabels(names)
    a2.set_xlabel("model")
    a2.set_ylabel("held-out abs(error) (µm)")
    a2.set_yscale("log")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path
