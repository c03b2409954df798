"""Figures of the experiments as PNG (matplotlib optional: none are written without it).

Both figures are drawn from ``results.json`` (the statistics the report prints), so every
number a figure shows is the one the report states. Controllers are named as in the report
(:mod:`~microctl.experiments.controllers`: AFM, EAFM, oracle) with one colour
and one marker each.

- ``fig5_absolute.png`` (paper Fig. 5): (a) per absolute point, the feedback t' of each
  trial, the AFM prediction and the EAFM mean with its ±2σ interval (the band the report's
  coverage counts), points ordered by the AFM prediction and drawn as markers only: the
  points are unrelated moves, so no line joins them; (b) the prediction errors PE of AFM and
  EAFM per point (linear axis); (c) the EAFM's standardised residuals (t' − mean)/σ per
  measurement with the ±2 limits, titled with the measured ±2σ coverage.
- ``fig6_incremental.png`` (paper Fig. 6): the steady-state error e_s = t_d − t_f of every
  trial, one panel per target, one marker per controller, side by side (horizontal offsets)
  so a controller that coincides with another stays visible, with the MSSE as a line. Top
  row: every controller on one y scale shared by all targets (so 1 µm at 7 µm and 5 µm at
  28 µm look their size); bottom row: the controllers other than the AFM (EAFM, oracle),
  again on one shared scale, to show the scatter the top row's scale hides.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

import microctl.experiments.controllers as registry
from microctl.util.atomic import save_figure

FIG5, FIG6 = "fig5_absolute.png", "fig6_incremental.png"


def _label(name: str) -> str:
    return registry.label(name)


def _marker_kw(name: str, size: float = 5.0) -> dict:
    st = registry.style(name)  # the same colour and marker in every figure
    return {"marker": st.marker, "ls": "none", "ms": size, "color": st.color, "mec": st.color,
            "mfc": st.color if st.fill else "white", "mew": 1.2}


def figure_fig5(absolute: dict, title: str = ""):
    """Fig. 5 analogue from ``results["absolute"]``; returns the matplotlib figure.

    Parameters
    ----------
    absolute : dict
        ``results.json``'s ``absolute`` (``measured_um`` (trials, points), ``afm_um``,
        ``eafm_mean_um``, ``eafm_std_um`` (trials, points), ``pe_um``,
        ``fraction_within_2sigma``).
    title : str
        Figure title prefix (e.g. the experiment file).
    """
    import matplotlib.pyplot as plt

    meas = np.asarray(absolute["measured_um"], dtype=float)  # (trials, points)
    afm = np.asarray(absolute["afm_um"], dtype=float)
    mean = np.asarray(absolute["eafm_mean_um"], dtype=float)
    std = np.asarray(absolute["eafm_std_um"], dtype=float)
    T, n = meas.shape
    order = np.argsort(afm)
    x = np.arange(1, n + 1)
    fig, (a, b, c) = plt.subplots(3, 1, figsize=(9, 10), sharex=True,
                                  gridspec_kw={"height_ratios": [3, 2, 2]})
    # (a) per point: EAFM mean ± 2σ (the trials start from the same zero state: their
    # predictions differ only by the zero state's reading, so the trial mean is drawn)
    m, s = np.nanmean(mean, axis=0)[order], np.nanmean(std, axis=0)[order]
    a.errorbar(x, m, yerr=2 * s, fmt="none", ecolor=registry.style("eafm").color, elinewidth=5, alpha=0.3,
               label="EAFM mean ± 2σ")
    a.plot(x, m, **_marker_kw("eafm", 4), label="EAFM mean")
    a.plot(x, afm[order], **{**_marker_kw("afm", 7), "marker": "x"}, label="AFM prediction")
    offs = np.linspace(-0.18, 0.18, T) if T > 1 else np.zeros(1)
    for k in range(T):
        a.plot(x + offs[k], meas[k, order], "k.", ms=6, label="feedback t' (each trial)" if k == 0 else None)
    a.set_ylabel("tool pose t (µm)")
    a.set_title("(a) feedback and predictions per point (markers only: the points are unrelated moves)")
    a.legend(fontsize=8, loc="upper left")
    a.grid(alpha=0.3)
    # (b) PE per point, linear axis
    pe_a = np.asarray(absolute["pe_um"]["afm"], dtype=float)[order]
    pe_e = np.asarray(absolute["pe_um"]["eafm"], dtype=float)[order]
    b.bar(x - 0.2, pe_a, width=0.4, color=registry.style("afm").color, label="AFM")
    b.bar(x + 0.2, pe_e, width=0.4, color=registry.style("eafm").color, label="EAFM")
    b.set_ylabel("prediction error PE (µm)")
    b.set_title(f"(b) PE = |t' − prediction|, mean of {T} trial{'s' if T != 1 else ''} per point")
    b.legend(fontsize=8, loc="upper left")
    b.grid(alpha=0.3, axis="y")
    # (c) standardised residuals of every measurement against the EAFM prediction
    z = (meas - mean) / std
    for k in range(T):
        c.plot(x + offs[k], z[k, order], **_marker_kw("eafm", 4))
    c.axhline(2, color="0.4", ls="--", lw=1)
    c.axhline(-2, color="0.4", ls="--", lw=1)
    c.axhline(0, color="0.6", lw=0.8)
    frac = absolute.get("fraction_within_2sigma")
    c.set_title("(c) EAFM residual (t' − mean) / σ per measurement; dashed: ±2σ"
                + (f" ({100 * frac:.1f} % inside)" if frac is not None else ""))
    c.set_ylabel("standardised residual (σ)")
    c.set_xlabel("absolute point, ordered by AFM prediction (index, no unit)")
    c.grid(alpha=0.3)
    fig.suptitle(f"{title}Absolute movement (Fig. 5 analogue): {n} points × {T} trials", fontsize=11)
    fig.tight_layout()
    return fig


def msse_dashes(k: int, n: int) -> tuple:
    """Dash pattern of controller ``k`` of ``n``: dashes of 4 points that interleave with the others'.

    Two controllers with the same MSSE draw the same line; interleaved dashes keep both colours
    visible along it.
    """
    return (4.0 * k, (4.0, 4.0 * max(n - 1, 1)))


def figure_fig6(incremental: dict, title: str = ""):
    """Fig. 6 analogue from ``results["incremental"]``; returns the matplotlib figure.

    Parameters
    ----------
    incremental : dict
        ``results.json``'s ``incremental`` (``targets_um``, ``trials``,
        ``controllers.<name>.sse_um`` (trials, targets) and ``msse_um``).
    title : str
        Figure title prefix.
    """
    import matplotlib.pyplot as plt

    targets = list(incremental["targets_um"])
    ctrls = incremental["controllers"]
    J, T = len(targets), int(incremental["trials"])
    quiet = [n for n in ctrls if n != "afm"]
    rows = 2 if quiet else 1
    zoomed = " and ".join(_label(n) for n in quiet)
    fig, axes = plt.subplots(rows, J, figsize=(3.3 * J + 0.6, 3.2 * rows + 1.0), squeeze=False,
                             sharey="row", layout="constrained")
    trials = np.arange(1, T + 1)
    for r, names in enumerate([list(ctrls), quiet][:rows]):
        for j, t in enumerate(targets):
            ax = axes[r, j]
            for k, name in enumerate(names):
                e = np.asarray(ctrls[name]["sse_um"], dtype=float)[:, j]
                off = registry.style(name).offset
                ax.plot(trials + off, e, **_marker_kw(name, 5), label=_label(name))
                ax.plot([0.6, T + 0.4], [ctrls[name]["msse_um"][j]] * 2, color=registry.style(name).color,
                        lw=1.4, alpha=0.9, ls=msse_dashes(k, len(names)), label=f"{_label(name)} MSSE")
            ax.axhline(0, color="0.5", lw=0.8)
            ax.set_xticks(trials if T <= 10 else np.linspace(1, T, 5).round().astype(int))
            ax.set_xlim(0.4, T + 0.6)
            ax.grid(alpha=0.3)
            ax.set_xlabel("trial (no unit)")
            if r == 0:
                ax.set_title(f"target $t_d$ = {t:g} µm")
            if j == 0:
                ax.set_ylabel("$e_s = t_d - t_f$ (µm)" if r == 0 else "$e_s$ without the AFM (µm)")
    handles, labels = axes[0, 0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="outside lower center", ncol=max(len(ctrls), 1),
               fontsize=8, title="markers: one trial each (side by side); dashed line: MSSE (equal MSSEs "
               "interleave their dashes, so none hides another)", title_fontsize=8)
    fig.suptitle(f"{title}Incremental movement (Fig. 6 analogue): steady-state error per trial, {T} trials\n"
                 + (f"top: every controller on one scale; bottom: {zoomed}, zoomed to one scale" if rows == 2
                    else "one scale for every target"), fontsize=10, x=0.02, ha="left")
    return fig


def write_figures(out: Path, results: dict, title: str = "") -> list[str]:
    """Write Fig. 5 and Fig. 6 analogues into ``out`` from ``results`` (the content of
    results.json); returns the file names written (empty without matplotlib).

    Parameters
    ----------
    out : Path
        Output folder.
    results : dict
        Plain-data results (:func:`~microctl.experiments.report.build_results`).
    title : str
        Prefix of each figure's title (e.g. ``"paper.yaml: "``).
    """
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:  # pragma: no cover - matplotlib is optional
        return []
    names: list[str] = []
    for key, make, name in (("absolute", figure_fig5, FIG5), ("incremental", figure_fig6, FIG6)):
        if results.get(key) is None:
            continue
        fig = make(results[key], title)
        save_figure(fig, Path(out) / name, dpi=110)
        plt.close(fig)
        names.append(name)
    return names
