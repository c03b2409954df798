"""The dictionary of physical noise sources a piezo stage may have, and their selection by the data.

The noise variance of a move is modelled as a floor plus independent sources (their variances
add; :mod:`microctl.gp.shaped_features` eq. 1). Which sources a stage has is not assumed: the
candidates below are computed from the stage model, and the data select among them.

Candidates, per actuator i (x = [s; u], s = [t_prev; q_prev], eq. 3; q_i = K_i u, eq. 12;
dq_i = K_i u - q_i,prev). They act on x followed by the move's context c (n_q: each actuator's
last direction of motion, +1 or -1, :mod:`microctl.models.direction`), which only the ``rev``
sources read; a model that selects none of them is trained on x alone:

``dq<i>:sq``       dq_i^2                      stick-slip whose std grows with the step
``dq<i>:abs``      |dq_i| (smoothed)           creep / settling whose variance grows with the step
``dq<i>:sat``      dq_i^2 / (dq_i^2 + s^2)     stiction that saturates after a few µm (s = 2 µm;
                                               ``sat@1`` and ``sat@4``: s = 1 and 4 µm, creep
                                               whose random part saturates sooner or later)
``dq<i>:step@d``   a smooth step in |dq_i| at d  a breakaway: small steps taken up elastically,
                                               a slip of fixed size beyond d (d = 2, 4 µm)
``dq<i>:up``       dq_i^2 on extending moves   direction-dependent slip (one sign of the step)
``dq<i>:down``     dq_i^2 on retracting moves
``dq<i>:rev@s``    dq_i^2/(dq_i^2 + s^2) where   hysteresis: the turning point of a minor loop is
                   the step reverses the         not repeatable, a move that goes on in the same
                   actuator's last direction     direction is (s = 1, 4 µm); reads the move's
                                                 context c_i (:mod:`microctl.models.direction`)
``q<i>:bump@c``    a Gaussian bump in q_i      a rough patch of the stroke centred at c (5 centres
                                               over the range, width range/10)
``q<i>:ext``       ((q_i - lo) / range)^2      scatter growing with the extension (drive voltage)
``f<i>:light``     exp(-F_i(u) / F_s)          scatter growing as ball i's contact force F_i
                                               falls (F_i linear in u while all balls are loaded,
                                               from the contact model; F_s = mean preload per
                                               ball / 4)

and per coordinate c of the platform's pose (u = [z, rx, ry] for Table I; the previous pose
u_prev = K^+ q_prev, K^+ the pseudo-inverse of eq. 12's K):

``d<c>:sq``        (u_c - u_prev,c)^2          slip of the platform itself growing with how far
                                               it moves in c whichever actuators move it (a
                                               flexure hinge or guide with a dry-friction contact
                                               slips by a fraction of its rotation)
``<c>:sq``         u_c^2                       scatter growing with the pose's distance from
                                               level in c (a gauge over a tilted target)

The ``f<i>:light`` candidates read the CAD contact model. On a stage whose CAD geometry shares
the preload evenly among the balls at every pose (Table I: four balls symmetric about the axis,
so commands q = K u never load the platform's twist mode), they are nearly constant over the
workspace and describe almost nothing. A ball whose actual load does move with the pose there (a
worn seat that sits it low, unequal actuator gains: both load the twist mode through heights the
CAD model does not have) is described by the tilt source of :func:`select_features` alone, a
scatter growing exponentially along a direction of the pose that the data choose.

Selection (:func:`select_features`) is forward and evidence-based with a multiple-testing
discipline: on the residual of the mean correction, r ~ N(0, c_0 + sum_S c_j phi_j(x)) with
c >= 0 is fitted by maximum likelihood; among the candidates significant at family-wise level
``alpha`` over the candidates still in play, the one that raises the maximised log-likelihood
most beyond the BIC's gain is added, until none is significant. The p-values gate the entry
(under the current fit the chance that any candidate passes is at most ``alpha``, whichever
passing one is then taken) but do not rank: they rest on the profiled gains, which hold the
current sources' proportions and so understate a source that takes over part of the floor (a
second stiction actuator whose scatter the floor had absorbed, refitted worth twice a false
source's gain, lost the entry to it by a p-value a thousandth lower when the smaller p-value
ranked). The candidates are strongly correlated (five shapes of one actuator's step describe
nearly the same thing), so a Bonferroni correction over their number would be far too strict;
the family-wise p-value is instead the max-statistic (Westfall-Young) one: each candidate's
profiled log-likelihood gain (:func:`_profile_gains`) is referred to the distribution of the
*largest* gain over all candidates in play, simulated under the current fit (residuals drawn from
N(0, v(x)) at the training inputs, :data:`NULL_DRAWS` draws, a fixed seed), which accounts for
their correlation exactly. On a stage whose scatter is the gauge alone, nothing is selected
with probability >= 1 - alpha (tested). Once no candidate enters, each selected source's shape
is re-chosen among the shapes of its quantity with the others in the model (an exchange adds no
parameter, so the entry tests stand; :func:`_refine_shapes`). The tilt source (below) keeps the
conservative Bonferroni correction (its direction is not identified under the null).
"""


from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from microctl.gp.shaped_features import ShapedFeatures
from microctl.models.afm import AnalyticForwardModel
from microctl.models.noise_inputs import step_map
from microctl.stage.causes import Effects
from microctl.stage.physics import ball_heights, contact_model
from microctl.util.bic import bic_penalty
from microctl.util.blas import single_thread_blas

__all__ = ["candidate_features", "context_width", "ball_load_map", "select_features", "Selection", "alternatives", "quantity",
           "fit_variance_with", "variance_design"]

#: Residual draws under the current fit for the max-statistic p-values, and their seed; the grid
#: of a candidate's share (times the mean current variance) its profiled gain is maximised over.
NULL_DRAWS, NULL_SEED = 1000, 20_261_124
PROFILE_RATIOS = np.concatenate([np.logspace(-2.5, 2.5, 26)])
#: Stroke-patch centres per actuator range, and width as a fraction of the range.
N_BUMPS, BUMP_WIDTH = 5, 0.1
#: Smoothing of |dq| and of the direction switch, µm; stiction saturation step, µm.
STEP_EPS_UM, SAT_UM = 0.2, 2.0
#: The other saturation steps, and the breakaway steps with the breakaway's width, µm.
SAT_MORE_UM, BREAKAWAY_UM, BREAKAWAY_WIDTH_UM = (1.0, 4.0), (2.0, 4.0), 0.5
#: Saturation steps of the reversal sources, µm (as ``sat@1``, ``sat@4``).
REVERSAL_SAT_UM = (1.0, 4.0)


def context_width(afm: AnalyticForwardModel) -> int:
    """Columns of the move's context after x = [s; u] (each actuator's last direction)."""
    return afm.n_q


def ball_load_map(afm: AnalyticForwardModel) -> tuple[np.ndarray, np.ndarray]:
    """Contact forces of the CAD stage, linear in the pose while every ball is loaded.

    With every ball in contact the elastic equilibrium is the minimiser of a quadratic, so the
    pose and each ball's force ``F_i = k_c (h_i - a_i . p)`` are affine in the commands h = (n.d) q,
    q = K u (eq. 12).

    Returns
    -------
    f0 : ndarray, shape (n_q,)
        Forces at u = 0, N.
    B : ndarray, shape (n_q, n_p)
        dF/du, N per unit pose.
    """
    model = contact_model(afm.stage, Effects())  # the CAD stage: no corrections, no defects
    A, kc = model.A, model.k_c
    H = kc * A.T @ A + np.diag(model.k_h)
    n_p = afm.n_p
    U = np.vstack([np.zeros(n_p), np.eye(n_p)])
    h = ball_heights(model, U @ afm.K.T)
    P = np.linalg.solve(H, (model.f_preload[:, None] + kc * A.T @ h.T)).T
    F = kc * (h - P @ A.T)
    return F[0], (F[1:] - F[0]).T


def candidate_features(afm: AnalyticForwardModel, *, context: bool = False) -> ShapedFeatures:
    """Every candidate source of the module docstring for this stage (scale 1; see
    :meth:`ShapedFeatures.rescaled`).

    ``context=False``: the sources of x = [s; u] alone (no ``rev``), on its n_s + n_p columns;
    True: all of them, on x followed by the move's context (:func:`context_width` columns)."""
    n_p, n_s = afm.n_p, afm.n_s
    d = n_s + n_p + (context_width(afm) if context else 0)  # x = [s; u] (and the move's context c)
    pose = slice(n_s, n_s + n_p)
    lo, hi = afm.stage.range_lo, afm.stage.range_hi
    f0, B = ball_load_map(afm)
    f_s = max(float(np.mean(np.abs(f0))) / 4.0, 1e-9)
    rows, offs, shapes, params, names, gates = [], [], [], [], [], []

    def add(a, b, shape, p, name, gate=None):
        rows.append(a)
        offs.append(b)
        shapes.append(shape)
        params.append(p)
        names.append(name)
        gates.append(np.zeros(d) if gate is None else gate)

    steps = step_map(afm)  # dq_i = K_i u - q_i,prev on x = [s; u]
    for i, nm in enumerate(afm.actuator_names):
        step = np.zeros(d)
        step[:n_s + n_p] = steps[i]
        end = np.zeros(d)
        end[pose] = afm.K[i]
        add(step, 0.0, "sq", (0.0, 0.0), f"d{nm}:sq")
        add(step, 0.0, "abs", (STEP_EPS_UM, 0.0), f"d{nm}:abs")
        add(step, 0.0, "sat", (SAT_UM, 0.0), f"d{nm}:sat")
        for s_um in SAT_MORE_UM:
            add(step, 0.0, "sat", (s_um, 0.0), f"d{nm}:sat@{s_um:g}")
        for d_um in BREAKAWAY_UM:
            add(step, 0.0, "step", (d_um, BREAKAWAY_WIDTH_UM), f"d{nm}:step@{d_um:g}")
        add(step, 0.0, "up", (STEP_EPS_UM, 0.0), f"d{nm}:up")
        add(step, 0.0, "down", (STEP_EPS_UM, 0.0), f"d{nm}:down")
        if context:
            last = np.zeros(d)
            last[n_s + n_p + i] = 1.0  # c_i
            for s_um in REVERSAL_SAT_UM:
                add(step, 0.0, "rev", (s_um, STEP_EPS_UM), f"d{nm}:rev@{s_um:g}", last)
        span = max(float(hi[i] - lo[i]), 1e-9)
        for k in range(N_BUMPS):
            c = float(lo[i] + (k + 0.5) * span / N_BUMPS)
            add(end, 0.0, "bump", (c, BUMP_WIDTH * span), f"{nm}:bump@{c:g}")
        add(end / span, -float(lo[i]) / span, "sq", (0.0, 0.0), f"{nm}:ext")
        load = np.zeros(d)
        load[pose] = -B[i] / f_s
        add(load, -float(f0[i]) / f_s, "exp", (0.0, 0.0), f"f{i + 1}:light")
    K_pinv = np.linalg.pinv(afm.K)  # u_prev = K^+ q_prev (exact on the reachable set)
    for j, c in enumerate(afm.dof):
        step = np.zeros(d)
        step[1:n_s] = -K_pinv[j]
        step[n_s + j] = 1.0
        end = np.zeros(d)
        end[n_s + j] = 1.0
        add(step, 0.0, "sq", (0.0, 0.0), f"d{c}:sq")
        add(end, 0.0, "sq", (0.0, 0.0), f"{c}:sq")
    return ShapedFeatures(np.array(rows), np.array(offs), tuple(shapes), np.array(params), np.ones(len(rows)),
                          tuple(names), np.array(gates) if context else None)


@dataclass(frozen=True)
class Selection:
    """What :func:`select_features` chose and why.

    Attributes
    ----------
    indices : tuple of int
        Selected candidates, in the order they entered.
    names : tuple of str
    gains : tuple of float
        Log-likelihood gain of each when it entered (nats), plus what an exchange of its shape
        added (``swaps``).
    thresholds : tuple of float
        The gain each needed at least (the BIC's half log n per parameter).
    loglik : float
        Maximised log-likelihood of the final set.
    tilt : ndarray, shape (k,), or None
        The direction of the tilt source, when it entered (its name is ``"tilt"``, last).
    p_values : tuple of float
        The adjusted p-value of each when it entered (it had to be below ``alpha``).
    swaps : tuple of (str, str)
        Shapes the refinement after the forward pass exchanged (entered as, kept as); a swapped
        source's gain includes the likelihood the exchange added (:func:`_refine_shapes`).
    """

    indices: tuple[int, ...]
    names: tuple[str, ...]
    gains: tuple[float, ...]
    thresholds: tuple[float, ...]
    loglik: float
    tilt: np.ndarray | None = None
    p_values: tuple[float, ...] = ()
    swaps: tuple[tuple[str, str], ...] = ()


def alternatives(residual: np.ndarray, variance: np.ndarray, Phi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each candidate source added alone to the fitted noise model, at its best size.

    For candidate j the variance ``a (v + rho phi_j)`` (v the fitted model's noise variance at
    the training moves, its shape held, with a free scale a: closed-form ``a = mean(r^2 / (v +
    rho phi_j))``) is profiled over rho >= 0 on the grid :data:`PROFILE_RATIOS` times
    mean(v) / mean(phi_j) (and rho = 0): :func:`_profile_gains`' profile, keeping where it peaks.

    Parameters
    ----------
    residual : ndarray, shape (n,)
        Residual of the mean correction at the training moves.
    variance : ndarray, shape (n,)
        The fitted noise variance there (µm²).
    Phi : ndarray, shape (n, P)
        The candidates at the training moves (non-negative).

    Returns
    -------
    coef : ndarray, shape (P,)
        The source's coefficient ``a rho`` at the best rho (µm² per unit of phi_j; 0 when the
        data prefer none).
    gain : ndarray, shape (P,)
        Its log-likelihood gain over rho = 0 (nats, >= 0).
    """
    r2 = np.asarray(residual, dtype=float) ** 2
    v = np.asarray(variance, dtype=float)
    Phi = np.asarray(Phi, dtype=float)
    n = r2.size
    m = np.maximum(Phi.mean(axis=0), 1e-300)  # (P,): each candidate at unit mean, as the grid assumes
    base = -0.5 * n * np.log(np.mean(r2 / v))  # rho = 0 (the constant terms cancel)
    gain, coef = np.zeros(Phi.shape[1]), np.zeros(Phi.shape[1])
    for rho, (inv_v, logdet) in zip(float(np.mean(v)) * PROFILE_RATIOS, _profile_terms(v, Phi / m)):
        a = (r2 @ inv_v) / n  # (P,)
        ll = -0.5 * (n * np.log(a) + logdet) - base
        better = ll > gain
        gain = np.where(better, ll, gain)
        coef = np.where(better, a * rho / m, coef)
    return coef, gain


def _fit_variance(r2: np.ndarray, Phi: np.ndarray) -> tuple[float, np.ndarray]:
    """Max over c >= 0 of sum -1/2 (log v + r^2 / v), v = c_0 + Phi c (c_0 > 0). Returns the
    log-likelihood (without the 2 pi constant) and c = (c_0, c_1..)."""
    n, p = Phi.shape
    D = np.hstack([np.ones((n, 1)), Phi])
    floor = 1e-6 * float(np.mean(r2)) + 1e-300

    def f(c):
        v = D @ c
        ll = -0.5 * np.sum(np.log(v) + r2 / v)
        g = -0.5 * D.T @ (1.0 / v - r2 / (v * v))
        return -ll, -g

    c0 = np.concatenate([[float(np.mean(r2))], np.full(p, 1e-3 * float(np.mean(r2)))])
    from scipy import optimize  # here, not at import: `microctl solve` reads the candidates without scipy
    res = optimize.minimize(f, c0, jac=True, method="L-BFGS-B",
                            bounds=[(floor, None)] + [(0.0, None)] * p, options={"maxiter": 500})
    return -float(res.fun), res.x


def _fit_tilt(r2: np.ndarray, Phi: np.ndarray, Z: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Max log-likelihood of v = c_0 + Phi c + c_t exp(w . z) over c >= 0 and a free direction w:
    a source whose variance grows exponentially along a direction of the pose that the data choose
    (a ball unloading where the actual geometry, unlike the CAD one, tilts its load). Started from
    the least-squares slope of log r^2 on z. Returns (log-likelihood, c = (c_0, c, c_t), w)."""
    n, p = Phi.shape
    k = Z.shape[1]
    D = np.hstack([np.ones((n, 1)), Phi])
    Zc = np.hstack([np.ones((n, 1)), Z])
    w0 = np.linalg.lstsq(Zc, np.log(r2 + 1e-12 * np.mean(r2)), rcond=None)[0][1:]
    floor = 1e-6 * float(np.mean(r2)) + 1e-300
    scale = float(np.mean(r2))

    def f(th):
        c, ct, w = th[: p + 1], th[p + 1], th[p + 2:]
        e = np.exp(np.clip(Z @ w, -50, 50))
        v = D @ c + ct * e
        a = 1.0 / v - r2 / (v * v)
        ll = -0.5 * np.sum(np.log(v) + r2 / v)
        g = -0.5 * np.concatenate([D.T @ a, [e @ a], Z.T @ (a * ct * e)])
        return -ll / n, -g / n

    best = (-np.inf, None, None)
    for w_init in (w0, 0.5 * w0):
        th0 = np.concatenate([[0.5 * scale], np.full(p, 1e-3 * scale), [0.5 * scale / max(np.mean(np.exp(Z @ w_init)), 1e-12)],
                              w_init])
        from scipy import optimize  # here, not at import: `microctl solve` reads the candidates without scipy
        res = optimize.minimize(f, th0, jac=True, method="L-BFGS-B",
                                bounds=[(floor, None)] + [(0.0, None)] * (p + 1)
                                + [(-TILT_MAX_SLOPE, TILT_MAX_SLOPE)] * k,
                                options={"maxiter": 500})
        ll = -float(res.fun) * n
        if ll > best[0]:
            best = (ll, res.x[: p + 2], res.x[p + 2:])
    return best


def _profile_terms(v: np.ndarray, Phi: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    """For each ratio of :data:`PROFILE_RATIOS`: ``1 / V`` (n, P) and ``sum_i log(V_i / v_i)`` (P,)
    with ``V = v + rho phi_j``, the parts of :func:`_profile_gains` that do not depend on the
    residuals (computed once for the observed residual and every null draw)."""
    rhos = float(np.mean(v)) * PROFILE_RATIOS
    terms = []
    for rho in rhos:
        V = v[:, None] + rho * Phi  # (n, P)
        terms.append((1.0 / V, np.sum(np.log(V / v[:, None]), axis=0)))
    return terms


def _profile_gains(R2: np.ndarray, v: np.ndarray, Phi: np.ndarray,
                   terms: list[tuple[np.ndarray, np.ndarray]] | None = None) -> np.ndarray:
    """Log-likelihood gain of each candidate entering the current variance, profiled.

    The variance with candidate j is ``a (v + rho phi_j)``: the current fit's shape v (its
    sources' proportions held) times a free scale a, plus the candidate at ratio rho >= 0. For a
    fixed rho the best scale is closed-form, ``a = mean(r^2 / (v + rho phi_j))``, so the profile
    log-likelihood over a grid of rho (:data:`PROFILE_RATIOS` times mean(v)) is a few matrix
    products for every candidate and every residual vector at once.

    Parameters
    ----------
    R2 : ndarray, shape (b, n)
        Squared residuals (b residual vectors).
    v : ndarray, shape (n,)
        Current variance at the training inputs.
    Phi : ndarray, shape (n, P)
    terms : list, optional
        :func:`_profile_terms` of (v, Phi), when the caller has them.

    Returns
    -------
    ndarray, shape (b, P)
        max over rho of the profile log-likelihood minus its value at rho = 0 (>= 0).
    """
    n = len(v)
    base = -0.5 * n * np.log(np.mean(R2 / v, axis=1))  # rho = 0 (the constant terms cancel)
    best = np.zeros((R2.shape[0], Phi.shape[1]))
    for inv_v, logdet in (terms if terms is not None else _profile_terms(v, Phi)):
        a = (R2 @ inv_v) / n  # (b, P)
        ll = -0.5 * (n * np.log(a) + logdet)
        best = np.maximum(best, ll - base[:, None])
    return best


def _max_stat_pvalues(r2: np.ndarray, v: np.ndarray, Phi: np.ndarray, *, with_gains: bool = False
                      ) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
    """Family-wise p-value of each candidate (columns of Phi): the probability, under the current
    fit, that the largest profiled gain (:func:`_profile_gains`) over all candidates reaches
    the candidate's observed one (Westfall-Young max-statistic; :data:`NULL_DRAWS` residual
    vectors drawn from N(0, v) at the training inputs).

    Returns
    -------
    ndarray, shape (P,)
        ``(1 + #{max* >= T_j}) / (1 + NULL_DRAWS)``; with ``with_gains`` also the observed
        profiled gains T_j, shape (P,).
    """
    terms = _profile_terms(v, Phi)
    obs = _profile_gains(r2[None, :], v, Phi, terms)[0]
    rng = np.random.default_rng(NULL_SEED)
    n = len(v)
    block = max(1, min(NULL_DRAWS, 500_000 // max(n, 1)))
    maxima = []
    with single_thread_blas():  # microctl.util.blas: with another process busy, a threaded BLAS spins
        for b in range(0, NULL_DRAWS, block):
            z = rng.standard_normal((min(block, NULL_DRAWS - b), n))
            maxima.append(_profile_gains(z * z * v, v, Phi, terms).max(axis=1))
    mx = np.sort(np.concatenate(maxima))
    exceed = NULL_DRAWS - np.searchsorted(mx, obs * (1 - 1e-12), side="left")
    p = (1.0 + exceed) / (1.0 + NULL_DRAWS)
    return (p, obs) if with_gains else p


def select_features(residual: np.ndarray, candidates: np.ndarray, names, *, tilt_inputs: np.ndarray | None = None,
                    alpha: float = 0.05, max_features: int = 6, refits: int = 4) -> Selection:
    """Forward selection of variance features (module docstring).

    At each step the candidates are ranked by their profiled log-likelihood gain at the current fit
    (:func:`_profile_gains`, which the p-values refer to the null; a local score statistic ranks a
    step's saturating shapes far below their gain); the ``refits`` best are fitted by maximum
    likelihood. With ``tilt_inputs`` one more candidate is a source growing exponentially along a
    direction of those inputs that the fit chooses (:func:`_fit_tilt`; k + 1 parameters). Entry
    needs an adjusted p-value below ``alpha`` and an exact gain of at least the BIC's (half log n
    per parameter): a fixed feature's p-value is the max-statistic one over the candidates in play
    (:func:`_max_stat_pvalues`, times 1.25 while the tilt is in play); the tilt's likelihood-ratio
    statistic is referred to chi2 with k + 1 degrees of freedom, Bonferroni over every candidate
    in play. Of those passing, the largest exact gain beyond the BIC's enters (ties: the smaller
    p-value; the module docstring says why). Then each selected source's shape is re-chosen among
    the candidates of its quantity (:func:`_refine_shapes`).

    Parameters
    ----------
    residual : ndarray, shape (n,)
        Residual of the mean correction at the training inputs.
    candidates : ndarray, shape (n, P)
        Candidate features at the training inputs (non-negative).
    names : sequence of str, length P
    tilt_inputs : ndarray, shape (n, k), optional
        Standardised inputs the tilt may grow along (the pose).
    alpha : float
        Family-wise level of each entry step.
    max_features : int
    refits : int
        Candidates refitted exactly per step.

    Returns
    -------
    Selection
    """
    r2, Phi = np.asarray(residual, dtype=float) ** 2, np.asarray(candidates, dtype=float)
    n, P = Phi.shape
    chosen: list[int] = []
    gains: list[float] = []
    thresholds: list[float] = []
    p_values: list[float] = []
    slots: list[int] = []  # where each of ``chosen`` is in ``gains`` (the tilt has a place there too)
    tilt = None
    ll, c = _fit_variance(r2, Phi[:, :0])
    while len(chosen) + (tilt is not None) < min(max_features, P):
        rest = np.array([j for j in range(P) if j not in chosen])
        m = len(rest) + (tilt_inputs is not None and tilt is None)
        v = c[0] + Phi[:, chosen] @ c[1: 1 + len(chosen)]
        if tilt is not None:
            v = v + c[-1] * np.exp(np.clip(tilt_inputs @ tilt, -50, 50))
        # max-statistic p at level 0.8 alpha while the tilt is in play (weighted Bonferroni: the tilt's own
        # p is Bonferroni over all m, <= 0.2 alpha); the largest profiled gains are refitted exactly
        p_all, profiled = _max_stat_pvalues(r2, v, Phi[:, rest], with_gains=True)
        p_rest = dict(zip(rest.tolist(), p_all * (1.25 if tilt_inputs is not None and tilt is None else 1.0)))
        order = rest[np.argsort(-profiled, kind="stable")][:refits]
        options = []  # (adjusted p, gain, needed gain, what, c, w)
        for j in order:
            lj, cj = fit_variance_with(r2, Phi[:, chosen + [int(j)]], tilt_inputs, tilt)
            g = lj - ll
            options.append((p_rest[int(j)] if g > 0 else 1.0, g, bic_penalty(1, n), int(j), cj, tilt))
        if tilt_inputs is not None and tilt is None:
            options.append(_tilt_option(r2, ll, Phi[:, chosen], tilt_inputs, m))
        passing = [o for o in options if o[0] < alpha and o[1] >= o[2]]
        if not passing:
            break
        best = max(passing, key=lambda o: (o[1] - o[2], -o[0]))  # the exact gain beyond the BIC's ranks
        if best[3] == "tilt":
            tilt = best[5]
        else:
            chosen.append(best[3])
            slots.append(len(gains))
        gains.append(best[1])
        thresholds.append(best[2])
        p_values.append(best[0])
        ll, c = ll + best[1], best[4]
    ll, swaps = _refine_shapes(r2, Phi, names, chosen, gains, slots, ll, tilt_inputs, tilt)
    names_out = tuple(names[j] for j in chosen) + (("tilt",) if tilt is not None else ())
    return Selection(tuple(chosen), names_out, tuple(gains), tuple(thresholds), ll,
                     None if tilt is None else np.asarray(tilt, dtype=float), tuple(p_values), tuple(swaps))


#: Passes of the shape refinement over the selected sources (each pass re-chooses every shape once),
#: and the least rise of the log-likelihood (nats) an exchange must bring (the optimiser's
#: tolerance stays well below it; two shapes equal on the data are not exchanged).
REFINE_PASSES, REFINE_MIN_GAIN = 3, 1e-3


def quantity(name: str) -> str:
    """The physical quantity a candidate is a shape of: its name before ``:`` (``dq3`` for
    ``dq3:sq`` and ``dq3:sat@4``, ``q2`` for the stroke shapes of actuator 2, ``f1``)."""
    return name.split(":", 1)[0]


def _refine_shapes(r2: np.ndarray, Phi: np.ndarray, names, chosen: list[int], gains: list[float], slots: list[int],
                   ll: float, Z: np.ndarray | None, w: np.ndarray | None) -> tuple[float, list[tuple[str, str]]]:
    """Re-choose each selected source's shape among the candidates of its quantity, the others held.

    Forward selection fixes a source's shape when it enters, against the fit of that step: a
    source entered before another actuator's is in the model sees that actuator's scatter in the
    floor, and a shape flat in the step (``abs``) can then beat the right one (``sq``) and keep its
    place although, with both in, the right shape has the higher likelihood (seen on stick-slip
    rigs of scripts/rig_families.py with two actuators). An exchange adds no parameter, so the
    entry tests stand; a shape is exchanged where the maximised log-likelihood rises, until a pass
    exchanges nothing (at most :data:`REFINE_PASSES`). ``chosen`` and ``gains`` (the step gains;
    ``slots``: where each of ``chosen`` is among them) are updated in place.

    Returns
    -------
    loglik : float
        Maximised log-likelihood of the final set.
    swaps : list of (str, str)
        (entered as, kept as) per exchange.
    """
    swaps = []
    for _ in range(REFINE_PASSES):
        changed = False
        for pos, j in enumerate(list(chosen)):
            best_ll, best_k = ll, j
            for k in range(Phi.shape[1]):
                if k in chosen or quantity(names[k]) != quantity(names[j]):
                    continue
                trial = chosen.copy()
                trial[pos] = k
                lk, _ = fit_variance_with(r2, Phi[:, trial], Z, w)
                if lk > best_ll + REFINE_MIN_GAIN:
                    best_ll, best_k = lk, k
            if best_k != j:
                chosen[pos] = best_k
                gains[slots[pos]] += best_ll - ll
                swaps.append((names[j], names[best_k]))
                ll, changed = best_ll, True
        if not changed:
            break
    return ll, swaps


def _tilt_option(r2: np.ndarray, ll: float, Phi: np.ndarray, Z: np.ndarray, m: int) -> tuple:
    """The tilt as an entry option ``(adjusted p, gain, needed gain, "tilt", c, w)`` against the
    current fit (log-likelihood ll, features Phi): its likelihood-ratio statistic referred to chi2
    with k + 1 degrees of freedom, Bonferroni over the m candidates in play."""
    n, k = Z.shape
    lt, ct, w = _fit_tilt(r2, Phi, Z)
    g = lt - ll
    from scipy import stats  # here, not at import: `microctl solve` reads the candidates without scipy
    return (float(stats.chi2.sf(2 * g, k + 1)) * m if g > 0 else 1.0, g, bic_penalty(k + 1, n), "tilt", ct, w)

#: the tilt's slope bound per standardised pose coordinate: its variance grows at most e^4-fold
#: per standard deviation of the training poses (a lightly loaded ball's scatter, planted at 2 in
#: the tests, is well inside; unbounded, the fit can put a spike of variance on one or two
#: outlying rows)
TILT_MAX_SLOPE = 4.0
def _with_tilt(Phi: np.ndarray, Z: np.ndarray | None, w: np.ndarray | None) -> np.ndarray:
    """Phi with the tilt's column exp(Z w) appended when the tilt is in the model."""
    return Phi if w is None else np.hstack([Phi, np.exp(np.clip(Z @ w, -50, 50))[:, None]])


def fit_variance_with(r2: np.ndarray, Phi: np.ndarray, Z: np.ndarray | None,
                      w: np.ndarray | None) -> tuple[float, np.ndarray]:
    """:func:`_fit_variance` with, when ``w`` is given, the tilt exp(Z w) as one more fixed feature.

    Returns
    -------
    loglik : float
    c : ndarray, shape (1 + p [+ 1],)
        Floor, the features' coefficients (and the tilt's); the variance is
        ``variance_design(Phi, Z, w) @ c``.
    """
    if w is None:
        return _fit_variance(r2, Phi)
    return _fit_variance(r2, _with_tilt(Phi, Z, w))


def variance_design(Phi: np.ndarray, Z: np.ndarray | None, w: np.ndarray | None) -> np.ndarray:
    """``[1, Phi (, exp(Z w))]``, shape (n, 1 + p [+ 1]): the variance model's design, whose product
    with :func:`fit_variance_with`'s coefficients is the fitted variance at each row."""
    Phi = np.asarray(Phi, dtype=float)
    return np.hstack([np.ones((Phi.shape[0], 1)), _with_tilt(Phi, Z, w)])
