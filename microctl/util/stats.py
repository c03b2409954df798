"""Statistics of the experiments (paper IV-B): SSE, MSSE, VSSE and the hypothesis tests.

Definitions (paper IV-B):

- steady-state error e_s(t_d) = t_d − t_f for one trial (t_f the gauge feedback);
- MSSE: the mean of e_s over the trials at one target (accuracy);
- VSSE: the sample variance (ddof = 1) of e_s over the trials at one target (repeatability);
- prediction error PE: |t' − prediction| per move.

Tests:

- the paper's: a two-sample t-test (Student, equal variances) on the per-target MSSE values of
  two controllers, and another on their per-target VSSE values; one-sided alternatives
  "EAFM smaller" are reported next to the two-sided p;
- per target, the statistician's addition for variances: the Brown–Forsythe test (Levene's test
  centred on the median), because the F-test for equal variances is badly non-robust to
  non-normal errors and stick-slip scatter is heavy-tailed; with 10 trials it is still valid;
- per target, for accuracy: Welch's t-test on |e_s| (no equal-variance assumption, since the
  point of the controller is that the variances differ);
- absolute movement: the paper's two-sample t-test on PE, plus a paired t-test and a Wilcoxon
  signed-rank test because AFM and EAFM predict the *same* moves (pairing removes the
  point-to-point spread).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import stats as _st


def steady_state_errors(target_um: np.ndarray, reached_um: np.ndarray) -> np.ndarray:
    """e_s = t_d − t_f (paper IV-B.2), elementwise; any matching shapes."""
    return np.asarray(target_um, dtype=float) - np.asarray(reached_um, dtype=float)


def msse(sse: np.ndarray) -> np.ndarray:
    """Mean of the steady-state errors over trials.

    Parameters
    ----------
    sse : ndarray, shape (n_trials, n_targets)

    Returns
    -------
    ndarray, shape (n_targets,)
    """
    return np.mean(np.asarray(sse, dtype=float), axis=0)


def vsse(sse: np.ndarray) -> np.ndarray:
    """Sample variance (ddof = 1) of the steady-state errors over trials, shape (n_targets,)."""
    return np.var(np.asarray(sse, dtype=float), axis=0, ddof=1)


def msse_stderr(sse: np.ndarray) -> np.ndarray:
    """Standard error of the MSSE, sqrt(VSSE / n_trials), shape (n_targets,)."""
    sse = np.asarray(sse, dtype=float)
    return np.sqrt(vsse(sse) / sse.shape[0])


@dataclass(frozen=True)
class TestResult:
    """A hypothesis test's outcome.

    Attributes
    ----------
    name : str
        Which test.
    statistic : float
    p_value : float
        Two-sided p-value.
    p_one_sided : float or None
        p-value of the one-sided alternative stated in ``alternative``.
    alternative : str
    """

    name: str
    statistic: float
    p_value: float
    p_one_sided: float | None = None
    alternative: str = ""

    def to_dict(self) -> dict:
        """Plain-data form for results.json."""
        return {
            "test": self.name,
            "statistic": float(self.statistic),
            "p_value": float(self.p_value),
            "p_one_sided": None if self.p_one_sided is None else float(self.p_one_sided),
            "alternative": self.alternative,
        }


def two_sample_t(a: np.ndarray, b: np.ndarray, *, equal_var: bool = True) -> TestResult:
    """Two-sample t-test of mean(a) vs mean(b); one-sided alternative: mean(b) < mean(a).

    ``equal_var=True`` is Student's test (the paper's "standard two-sample t-test"),
    ``False`` is Welch's.
    """
    a = np.asarray(a, dtype=float)
    b = np.asarray(b, dtype=float)
    two = _st.ttest_ind(a, b, equal_var=equal_var)
    one = _st.ttest_ind(a, b, equal_var=equal_var, alternative="greater")
    name = "Student two-sample t-test" if equal_var else "Welch two-sample t-test"
    return TestResult(name, float(two.statistic), float(two.pvalue), float(one.pvalue), "second < first")


def paired_t(a: np.ndarray, b: np.ndarray) -> TestResult:
    """Paired t-test on a − b; one-sided alternative: b < a."""
    two = _st.ttest_rel(a, b)
    one = _st.ttest_rel(a, b, alternative="greater")
    return TestResult("paired t-test", float(two.statistic), float(two.pvalue), float(one.pvalue), "second < first")


def wilcoxon_signed_rank(a: np.ndarray, b: np.ndarray) -> TestResult:
    """Wilcoxon signed-rank test on a − b; one-sided alternative: b < a."""
    two = _st.wilcoxon(a, b)
    one = _st.wilcoxon(a, b, alternative="greater")
    return TestResult("Wilcoxon signed-rank test", float(two.statistic), float(two.pvalue), float(one.pvalue), "second < first")


def brown_forsythe(a: np.ndarray, b: np.ndarray) -> TestResult:
    """Brown–Forsythe test of equal variances (Levene centred on the median).

    The one-sided p halves the two-sided p when var(b) < var(a), else it is 1 − p/2
    (the statistic is an F on absolute deviations, so its direction is read off the spreads).
    """
    a = np.asarray(a, dtype=float)
    b = np.asarray(b, dtype=float)
    res = _st.levene(a, b, center="median")
    p = float(res.pvalue)
    smaller = np.var(b, ddof=1) < np.var(a, ddof=1)
    return TestResult(
        "Brown-Forsythe test (Levene, median-centred)",
        float(res.statistic),
        p,
        p / 2 if smaller else 1 - p / 2,
        "var(second) < var(first)",
    )


def f_test_variances(a: np.ndarray, b: np.ndarray) -> TestResult:
    """Classical F-test of var(a) = var(b) (normal errors); one-sided: var(b) < var(a)."""
    a = np.asarray(a, dtype=float)
    b = np.asarray(b, dtype=float)
    F = np.var(a, ddof=1) / np.var(b, ddof=1)
    dfa, dfb = a.size - 1, b.size - 1
    one = float(_st.f.sf(F, dfa, dfb))
    two = float(min(1.0, 2 * min(one, 1 - one)))
    return TestResult("F-test of variances", float(F), two, one, "var(second) < var(first)")


def fraction_within(measured: np.ndarray, mean: np.ndarray, std: np.ndarray, k: float = 2.0) -> float:
    """Fraction of measurements inside mean ± k·std."""
    measured, mean, std = (np.asarray(x, dtype=float) for x in (measured, mean, std))
    return float(np.mean(np.abs(measured - mean) <= k * std))
