"""Figures of the experiments as PNG (matplotlib optional: none are written without it).

- ``fig5_absolute.png`` (paper Fig. 5): (a) the feedback t' of each absolute move with the AFM
  prediction and the EAFM mean ± σ band, points ordered by the AFM prediction; (b) the
  prediction errors of AFM and EAFM per point.
- ``fig6_incremental.png`` (paper Fig. 6): the steady-state error per trial, one panel per
  target, one line per controller.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np


def write_figures(out: Path, absolute: dict | None, incremental: dict | None) -> list[str]:
    """Write the figures into ``out``; returns the file names written (empty without matplotlib)."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:  # pragma: no cover - matplotlib is optional
        return []
    names: list[str] = []
    if absolute is not None:
        meas = absolute["measured_um"]  # (trials, points)
        order = np.argsort(absolute["afm_um"])
        x = np.arange(meas.shape[1])
        mean = np.nanmean(absolute["eafm_mean_um"], axis=0)[order]
        std = np.nanmean(absolute["eafm_std_um"], axis=0)[order]
        fig, (a, b) = plt.subplots(2, 1, figsize=(8, 7), sharex=True)
        a.fill_between(x, mean - std, mean + std, color="tab:red", alpha=0.2, label="EAFM mean ± σ")
        a.plot(x, mean, color="tab:red", label="EAFM mean")
        a.plot(x, absolute["afm_um"][order], color="tab:blue", ls="--", label="AFM")
        for k in range(meas.shape[0]):
            a.plot(x, meas[k, order], "k.", ms=5, label="feedback t'" if k == 0 else None)
        a.set_ylabel("tool pose t (µm)")
        a.set_title("(a) absolute movement: feedback and predictions")
        a.legend(fontsize=8)
        pe_a = np.abs(meas - absolute["afm_um"][None, :]).mean(axis=0)[order]
        pe_e = np.abs(meas - absolute["eafm_mean_um"]).mean(axis=0)[order]
        b.bar(x - 0.2, pe_a, width=0.4, color="tab:blue", label="AFM")
        b.bar(x + 0.2, pe_e, width=0.4, color="tab:red", label="EAFM")
        b.set_xlabel("point (ordered by AFM prediction)")
        b.set_ylabel("prediction error (µm)")
        b.set_title("(b) prediction errors")
        b.legend(fontsize=8)
        fig.tight_layout()
        fig.savefig(Path(out) / "fig5_absolute.png", dpi=110)
        plt.close(fig)
        names.append("fig5_absolute.png")
    if incremental is not None:
        targets = incremental["targets_um"]
        fig, axes = plt.subplots(1, len(targets), figsize=(3.2 * len(targets), 3.4), squeeze=False)
        colors = {"afm": "tab:blue", "eafm": "tab:red", "oracle": "tab:green"}
        for j, t in enumerate(targets):
            ax = axes[0, j]
            for name, r in incremental["controllers"].items():
                e = t - r["reached_um"][:, j]
                ax.plot(np.arange(1, len(e) + 1), e, "o-", ms=3, color=colors.get(name), label=name.upper())
            ax.axhline(0, color="0.5", lw=0.8)
            ax.set_title(f"{t:g} µm")
            ax.set_xlabel("trial")
            if j == 0:
                ax.set_ylabel("steady-state error (µm)")
                ax.legend(fontsize=8)
        fig.tight_layout()
        fig.savefig(Path(out) / "fig6_incremental.png", dpi=110)
        plt.close(fig)
        names.append("fig6_incremental.png")
    return names
