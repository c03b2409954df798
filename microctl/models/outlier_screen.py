"""Corrupt readings in a training log: found by deletion, named by row, left out of the fit.

A gross error in one reading (a gauge glitch, a reading logged against the wrong command) does
not show as a large residual of the fitted heteroscedastic model: the noise model is free to
raise its variance where the error sits. The noise-source selection picks a source that peaks
there (or the tilt, whose direction the fit chooses), g's GP raises it further, and the row's
standardised residual looks ordinary (masking), while the selected sources are no longer the
stage's (``tests/models/test_outlier_screen.py`` plants such a reading).

The screen therefore judges each suspect row by a variance fitted *without* it:

1. on the residual r of the mean correction and the selected sources' variance model
   ``v = c_0 + sum_j c_j phi_j (+ tilt)`` (:mod:`microctl.models.noise_dictionary`), the rows with
   the largest ``r^2 / v`` and those with the largest ``|r|`` (:data:`SCREEN_TOP` of each: a
   masked row can have an ordinary ``r^2 / v``, never an ordinary ``|r|`` if its error is gross)
   are the suspects;
2. each suspect is judged by the sources selected again on every row but it
   (:func:`sources_without_row`; the selection made with a corrupt reading can hold a source
   that peaks at it, and the other rows keep that source's coefficient when the row alone is
   refitted out); their coefficients are refitted on every other row (the sources and the
   tilt's direction held), and ``z_(-i) = r_i / sqrt(v_(-i)(x_i))`` is its deletion residual:
   under the model it is standard normal whatever row i holds. The tails of step 4 are read
   under the sources selected without all suspects (:func:`screening_sources`);
3. the parametric sources describe a stage's scatter only in part (g's GP models the rest), so
   a suspect is also judged against the scatter of its
   :data:`SCREEN_NEIGHBOURS` nearest moves (in the standardised actuator positions before and
   after the move, which every source of the dictionary is a function of): where their median
   ``r_j^2 / v_(-i)(x_j)`` is above chi2_1's median, the suspect's variance is raised by that
   ratio (never lowered, so a stage the model describes is judged as in step 2);
4. a suspect is found (:func:`screen_rows`) when ``|z_(-i)|`` exceeds the Bonferroni bound of
   family-wise level :data:`SCREEN_ALPHA` over the n rows (two-sided) for the tails the rows
   not suspected show under those sources fitted on them (:func:`tail_bound`: Gaussian when
   they look Gaussian; where a ball lifts off, as on the paper-scale rig, the sources leave a
   scatter with much heavier tails, and a Gaussian bound set aside legitimate moves): a stage
   whose scatter the model describes sets aside no row with probability at most about
   ``SCREEN_ALPHA``;
5. training (:func:`microctl.models.training._screened`) confirms each row this screen finds
   with the whole first model (f, g's GP and its stick-slip prior) refitted without the row: the
   row is set aside only if its residual is beyond the same bound under that model's
   predictive variance too. (The whole model's own residuals cannot give the tails: g's GP
   takes up each large one when it is in the fit, so they look Gaussian while the same rows,
   left out, are far out.)

When more rows than :data:`SCREEN_MAX_SHARE` of the log exceed the bound, the exceedances are
not a few corrupt readings but scatter with heavier tails than the model's (or a noise structure
the dictionary does not hold): then no row is set aside, and the record says so.

Nothing is lost: the log is not changed; the rows set aside and their deletion residuals (the
whole model's) are in the model's ``info["noise_selection"]["screened"]`` and ``microctl train``
prints them by their line in the log file and their ``seq``.
"""

from __future__ import annotations

from dataclasses import dataclass
from statistics import NormalDist

import numpy as np

from microctl.models.noise_dictionary import fit_variance_with, select_features, variance_design

__all__ = ["describe_screen", "fitted_variance", "sources_without_row", "suspect_rows", "screening_sources", "SCREEN_ALPHA", "SCREEN_TOP", "SCREEN_MAX_SHARE", "SCREEN_NEIGHBOURS", "MIN_NU", "Screen",
           "deletion_residuals", "screen_rows", "bonferroni_bound", "max_screened", "tail_bound"]

#: Family-wise level of the screen over a log's rows (two-sided). Chosen before it was measured
#: on the rig families: a legitimate row set aside costs the model a real observation of the
#: stage's scatter, a corrupt one kept costs it the noise model, so the screen is meant for
#: gross errors only.
SCREEN_ALPHA = 1e-3
#: Rows with the largest standardised residual, and rows with the largest residual, whose
#: deletion residual is computed.
SCREEN_TOP = 5
#: Most rows set aside, as a share of the log (at least 1 row); more exceedances: none set aside.
SCREEN_MAX_SHARE = 0.02
#: Nearest moves (in the standardised actuator positions before and after the move) whose
#: scatter a suspect is also judged against (step 3 of the module docstring).
SCREEN_NEIGHBOURS = 20
#: Fewest degrees of freedom :func:`tail_bound` reads from the data (a t with kurtosis 9; towards
#: 2 degrees of freedom the bound would grow without limit and find nothing).
MIN_NU = 5.0
#: Median of chi-squared with one degree of freedom: the median squared standardised residual of
#: moves the variance model describes.
_CHI2_1_MEDIAN = 0.45493642311957283


@dataclass(frozen=True)
class Screen:
    """What :func:`screen_rows` found.

    Attributes
    ----------
    rows : tuple of int
        Rows found (0-based positions in the residual vector; training sets them aside once the
        whole model confirms them).
    z : tuple of float
        Their deletion residuals ``z_(-i)``.
    bound : float
        The bound |z_(-i)| had to exceed (:func:`tail_bound` of the rows not suspected).
    exceeding : int
        Suspects beyond the bound (more than ``rows`` when the share cap withheld them).
    withheld : bool
        True when more rows than the cap exceeded the bound, so none was set aside.
    nu : float
        Degrees of freedom of the tails the bound is for (inf: Gaussian).
    """

    rows: tuple[int, ...]
    z: tuple[float, ...]
    bound: float
    exceeding: int
    withheld: bool = False
    nu: float = float("inf")


def max_screened(n: int) -> int:
    """Most rows of an n-row log the screen sets aside (:data:`SCREEN_MAX_SHARE`, at least 1)."""
    return max(1, int(SCREEN_MAX_SHARE * n))


def bonferroni_bound(n: int, alpha: float = SCREEN_ALPHA) -> float:
    """|z| beyond which one of n standard normal residuals is an outlier at family-wise level alpha."""
    return -float(NormalDist().inv_cdf(alpha / (2.0 * max(int(n), 1))))  # the lower tail: no 1 - tiny


def tail_bound(z: np.ndarray, n: int, alpha: float = SCREEN_ALPHA) -> tuple[float, float]:
    """The Bonferroni bound for n residuals with the tails the bulk of ``z`` shows.

    A stage's scatter need not be Gaussian (where a ball lifts off, the reading is a kink
    averaged over the scatter), and a Gaussian bound then sets aside its legitimate tail. The
    tails are read from the ratio of the 95 % and 50 % quantiles of ``|z|`` (2.906 for a
    Gaussian; gross rows raise the 95 % quantile, so the caller leaves out the rows it suspects):
    the Student t whose ratio matches gives the bound, at unit variance,
    ``t_nu.isf(alpha / 2n) sqrt((nu - 2) / nu)``. A ratio at or below the Gaussian's gives the
    Gaussian bound (:func:`bonferroni_bound`).

    Parameters
    ----------
    z : ndarray, shape (m,)
        Standardised residuals of the rows under the fitted model (unit variance if it is right).
    n : int
        Rows the bound is over.
    alpha : float

    Returns
    -------
    bound : float
    nu : float
        The t's degrees of freedom (inf: Gaussian), at least :data:`MIN_NU`.
    """
    from scipy import optimize, stats  # here, not at import: the controller reads no scipy

    a = np.abs(np.asarray(z, dtype=float))
    ratio = float(np.quantile(a, 0.95) / max(np.quantile(a, 0.5), 1e-300))

    def t_ratio(nu: float) -> float:
        return float(stats.t.isf(0.025, nu) / stats.t.isf(0.25, nu))

    if not np.isfinite(ratio) or ratio <= t_ratio(1e6):
        return bonferroni_bound(n, alpha), float("inf")
    nu = MIN_NU if ratio >= t_ratio(MIN_NU) else float(optimize.brentq(lambda v: t_ratio(v) - ratio, MIN_NU, 1e6))
    return float(stats.t.isf(alpha / (2.0 * max(int(n), 1)), nu) * np.sqrt((nu - 2.0) / nu)), nu


def deletion_residuals(residual: np.ndarray, Phi: np.ndarray, rows: np.ndarray, *,
                       tilt_inputs: np.ndarray | None = None, tilt: np.ndarray | None = None,
                       local_inputs: np.ndarray | None = None, neighbours: int = SCREEN_NEIGHBOURS) -> np.ndarray:
    """Each given row's residual standardised by the variance model refitted without it (and,
    with ``local_inputs``, by the scatter of its nearest moves where that is larger).

    Parameters
    ----------
    residual : ndarray, shape (n,)
        Residual of the mean correction, µm.
    Phi : ndarray, shape (n, p)
        The selected sources at the training inputs (p may be 0: the floor alone).
    rows : ndarray of int, shape (k,)
    tilt_inputs, tilt : ndarray, shapes (n, m) and (m,), optional
        The tilt source's inputs and its direction (held), when the selection took it.
    local_inputs : ndarray, shape (n, l), optional
        Coordinates in which a row's nearest moves are found (standardised).
    neighbours : int
        How many nearest moves.

    Returns
    -------
    ndarray, shape (k,)
        ``r_i / sqrt(v_(-i)(x_i) max(1, m_i))`` with ``m_i`` the median of ``r_j^2 / v_(-i)(x_j)``
        over row i's nearest moves divided by chi2_1's median (``m_i = 1`` without ``local_inputs``).
    """
    r = np.asarray(residual, dtype=float)
    Phi = np.asarray(Phi, dtype=float).reshape(len(r), -1)
    D = variance_design(Phi, tilt_inputs, tilt)
    out = np.empty(len(rows))
    for k, i in enumerate(np.asarray(rows, dtype=int)):
        keep = np.ones(len(r), dtype=bool)
        keep[i] = False
        Z = None if tilt_inputs is None else tilt_inputs[keep]
        _, c = fit_variance_with(r[keep] ** 2, Phi[keep], Z, tilt)
        v = np.maximum(D @ c, 1e-300)
        local = 1.0
        if local_inputs is not None and neighbours > 0:
            d2 = np.sum((local_inputs - local_inputs[i]) ** 2, axis=1)
            d2[i] = np.inf
            near = np.argsort(d2)[: min(neighbours, len(r) - 1)]
            local = max(1.0, float(np.median(r[near] ** 2 / v[near])) / _CHI2_1_MEDIAN)
        out[k] = r[i] / np.sqrt(v[i] * local)
    return out


def fitted_variance(residual: np.ndarray, Phi: np.ndarray, tilt_inputs: np.ndarray | None = None,
                    tilt: np.ndarray | None = None) -> np.ndarray:
    """The variance model ``c_0 + sum_j c_j phi_j (+ tilt)`` fitted by maximum likelihood to the
    squared residual, at the rows given.

    Parameters
    ----------
    residual : ndarray, shape (n,)
    Phi : ndarray, shape (n, p)
    tilt_inputs, tilt : ndarray, shapes (n, m) and (m,), optional
        The tilt source's inputs and its direction (held).

    Returns
    -------
    ndarray, shape (n,)
    """
    r = np.asarray(residual, dtype=float)
    _, c = fit_variance_with(r ** 2, Phi, tilt_inputs, tilt)
    return np.maximum(variance_design(Phi, tilt_inputs, tilt) @ c, 1e-300)


def suspect_rows(residual: np.ndarray, variance: np.ndarray, top: int = SCREEN_TOP) -> np.ndarray:
    """Step 1 of the module docstring: the ``top`` rows with the largest ``r^2 / v`` and the ``top``
    with the largest ``|r|`` (a source that peaks at a corrupt row can pull its standardised
    residual down to nothing), sorted, shape (<= 2 top,)."""
    r = np.asarray(residual, dtype=float)
    k = min(top, len(r))
    return np.unique(np.concatenate([np.argsort(-(r * r) / variance)[:k], np.argsort(-np.abs(r))[:k]]))


def screening_sources(residual: np.ndarray, candidates: np.ndarray, names, tilt_inputs: np.ndarray, selection, *,
                      reselect: bool, alpha: float) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, np.ndarray | None]:
    """The suspects under the selection made on every row, and the sources the screen judges them
    by (module docstring, steps 1-2): the selection made again on every row but the suspects.

    The selection made with a corrupt reading can hold a source that peaks at it and masks it:
    on the independent stage of ``tests/models/test_outlier_screen.py`` a saturating step of the
    stick-slip actuator, whose coefficient the other large steps keep when the reading alone is
    left out of the refit.

    Parameters
    ----------
    residual : ndarray, shape (n,)
    candidates : ndarray, shape (n, P)
        Every candidate source at the training inputs.
    names : sequence of str, length P
    tilt_inputs : ndarray, shape (n, k)
        The tilt's inputs.
    selection : Selection
        The selection made on every row (:func:`microctl.models.noise_dictionary.select_features`).
    reselect : bool
        False keeps ``selection`` (sources named by the user).
    alpha : float
        The selection's level.

    Returns
    -------
    suspects : ndarray of int
    Phi : ndarray, shape (n, p)
        The sources to judge by, at every row.
    tilt_inputs, tilt : ndarray or None
        The tilt's inputs and direction when those sources hold it.
    """
    r = np.asarray(residual, dtype=float)
    given = _sources_of(selection, candidates, tilt_inputs)
    suspects = suspect_rows(r, fitted_variance(r, *given))
    if not reselect:
        return (suspects, *given)
    return (suspects, *_selected_without(r, candidates, names, tilt_inputs, suspects, alpha))


def _sources_of(selection, candidates: np.ndarray, tilt_inputs: np.ndarray) -> tuple:
    """``(Phi, tilt_inputs or None, tilt)`` of a selection, at every row."""
    return candidates[:, list(selection.indices)], (tilt_inputs if selection.tilt is not None else None), selection.tilt


def _selected_without(r: np.ndarray, candidates: np.ndarray, names, tilt_inputs: np.ndarray, rows, alpha: float) -> tuple:
    """:func:`_sources_of` the selection made on every row but ``rows``."""
    keep = np.setdiff1d(np.arange(len(r)), rows)
    return _sources_of(select_features(r[keep], candidates[keep], names, tilt_inputs=tilt_inputs[keep], alpha=alpha),
                       candidates, tilt_inputs)


def sources_without_row(residual: np.ndarray, candidates: np.ndarray, names, tilt_inputs: np.ndarray, *,
                        alpha: float):
    """``own(i) -> (Phi_i, tilt_inputs_i, tilt_i)``: the sources selected on every row but i (at
    every row), for :func:`screen_rows`'s ``own_sources``. Left out together, the suspects can
    take with them the evidence of a source the stage has (gauge_tilt rig 1 of
    ``scripts/bench_screen.py``: ``rx:sq`` rests on them); left out alone, a corrupt row takes
    only the source it made."""
    r = np.asarray(residual, dtype=float)
    return lambda i: _selected_without(r, candidates, names, tilt_inputs, [i], alpha)


def screen_rows(residual: np.ndarray, Phi: np.ndarray, *, tilt_inputs: np.ndarray | None = None,
                tilt: np.ndarray | None = None, local_inputs: np.ndarray | None = None,
                alpha: float = SCREEN_ALPHA, top: int = SCREEN_TOP, max_rows: int | None = None,
                suspects: np.ndarray | None = None, own_sources=None) -> Screen:
    """Rows whose deletion residual is beyond the bound for the other rows' tails (module docstring,
    steps 1-4).

    Parameters
    ----------
    residual : ndarray, shape (n,)
    Phi : ndarray, shape (n, p)
        The selected sources at the training inputs.
    tilt_inputs, tilt, local_inputs : optional
        As in :func:`deletion_residuals`.
    alpha : float
        Family-wise level over the n rows.
    top : int
        Suspects examined: this many with the largest ``r^2 / v`` under the fit on every row, and
        this many with the largest ``|r|``.
    max_rows : int, optional
        Most rows set aside (default :func:`max_screened` of n); more beyond the bound: none.
    suspects : ndarray of int, optional
        Rows examined besides this fit's own suspects (training passes the suspects of the
        selection that was made with every row, when Phi holds the sources selected without them).
    own_sources : callable, optional
        ``own_sources(i) -> (Phi_i, tilt_inputs_i, tilt_i)``: the sources suspect i is judged by
        (training: those selected on every row but i); default Phi's.

    Returns
    -------
    Screen
    """
    r = np.asarray(residual, dtype=float)
    n = len(r)
    Phi = np.asarray(Phi, dtype=float).reshape(n, -1)
    v = fitted_variance(r, Phi, tilt_inputs, tilt)
    suspects = np.union1d(suspect_rows(r, v, top), [] if suspects is None else suspects).astype(int)
    if own_sources is None:
        z = deletion_residuals(r, Phi, suspects, tilt_inputs=tilt_inputs, tilt=tilt, local_inputs=local_inputs)
    else:  # each suspect by the sources selected without it
        z = np.array([deletion_residuals(r, P_i, [i], tilt_inputs=Z_i, tilt=w_i, local_inputs=local_inputs)[0]
                      for i in suspects for P_i, Z_i, w_i in [own_sources(int(i))]])
    bulk = np.setdiff1d(np.arange(n), suspects)  # the tails of the rows not suspected, under a fit on them
    vb = fitted_variance(r[bulk], Phi[bulk], None if tilt_inputs is None else tilt_inputs[bulk], tilt)
    bound, nu = tail_bound(r[bulk] / np.sqrt(vb), n, alpha)
    out = np.abs(z) > bound
    cap = max_screened(n) if max_rows is None else int(max_rows)
    if int(out.sum()) > cap:
        return Screen((), (), bound, int(out.sum()), withheld=True, nu=nu)
    order = np.argsort(suspects[out])
    return Screen(tuple(int(i) for i in suspects[out][order]), tuple(float(x) for x in z[out][order]), bound,
                  int(out.sum()), nu=nu)


def describe_screen(record: dict | None, seq) -> str:
    """One line on the rows the screen set aside (the record training keeps, ``info["noise_selection"]["screened"]``),
    each by its line in the log file (the header is line 1) and its ``seq``; "" when it set aside none
    and withheld none."""
    if not record or (not record["rows"] and not record["withheld"]):
        return ""
    if not record["rows"]:
        return (f"note: {record['withheld']} readings are beyond |z| = {record['bound']:.2f} under the noise sources "
                "fitted without each; that many are not a few corrupt readings but heavier tails than the model's, so "
                "none was set aside")
    rows = ", ".join(f"line {i + 2} (seq {int(seq[i])}, z = {z:+.1f})" for i, z in zip(record["rows"], record["z"]))
    return (f"set aside {len(record['rows'])} reading(s) that the model, fitted without each, puts beyond "
            f"|z| = {record['bound']:.2f} (family-wise level {record['alpha']:g} for the tails of the other rows; "
            f"a corrupt reading?): {rows}; the log is unchanged")
