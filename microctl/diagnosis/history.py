"""Leftover tests that look at how the stage got where it is: move history and periodic errors.

The generic bases of :func:`~microctl.diagnosis.residuals.generic_blocks` look at the pose u,
the time and each actuator's direction of approach. A piezo's hysteresis (its output depends
on the direction *and the length* of the last move, a loop) and a gauge's periodic
interpolation error (a ripple along the reading) are invisible to them. Two more families of
nested F-tests, in the same multiple-testing discipline (each exact F under the null,
Bonferroni with the generic ones in :func:`~microctl.diagnosis.residuals.structure_f_test`):

- :func:`history_blocks` — per actuator i, with a_i = |Δq_i| (standardised), d_i the direction
  of approach and ρ_i = 1 when this move reversed actuator i's direction: the *last step*
  block (d_i·a_i, d_i·a_i², a_i: direction × length; ρ_i, ρ_i·d_i, ρ_i·d_i·a_i: how far a
  reversal travelled, which is where a play operator only half switches), the *previous
  state* block (q_prev,i and d_i·q_prev,i) and the *play operators* block
  (:func:`play_deviations`: generic play operators of 4 thresholds run along the commands, the
  memory of more than one move). Tested beyond a
  constant, the pose (linear) and the directions, so that a significant result says "depends
  on the history beyond where the stage is and from which side it came" (a backlash is a pure
  direction step and is not history in this sense).
- :func:`periodic_scan` — sin and cos of 2π r̂/λ in the *predicted* reading r̂ (a function of
  the inputs, so the test stays exact under the null), over a grid of periods from
  :data:`PERIOD_MIN_UM` to half the reading span spaced by half the frequency resolution;
  each pair tested beyond a constant and the linear pose, Bonferroni over the grid.
"""

from __future__ import annotations

import numpy as np
from scipy import stats

from microctl.diagnosis.data import DiagnosisData

#: Shortest period (µm of reading) of the periodic scan: below it a ripple of a fraction of
#: a µm is hard to tell from the model's own error of ~σ in the predicted reading.
PERIOD_MIN_UM = 2.0

#: Oversampling of the frequency grid (spacing 1 / (OVERSAMPLE × reading span)).
OVERSAMPLE = 2

#: Most periods the scan tests (its Bonferroni factor).
MAX_PERIODS = 200


def _z(x: np.ndarray) -> np.ndarray:
    sd = x.std(axis=0)
    return (x - x.mean(axis=0)) / np.where(sd > 0, sd, 1.0)


def reversals(data: DiagnosisData) -> np.ndarray:
    """1 where a move reversed an actuator's direction of approach, shape (n, n_q).

    The direction before the first row is the zero state's "up" (as
    :func:`microctl.stage.physics.directions_from_steps`)."""
    before = np.vstack([np.ones((1, data.direction.shape[1])), data.direction[:-1]])
    return (data.direction != before).astype(float)


#: Thresholds of the generic play operators, as fractions of each actuator's command spread
#: (1, 2, 4, 8 µm on a 32 µm stroke).
PLAY_FRACTIONS = (1 / 32, 1 / 16, 1 / 8, 1 / 4)


def play_outputs(data: DiagnosisData, fractions=PLAY_FRACTIONS) -> tuple[np.ndarray, np.ndarray]:
    """Play operators run along each actuator's commands: y_k = max(q_k − r, min(q_k + r, y_{k−1}))
    (Krasnosel'skii & Pokrovskii; the building block of every Prandtl-Ishlinskii hysteresis).

    Each row feeds q_prev then q (a row whose predecessor was left out still starts from its
    true previous command); the zero state is approached from below (y = −r).

    Returns
    -------
    offsets : ndarray, shape (n, m, n_q)
        y − q per row, threshold ``fractions[j]`` × the spread of actuator i's commands.
    r : ndarray, shape (m, n_q)
        The thresholds, µm.
    """
    q, qp = data.q, data.q_prev
    n, n_q = q.shape
    r = np.outer(np.ptp(np.vstack([q, qp]), axis=0), fractions).T  # (m, n_q)
    y = -r.copy()
    out = np.empty((n, r.shape[0], n_q))
    for k in range(n):
        for x in (qp[k], q[k]):
            y = np.maximum(x - r, np.minimum(x + r, y))
        out[k] = y - q[k]
    return out, r


def play_deviations(data: DiagnosisData, fractions=PLAY_FRACTIONS) -> np.ndarray:
    """Generic rate-independent memory: each play operator's deviation from a pure backlash,
    y − q + r d (:func:`play_outputs`), zero after a move longer than 2r, growing after a short
    reversal.

    Returns
    -------
    ndarray, shape (n, n_q × len(fractions))
        Column i + n_q j: actuator i, threshold ``fractions[j]`` × the spread of its commands.
    """
    off, r = play_outputs(data, fractions)
    return (off + r[None] * data.direction[:, None, :]).reshape(data.n, -1)


def hysteresis_estimate(resid: np.ndarray, data: DiagnosisData, sensitivity: np.ndarray) -> dict:
    """A Prandtl-Ishlinskii loop fitted to a residual: what a hysteresis would have to be.

    resid ≈ c + b·u + Σ_i J_i Σ_j w_ij (y_ij − q_i), w ≥ 0 (non-negative least squares on the
    operators of :func:`play_outputs`, J_i = ∂reading/∂q_act,i); the major-loop half-width of
    actuator i is h_i = Σ_j w_ij r_ij. A description of the leftover, not a vocabulary cause.

    Parameters
    ----------
    resid : ndarray (n,)
        Unweighted residual, µm.
    data : DiagnosisData
    sensitivity : ndarray (n, n_q)
        J, reading per actuator µm.

    Returns
    -------
    dict
        ``{"shape", "half_width_um": {actuator: h}, "actuators" (those carrying the loop),
        "rms_um" (of the fitted loop's readings), "heldout_rmse_um" ({"without", "with"}: 5-fold
        cross-validated RMSE of the residual after a constant and the linear pose, without and
        with the loop), "note"}``.
    """
    from scipy.optimize import lsq_linear

    off, r = play_outputs(data)
    m, n_q = r.shape
    X = (sensitivity[:, None, :] * off).reshape(data.n, -1)
    B0 = np.column_stack([np.ones(data.n), _z(data.u)])
    A = np.hstack([B0, X])
    lo = np.r_[np.full(B0.shape[1], -np.inf), np.zeros(X.shape[1])]
    sol = lsq_linear(A, resid, bounds=(lo, np.full(A.shape[1], np.inf)))
    w = sol.x[B0.shape[1]:].reshape(m, n_q)
    h = (w * r).sum(axis=0)
    # what the loop buys on held-out moves: 5-fold CV (seeded) of the base alone and with the loop
    folds = np.random.default_rng(0).permutation(data.n) % 5
    err = {"without": [], "with": []}
    for f in range(5):
        tr, te = folds != f, folds == f
        for name, M, bl in (("without", B0, lo[:B0.shape[1]]), ("with", A, lo)):
            x = lsq_linear(M[tr], resid[tr], bounds=(bl, np.full(M.shape[1], np.inf))).x
            err[name].append(resid[te] - M[te] @ x)
    cv = {k: float(np.sqrt(np.mean(np.concatenate(v) ** 2))) for k, v in err.items()}
    # the actuators that carry the loop: at least a quarter of the largest and 0.02 µm (below it a
    # loop is a fraction of the gauge noise of a rig)
    acts = [i + 1 for i in range(n_q) if h[i] >= max(0.25 * h.max(), 0.02)]
    return {"shape": "rate-independent hysteresis (Prandtl-Ishlinskii loop, play operators)",
            "half_width_um": {str(i + 1): float(h[i]) for i in range(n_q)}, "actuators": acts,
            "rms_um": float(np.sqrt(np.mean((X @ sol.x[B0.shape[1]:]) ** 2))),
            "heldout_rmse_um": cv,
            "note": "a description of the leftover (non-negative play-operator weights), not a vocabulary cause"}


def history_blocks(data: DiagnosisData) -> dict[str, np.ndarray]:
    """Move-history regressors in named blocks, each shape (n, p_block) (see the module docstring);
    the columns of actuator i are i, i + n_q, i + 2 n_q, …"""
    d = data.direction
    a = np.abs(data.dq)
    a = a / np.where(a.std(axis=0) > 0, a.std(axis=0), 1.0)
    rho = reversals(data)
    qp = _z(data.q_prev)
    step = np.hstack([d * a, d * a**2, a, rho, rho * d, rho * d * a])
    prev = np.hstack([qp, d * qp])
    return {"last step (direction × length, reversal)": step, "previous state": prev,
            "play operators": play_deviations(data)}


def _base(data: DiagnosisData) -> np.ndarray:
    """What the history tests are nested beyond: constant, linear pose, directions."""
    return np.column_stack([np.ones(data.n), _z(data.u), data.direction])


def _nested_f(y: np.ndarray, B0: np.ndarray, B1: np.ndarray, k_fitted: int) -> dict | None:
    """F-test of y on [B0, B1] against B0; None when it has no degrees of freedom."""
    c0, _, r0, _ = np.linalg.lstsq(B0, y, rcond=None)
    X = np.hstack([B0, B1])
    c1, _, r1, _ = np.linalg.lstsq(X, y, rcond=None)
    e0, e1 = y - B0 @ c0, y - X @ c1
    rss0, rss1 = float(e0 @ e0), float(e1 @ e1)
    p = int(r1) - int(r0)
    df2 = y.size - int(r1) - max(k_fitted - 1, 0)
    if p < 1 or df2 < 5 or rss1 <= 0:
        return None
    F = ((rss0 - rss1) / p) / (rss1 / df2)
    return {"statistic": float(F), "df": [float(p), float(df2)], "p_value": float(stats.f.sf(F, p, df2)),
            "explained_fraction": float(1.0 - rss1 / rss0) if rss0 > 0 else 0.0}


def history_tests(resid: np.ndarray, data: DiagnosisData, k_fitted: int = 0,
                  weights: np.ndarray | None = None) -> list[dict]:
    """Nested F-tests of the residual against each history block.

    Parameters
    ----------
    resid : ndarray (n,)
        Residual (already weighted if ``weights`` is given).
    data : DiagnosisData
    k_fitted : int
        Mean parameters fitted.
    weights : ndarray (n,), optional
        1/std per row: the regressors are weighted the same way.

    Returns
    -------
    list of dict
        ``{"basis", "statistic", "df", "p_value", "explained_fraction", "per_actuator"}``
        (``per_actuator``: the p-value of the block's columns of each actuator alone, a
        description of where the history acts, not part of the decision).
    """
    w = 1.0 if weights is None else weights[:, None]
    B0 = _base(data) * w
    blocks = history_blocks(data)
    n_q = data.direction.shape[1]
    out = []
    for name, cols in blocks.items():
        t = _nested_f(resid, B0, cols * w, k_fitted)
        if t is None:
            continue
        per = {}
        for i in range(n_q):
            ti = _nested_f(resid, B0, cols[:, i::n_q] * w, k_fitted)
            per[f"{i + 1}"] = None if ti is None else ti["p_value"]
        out.append({"basis": f"history: {name}", **t, "per_actuator": per})
    return out


def periods_um(reading: np.ndarray) -> np.ndarray:
    """The scan's periods (µm of reading): frequencies 1/(span/2) … 1/PERIOD_MIN_UM, spacing 1/(2 span)."""
    span = float(np.ptp(reading))
    if span <= 2 * PERIOD_MIN_UM:
        return np.zeros(0)
    f = np.arange(2.0 / span, 1.0 / PERIOD_MIN_UM, 1.0 / (OVERSAMPLE * span))
    if f.size > MAX_PERIODS:
        f = np.geomspace(f[0], f[-1], MAX_PERIODS)
    return 1.0 / f


def periodic_scan(resid: np.ndarray, data: DiagnosisData, reading: np.ndarray, k_fitted: int = 0,
                  weights: np.ndarray | None = None) -> dict | None:
    """Scan of the residual for a ripple along the predicted reading (Bonferroni over the periods).

    Parameters
    ----------
    resid : ndarray (n,)
        Residual (already weighted if ``weights`` is given).
    data : DiagnosisData
    reading : ndarray (n,)
        The model's predicted reading, µm.
    k_fitted : int
    weights : ndarray (n,), optional

    Returns
    -------
    dict or None
        ``{"basis", "statistic", "df", "p_value" (Bonferroni), "p_single", "period_um",
        "amplitude_um" (in the units of ``resid``: µm when unweighted), "periods_tested"}`` of the
        best period; None when the reading spans too little.
    """
    lam = periods_um(reading)
    if lam.size == 0:
        return None
    w = 1.0 if weights is None else weights[:, None]
    B0 = np.column_stack([np.ones(data.n), _z(data.u)]) * w
    best = None
    for L in lam:
        ph = 2.0 * np.pi * reading / L
        H = np.column_stack([np.sin(ph), np.cos(ph)])
        t = _nested_f(resid, B0, H * w, k_fitted)
        if t is not None and (best is None or t["p_value"] < best[0]["p_value"]):
            best = (t, L, H)
    if best is None:
        return None
    t, L, H = best
    coef, *_ = np.linalg.lstsq(np.hstack([B0, H * w]), resid, rcond=None)
    amp = float(np.hypot(coef[-2], coef[-1]))
    return {"basis": "periodic in the reading", **t, "p_value": float(min(1.0, lam.size * t["p_value"])),
            "p_single": t["p_value"], "period_um": float(L), "amplitude_um": amp, "periods_tested": int(lam.size)}


def _significant(parts: list[dict], alpha: float) -> list[dict]:
    """The history and periodic parts of a structure test significant after Bonferroni over all parts."""
    m = max(len(parts), 1)
    return [t for t in parts if t["basis"].startswith(("history", "periodic")) and m * t["p_value"] < alpha]


def history_findings(parts: list[dict], alpha: float) -> dict:
    """What the leftover depends on beyond the pose, the time and the directions.

    Parameters
    ----------
    parts : list of dict
        ``details["tests"]`` of :func:`~microctl.diagnosis.residuals.structure_f_test`.
    alpha : float
        Level (Bonferroni over the parts).

    Returns
    -------
    dict
        ``{"history": bool, "periodic": bool, "tests": [...significant parts...],
        "depends_on": sentence}``.
    """
    sig = _significant(parts, alpha)
    phrases = []
    for t in sig:
        if t["basis"].startswith("periodic"):
            phrases.append(f"a ripple of {t['amplitude_um']:.2f} µm with a period of {t['period_um']:.1f} µm along "
                           f"the reading (p = {t['p_value']:.1e}), as a gauge's periodic (interpolation) error makes")
            continue
        per = {a: p for a, p in t.get("per_actuator", {}).items() if p is not None}
        strong = sorted((a for a, p in per.items() if len(per) * p < alpha), key=int)
        if not strong and per:
            strong = [min(per, key=per.get)]
        what = t["basis"].split(": ", 1)[1]
        phrases.append(f"the {what} of the moves (p = {t['p_value']:.1e}; strongest on actuator "
                       f"{', '.join(strong)})")
    if phrases:
        sentence = ("The residual depends on how the stage got to the pose, not only on the pose: "
                    + "; ".join(phrases) + ". No vocabulary cause models this (a rate-independent hysteresis "
                    "of the actuators, if the history is the last step's length and reversals); causes that "
                    "the flexible term with these regressors explains as well are withheld from extended.yaml.")
    else:
        sentence = ("The residual has structure in the pose, the time or the directions of approach that no "
                    "vocabulary cause explains.")
    return {"history": any(t["basis"].startswith("history") for t in sig),
            "periodic": any(t["basis"].startswith("periodic") for t in sig), "tests": sig, "depends_on": sentence}


def extra_basis(data: DiagnosisData, parts: list[dict], reading: np.ndarray | None, alpha: float) -> np.ndarray:
    """Columns the flexible term adds when a history or periodic test is significant, shape (n, p).

    The blocks of :func:`history_blocks` whose test is significant, and sin/cos of the best
    period of the periodic scan when it is (``reading``: the predicted reading it was run on)."""
    cols = []
    blocks = history_blocks(data)
    for t in _significant(parts, alpha):
        if t["basis"].startswith("periodic"):
            if reading is not None:
                ph = 2.0 * np.pi * reading / t["period_um"]
                cols += [np.sin(ph)[:, None], np.cos(ph)[:, None]]
            continue
        cols.append(blocks[t["basis"].split(": ", 1)[1]])
    return np.hstack(cols) if cols else np.zeros((data.n, 0))
