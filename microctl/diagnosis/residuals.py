"""Question 1, "what does the model get wrong?": residual size, structure and where it grows.

Tests (all on the residual r = t − t̂ of a fitted mean model, optionally weighted):

- :func:`structure_f_test` — nested F-tests of r against generic bases that know nothing
  about the vocabulary (:func:`generic_blocks`: the monomials of the standardised pose u up
  to degree 3, the last-move direction of every actuator (±1) and its products with u, and
  the time up to degree 3), each beyond a constant (the gauge zero, a nuisance in every
  model): quadratic in u, cubic in u, directions, time, all of them; and the leftover tests
  that look at history (:mod:`microctl.diagnosis.history`: the last step's direction × length,
  reversals, the previous state, each beyond the linear pose and the directions) and at a
  ripple along the predicted reading (Bonferroni over all the tests). Under the null (the model is right, homoscedastic Gaussian noise) each
  F = ((RSS₀−RSS₁)/p) / (RSS₁/(n−p−k)) ~ F(p, n−p−k), exact when only the constant was
  fitted (k = 1; more fitted mean parameters make it approximate).
- :func:`gp_lr_test` — likelihood ratio of a homoscedastic GP (squared-exponential ARD on
  the standardised inputs :func:`gp_inputs`: pose, time, directions of approach) against
  white noise on r: catches smooth structure the polynomial basis misses (a sinusoid, a
  bump, a warm-up with a time constant). The lengthscales are not identified under the
  null, so its χ² reference uses 2 (d + 1) degrees of freedom (conservative; calibrated
  on clean data in ``scripts/diagnosis_confusion.py``).
- :func:`breusch_pagan` — Koenker's studentised Breusch–Pagan test: n R² of the
  regression of r² on Z (e.g. |Δq_i|) ~ χ²(dim Z).
- :func:`where_analysis` — r against each input, the previous state, time (F-test of a
  cubic in that variable) and each actuator's direction of approach (Welch t-test).
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass, field

import numpy as np
from scipy import stats
from scipy.linalg import cho_factor, cho_solve
from scipy.optimize import minimize

from microctl.diagnosis.data import DiagnosisData
from microctl.diagnosis.history import history_tests, periodic_scan
from microctl.gp.kernels import Kernel


@dataclass(frozen=True)
class Test:
    """Outcome of one test.

    Attributes
    ----------
    name : str
    statistic : float
    p_value : float
    df : tuple of float
        Degrees of freedom of the reference distribution.
    details : dict
        Test-specific extras (plain data).
    """

    name: str
    statistic: float
    p_value: float
    df: tuple = ()
    details: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        """Plain-data form for report.json."""
        return {"test": self.name, "statistic": float(self.statistic), "p_value": float(self.p_value),
                "df": [float(d) for d in self.df], **self.details}


def _z(x: np.ndarray) -> np.ndarray:
    sd = x.std(axis=0)
    return (x - x.mean(axis=0)) / np.where(sd > 0, sd, 1.0)


#: Fewest rows per column of the generic basis: below it the basis drops the products of
#: directions and u and the time's powers (a small data set keeps a usable F-test).
ROWS_PER_COLUMN = 3


def generic_blocks(data: DiagnosisData, degree: int = 3) -> dict[str, np.ndarray]:
    """The vocabulary-free regressors, in named blocks (each shape (n, p_block)).

    ``u^1-2`` (monomials of the standardised pose up to degree 2), ``u^3`` (degree 3 up to
    ``degree``), ``direction`` (each actuator's direction of approach ±1, and its products with
    the monomials of u up to degree 2: a direction-dependent slope or curvature), ``time``
    (the standardised time, its square and cube). With fewer than :data:`ROWS_PER_COLUMN` rows
    per column of the whole basis the direction products and the time's powers are left out.
    """
    u = _z(data.u)
    mono = {}
    for deg in range(1, degree + 1):
        mono[deg] = [np.prod(u[:, c], axis=1) for c in itertools.combinations_with_replacement(range(u.shape[1]), deg)]
    ts = None if data.time_s is None else _z(data.time_s[:, None])[:, 0]
    dirs = list(data.direction.T)
    dir_u = [d * m for d in data.direction.T for m in mono[1] + mono.get(2, [])]
    t_pow = [] if ts is None else [ts**2, ts**3]
    low = sum(len(mono[d]) for d in mono) + len(dirs) + (ts is not None)
    rich = data.n >= ROWS_PER_COLUMN * (1 + low + len(dir_u) + len(t_pow))
    blocks = {"u^1-2": np.column_stack(mono[1] + mono.get(2, []))}
    if degree >= 3:
        blocks["u^3"] = np.column_stack([m for d in range(3, degree + 1) for m in mono[d]])
    blocks["direction"] = np.column_stack(dirs + (dir_u if rich else []))
    if ts is not None:
        blocks["time"] = np.column_stack([ts] + (t_pow if rich else []))
    return blocks


def generic_basis(data: DiagnosisData, degree: int = 3) -> np.ndarray:
    """Intercept and every block of :func:`generic_blocks`, shape (n, p): the flexible term's basis."""
    return np.column_stack([np.ones(data.n), *generic_blocks(data, degree).values()])


#: The nested F-tests of :func:`structure_f_test`: name -> blocks of :func:`generic_blocks`
#: (None: all of them).
#: Several small tests keep the power for low-order structure (a curvature) that one test on
#: all 38 columns would dilute; a Bonferroni correction over them keeps the level.
STRUCTURE_TESTS = {
    "quadratic in u": ("u^1-2",),
    "cubic in u": ("u^1-2", "u^3"),
    "directions (and × u)": ("direction",),
    "time (cubic)": ("time",),
    "all": None,  # every block there is
}


def gp_inputs(data: DiagnosisData) -> np.ndarray:
    """Inputs of the vocabulary-free GP: the pose u, the time (if known) and each actuator's
    direction of approach, shape (n, n_p [+ 1] + n_q)."""
    cols = [data.u] + ([data.time_s[:, None]] if data.time_s is not None else []) + [data.direction]
    return np.hstack(cols)


def _ols_rss(B: np.ndarray, y: np.ndarray) -> tuple[float, int]:
    coef, _, rank, _ = np.linalg.lstsq(B, y, rcond=None)
    r = y - B @ coef
    return float(r @ r), int(rank)


def structure_f_test(resid: np.ndarray, data: DiagnosisData, k_fitted: int = 0,
                     weights: np.ndarray | None = None, reading: np.ndarray | None = None) -> Test:
    """Nested F-tests of the residual against the generic bases of :data:`STRUCTURE_TESTS`.

    Each test compares a constant (the gauge zero, a nuisance of every model) with the
    constant plus the named blocks of :func:`generic_blocks`; under the null (the model is
    right, homoscedastic Gaussian noise) its statistic is F(p, n − p − k). The result's
    p-value is the Bonferroni minimum over the tests (tests whose time block is missing are
    skipped); ``details["tests"]`` lists each.

    Parameters
    ----------
    resid : ndarray, shape (n,)
        Residual (already weighted if ``weights`` is given).
    data : DiagnosisData
    k_fitted : int
        Mean parameters already fitted (reduce the denominator's degrees of freedom).
    weights : ndarray (n,), optional
        1/std per row: the bases are weighted the same way (weighted least squares).
    reading : ndarray (n,), optional
        The model's predicted reading, µm: adds the periodic scan
        (:func:`microctl.diagnosis.history.periodic_scan`). The move-history tests
        (:func:`microctl.diagnosis.history.history_tests`) are always among the tests.
    """
    blocks = generic_blocks(data)
    w = 1.0 if weights is None else weights[:, None]
    one = np.ones((data.n, 1)) * w
    rss0, _ = _ols_rss(one, resid)
    parts = []
    for name, names in STRUCTURE_TESTS.items():
        names = tuple(blocks) if names is None else names
        if any(b not in blocks for b in names):
            continue
        B = np.column_stack([one] + [blocks[b] * w for b in names])
        rss1, p = _ols_rss(B, resid)
        p -= 1
        df2 = data.n - p - max(k_fitted, 1)
        if p < 1 or df2 < 5 or rss1 <= 0:
            continue
        F = ((rss0 - rss1) / p) / (rss1 / df2)
        parts.append({"basis": name, "statistic": float(F), "df": [float(p), float(df2)],
                      "p_value": float(stats.f.sf(F, p, df2)),
                      "explained_fraction": float(1.0 - rss1 / rss0) if rss0 > 0 else 0.0})
    parts += history_tests(resid, data, k_fitted, weights)
    if reading is not None:
        scan = periodic_scan(resid, data, reading, k_fitted, weights)
        if scan is not None:
            parts.append(scan)
    if not parts:
        return Test("F-tests against generic bases", float("nan"), 1.0)
    best = min(parts, key=lambda t: t["p_value"])
    p_all = float(min(1.0, len(parts) * best["p_value"]))
    return Test(f"F-tests against generic bases (Bonferroni over {len(parts)}: "
                + ", ".join(t["basis"] for t in parts) + ")", best["statistic"], p_all,
                tuple(best["df"]), {"tests": parts, "smallest": best["basis"]})


def breusch_pagan(resid: np.ndarray, Z: np.ndarray, name: str = "Breusch-Pagan (Koenker)") -> Test:
    """Koenker's studentised Breusch–Pagan test of r² against Z.

    Parameters
    ----------
    resid : ndarray, shape (n,)
    Z : ndarray, shape (n, m)
        Variance regressors (an intercept is added).

    Returns
    -------
    Test
        LM = n R² ~ χ²(m).
    """
    n = resid.size
    e2 = resid**2
    X = np.column_stack([np.ones(n), Z])
    coef, _, rank, _ = np.linalg.lstsq(X, e2, rcond=None)
    fitted = X @ coef
    ss_tot = float(np.sum((e2 - e2.mean()) ** 2))
    r2 = 1.0 - float(np.sum((e2 - fitted) ** 2)) / ss_tot if ss_tot > 0 else 0.0
    lm = n * r2
    df = max(rank - 1, 1)
    return Test(name, lm, float(stats.chi2.sf(lm, df)), (df,), {"r2": r2})


# ---- homoscedastic GP against white noise -------------------------------------------


def _gp_nll(theta: np.ndarray, X: np.ndarray, y: np.ndarray) -> tuple[float, np.ndarray]:
    """Negative log marginal likelihood of an SE-ARD GP + white noise and its gradient.

    θ = [log ℓ_1..d, log σ_f², log σ_n²]; K = k(X, X) + σ_n² I with the package's one SE kernel
    (:class:`microctl.gp.kernels.Kernel`); ∂(−log p)/∂θ = −½ tr((ααᵀ − K⁻¹) ∂K/∂θ), α = K⁻¹ y
    (Rasmussen & Williams eq. 5.9).
    """
    d = X.shape[1]
    k = Kernel(theta[:d], float(theta[d]))
    sn2 = float(np.exp(theta[d + 1]))
    Kse = k.se(X, X)
    K = Kse + sn2 * np.eye(len(y))
    try:
        c = cho_factor(K, lower=True)
    except np.linalg.LinAlgError:
        return 1e10, np.zeros_like(theta)
    alpha = cho_solve(c, y)
    nll = 0.5 * y @ alpha + np.sum(np.log(np.diag(c[0]))) + 0.5 * len(y) * np.log(2 * np.pi)
    W = np.outer(alpha, alpha) - cho_solve(c, np.eye(len(y)))
    g = np.empty_like(theta)
    g[: d + 1] = -k.grad_traces(0.5 * W, Kse, X)  # lengthscales and signal variance
    g[d + 1] = -0.5 * sn2 * np.trace(W)
    return float(nll), g


@dataclass(frozen=True)
class GPFit:
    """A homoscedastic GP fitted to a residual (standardised inputs, output in µm).

    Attributes
    ----------
    lengthscales : ndarray (d,)
        In standard deviations of each input.
    signal_std_um, noise_std_um : float
    loglik : float
        Log marginal likelihood.
    """

    lengthscales: np.ndarray
    signal_std_um: float
    noise_std_um: float
    loglik: float
    x_mean: np.ndarray | None = None
    x_std: np.ndarray | None = None

    def kernel(self, Xa: np.ndarray, Xb: np.ndarray | None = None) -> np.ndarray:
        """Signal covariance k(Xa, Xb) in µm² (inputs in the fit's original units), shape (n_a, n_b)."""
        za = (Xa - self.x_mean) / self.x_std
        zb = za if Xb is None else (Xb - self.x_mean) / self.x_std
        return Kernel(np.log(self.lengthscales), 2.0 * float(np.log(self.signal_std_um))).se(za, zb)


#: Largest number of residuals the GP tests use (a seeded subset beyond; O(n³) per evaluation).
GP_MAX_POINTS = 250


def fit_gp(X: np.ndarray, y: np.ndarray, max_points: int = GP_MAX_POINTS, seed: int = 0) -> GPFit:
    """Maximise the marginal likelihood of an SE-ARD GP + noise on (X, y).

    Parameters
    ----------
    X : ndarray, shape (n, d)
    y : ndarray, shape (n,)
    max_points : int
        Larger data sets are subsampled (seeded) to this many points.
    """
    rng = np.random.default_rng(seed)
    if len(y) > max_points:
        idx = rng.choice(len(y), max_points, replace=False)
        X, y = X[idx], y[idx]
    x_mean, x_sd = X.mean(axis=0), X.std(axis=0)
    x_sd = np.where(x_sd > 0, x_sd, 1.0)
    Xs = (X - x_mean) / x_sd
    scale = float(np.std(y)) or 1.0
    ys = (y - y.mean()) / scale
    d = X.shape[1]
    bounds = [(np.log(0.05), np.log(30.0))] * d + [(-12.0, 3.0), (-12.0, 1.0)]
    best = None
    # the long start with most variance in the signal reaches binary inputs (directions) and a
    # structure in one input among many before the optimiser drops the signal
    for ls0, f0 in ((1.0, 0.3), (0.3, 0.5), (3.0, 0.7)):
        x0 = np.concatenate([np.full(d, np.log(ls0)), [np.log(f0), np.log(1 - f0)]])
        res = minimize(_gp_nll, x0, args=(Xs, ys), jac=True, method="L-BFGS-B", bounds=bounds,
                       options={"maxiter": 100})
        if best is None or res.fun < best.fun:
            best = res
    th = best.x
    # log-likelihood in the original units: subtract n log(scale)
    ll = -best.fun - len(ys) * np.log(scale)
    return GPFit(np.exp(th[:d]), float(np.sqrt(np.exp(th[d]))) * scale, float(np.sqrt(np.exp(th[d + 1]))) * scale, ll,
                 x_mean, x_sd)


def gp_lr_test(resid: np.ndarray, X: np.ndarray, seed: int = 0) -> tuple[Test, GPFit]:
    """Likelihood-ratio test of a homoscedastic GP against white noise on the residual.

    Parameters
    ----------
    resid : ndarray, shape (n,)
    X : ndarray, shape (n, d)
        GP inputs (e.g. the pose u).

    Returns
    -------
    Test
        LR = 2 (log p_GP − log p_white) on at most :data:`GP_MAX_POINTS` residuals (a seeded
        subset); reference χ²(2 (d + 1)) (see the module docstring).
    GPFit
    """
    if resid.size > GP_MAX_POINTS:  # the same (seeded) subset for both likelihoods
        idx = np.random.default_rng(seed).choice(resid.size, GP_MAX_POINTS, replace=False)
        X, resid = X[idx], resid[idx]
    gp = fit_gp(X, resid, seed=seed)
    r = resid - resid.mean()
    n = r.size
    ll0 = -0.5 * n * (np.log(2 * np.pi * np.mean(r**2)) + 1.0)
    lr = max(2.0 * (gp.loglik - ll0), 0.0)
    df = 2 * (X.shape[1] + 1)
    return Test("GP likelihood ratio against white noise", lr, float(stats.chi2.sf(lr, df)), (df,),
                {"gp_signal_std_um": gp.signal_std_um, "gp_noise_std_um": gp.noise_std_um,
                 "gp_lengthscales_sd": [float(v) for v in gp.lengthscales]}), gp


# ---- where does the residual grow ---------------------------------------------------


def where_variables(data: DiagnosisData, stage_names: tuple[str, ...], dof: tuple[str, ...], tool: str) -> dict:
    """Continuous variables the residual is examined against: name -> (n,) array."""
    out = {f"u_{d}": data.u[:, j] for j, d in enumerate(dof)}
    out[f"{tool}_prev"] = data.t_prev
    for i, a in enumerate(stage_names):
        out[f"{a}_prev"] = data.q_prev[:, i]
    if data.time_s is not None:
        out["time_s"] = data.time_s
    return out


def where_units(dof: tuple[str, ...], actuator_names: tuple[str, ...], tool: str) -> dict:
    """Unit of each variable of :func:`where_variables` (for figure axes)."""
    out = {f"u_{d}": ("mrad" if d.startswith("r") else "µm") for d in dof}
    out[f"{tool}_prev"] = "µm"
    out.update({f"{a}_prev": "µm" for a in actuator_names})
    out["time_s"] = "s"
    return out


def where_analysis(resid: np.ndarray, data: DiagnosisData, actuator_names: tuple[str, ...],
                   dof: tuple[str, ...], tool: str) -> list[dict]:
    """Residual against each input, previous state, time and direction of approach.

    Returns
    -------
    list of dict
        ``{"variable", "test", "statistic", "p_value", "effect_um"}``: for continuous
        variables an F-test of a cubic in the variable (effect = rms of the fitted cubic),
        for each actuator's direction a Welch t-test of r between last-moved-up and -down
        moves (effect = difference of the means).
    """
    out = []
    n = resid.size
    r = resid - resid.mean()
    rss0 = float(r @ r)
    for name, v in where_variables(data, actuator_names, dof, tool).items():
        x = _z(v[:, None])[:, 0]
        B = np.column_stack([np.ones(n), x, x**2, x**3])
        rss1, p = _ols_rss(B, resid)
        p = p - 1
        if p < 1 or rss1 <= 0:
            continue
        F = ((rss0 - rss1) / p) / (rss1 / (n - p - 1))
        out.append({"variable": name, "test": "F-test of a cubic", "statistic": float(F),
                    "p_value": float(stats.f.sf(F, p, n - p - 1)), "effect_um": float(np.sqrt(max(rss0 - rss1, 0) / n))})
    for i, a in enumerate(actuator_names):
        up = resid[data.direction[:, i] > 0]
        down = resid[data.direction[:, i] < 0]
        if len(up) < 3 or len(down) < 3:
            continue
        t = stats.ttest_ind(up, down, equal_var=False)
        out.append({"variable": f"direction_{a}", "test": "Welch t-test up vs down", "statistic": float(t.statistic),
                    "p_value": float(t.pvalue), "effect_um": float(up.mean() - down.mean())})
    return out
