"""Greedy forward selection of mean causes by BIC, with equivalence classes.

Step 0 fits the stage model as configured (no new cause). At each step every remaining
candidate (:func:`~microctl.diagnosis.causes.candidate_specs`) is fitted *jointly* with the
causes accepted so far (warm-started) and the one with the lowest BIC,

    BIC = n log(RSS/n) + k log n,

is accepted if it pays: ΔBIC < 0 against the current model **and** its likelihood-ratio
test LR = n log(RSS_cur/RSS_new) ~ χ²(Δk), Bonferroni-corrected over the candidates of the
step, has p < α. Selection stops when nothing pays, or when the residual is at the noise
level (the generic structure F-test of :mod:`microctl.diagnosis.residuals` is not
significant and no candidate's LR is).

Equivalence: a candidate whose own fit is within ``EQUIV_LR`` of the accepted one's
likelihood (2 Δℓ = n log(RSS_c/RSS_best) < 6: the two causes predict the same data within
the noise) is listed in the accepted cause's ``equivalent`` and removed from later steps. Among
equivalents the one accepted (and written to extended.yaml) is the one the physics makes most
plausible (:func:`~microctl.diagnosis.separate.choose_plausible`), not the lowest BIC.
For the Table I stage with one gauge this groups ``tool_offset`` with ``contact_offset`` of
every actuator (docs/diagnosis.md derives why and what measurement separates them).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Callable, Sequence

import numpy as np
from scipy import stats

from microctl.diagnosis.causes import CauseSpec, MeanFit, candidate_specs, fit_mean
from microctl.diagnosis.data import DiagnosisData
from microctl.diagnosis.residuals import Test, structure_f_test
from microctl.diagnosis.separate import choose_plausible
from microctl.stage.causes import Effects
from microctl.stage.geometry import Stage

#: 2 Δ log-likelihood below which two fitted causes are called equivalent.
EQUIV_LR = 6.0

#: Most mean causes accepted (a safety stop; the data rarely support more). Six: a hysteresis
#: loop on each of four actuators is four causes, and a greedy first step may take a cause that
#: stands in for their sum (a sensor scale) before the backward check drops it.
MAX_CAUSES = 6


def cause_entry(spec: CauseSpec, theta: np.ndarray, stderr: np.ndarray, **extra) -> dict:
    """A report entry ``{"cause", "params", "stderr", ...}`` (shared/spec/diagnosis.md)."""
    return {
        "cause": spec.cause,
        "params": spec.params_dict(theta),
        "stderr": {p: (float(s) if np.isfinite(s) else None) for p, s in zip(spec.params, stderr)},
        **extra,
    }


@dataclass(frozen=True, eq=False)
class Step:
    """One step of the greedy selection.

    Attributes
    ----------
    current : MeanFit
        Model before the step.
    fits : dict of str -> MeanFit
        Joint fit of the current causes + each candidate (key = candidate key).
    best : str or None
        Key of the lowest BIC.
    p_value : float
        Bonferroni LR p-value of the best candidate.
    structure : Test
        Structure F-test of the current model's residual.
    accepted : bool
    equivalent : tuple of str
        Keys equivalent to the best.
    chosen : dict or None
        With equivalents: how ``best`` was chosen among them
        (:func:`~microctl.diagnosis.separate.choose_plausible`; ``best`` is then the most
        plausible, not necessarily the lowest BIC).
    """

    current: MeanFit
    fits: dict
    best: str | None
    p_value: float
    structure: Test
    accepted: bool
    equivalent: tuple = ()
    chosen: dict | None = None
    members: tuple = ()

    def accepts(self, key: str) -> bool:
        """Whether this step accepted the candidate ``key`` (alone, or in a shared group)."""
        return self.accepted and (key == self.best or key in self.members)


#: Per-actuator causes that are also tried on every actuator at once (a *shared* candidate,
#: ``cause[1,2,3,4]``): a stage's stacks are alike, and hysteresis is a property of the stack's
#: material, so a stage with one loop often has one on each actuator. One at a time, the first
#: loop accepted stands in for all of them (each alone explains most of the others' effect,
#: fitted wider than it is) and the others no longer pay; together they do.
SHARED_CAUSES = ("hysteresis",)


#: The shared candidate is fitted only when one of its members is among this many best single
#: candidates of the step (by BIC): elsewhere the data show no loop, and the joint fit of every
#: actuator's loop is the most expensive fit of a step.
SHARED_TOP = 3


def _shared_groups(remaining: Sequence[CauseSpec], fits: dict) -> dict:
    """The shared candidates: each cause of :data:`SHARED_CAUSES` on every actuator still in play
    (two or more), keyed ``cause[i,j,...]``, when one of them is among the step's
    :data:`SHARED_TOP` best single fits."""
    top = set(sorted(fits, key=lambda k: fits[k].bic)[:SHARED_TOP])
    out: dict[str, tuple[CauseSpec, ...]] = {}
    for name in SHARED_CAUSES:
        members = tuple(s for s in remaining if s.cause == name and s.actuator is not None)
        if len(members) >= 2 and any(m.key in top for m in members):
            out[f"{name}[{','.join(str(m.actuator) for m in members)}]"] = members
    return out


@dataclass(frozen=True, eq=False)
class Selection:
    """Result of :func:`select_mean_causes`.

    Attributes
    ----------
    baseline : MeanFit
        The configured model (no new cause).
    final : MeanFit
        The accepted causes fitted jointly.
    steps : list of Step
    accepted : list of CauseSpec
    entries : list of dict
        Report entries, ranked best first: the accepted causes (with params from ``final``
        and their ``equivalent`` lists), then the other candidates of the first step by BIC.
    stop_reason : str
    """

    baseline: MeanFit
    final: MeanFit
    steps: list
    accepted: list
    entries: list
    stop_reason: str
    specs: tuple = field(default=())
    withdrawn: tuple = field(default=())


def _lr_p(cur: MeanFit, new: MeanFit, n_tests: int) -> float:
    dk = max(new.k - cur.k, 1)
    lr = max(new.n * np.log(max(cur.rss, 1e-300) / max(new.rss, 1e-300)), 0.0)
    return float(min(stats.chi2.sf(lr, dk) * n_tests, 1.0))


def select_mean_causes(
    stage: Stage,
    data: DiagnosisData,
    *,
    alpha: float = 1e-3,
    weights: np.ndarray | None = None,
    specs: Sequence[CauseSpec] | None = None,
    progress: Callable[[str], None] | None = None,
) -> Selection:
    """Greedy forward selection (see the module docstring).

    Parameters
    ----------
    stage : Stage
        The configured model; ``stage.corrections`` stay in every fit.
    data : DiagnosisData
    alpha : float
        Significance level of an acceptance (Bonferroni over a step's candidates).
    weights : ndarray (n,), optional
        1/std per reading from a noise model (weighted least squares).
    specs : sequence of CauseSpec, optional
        Candidates (default every vocabulary cause; ``drift`` only with times).
    progress : callable(str), optional
        Called once per candidate fit.

    Returns
    -------
    Selection
    """
    base: Effects = stage.corrections
    has = ("time_s",) if data.time_s is not None else ()
    specs = list(candidate_specs(stage, has) if specs is None else specs)
    baseline = fit_mean(stage, base, [], data, weights=weights)
    current = baseline
    accepted: list[CauseSpec] = []
    excluded: set[str] = set()
    steps: list[Step] = []
    stop = "nothing pays"
    while True:
        resid = data.t - current.pred
        if weights is not None:
            resid = resid * weights
        structure = structure_f_test(resid, data, current.k, weights, reading=current.pred)
        remaining = [s for s in specs if s.key not in excluded]
        if len(accepted) >= MAX_CAUSES or not remaining:
            steps.append(Step(current, {}, None, 1.0, structure, False))
            stop = "no candidates left" if not remaining else f"{MAX_CAUSES} causes accepted"
            break
        fits, groups = _fit_candidates(stage, base, accepted, remaining, current, data, weights, progress)
        if not fits:
            steps.append(Step(current, {}, None, 1.0, structure, False))
            stop = "no candidate fits without lifting a ball"
            break
        best_key = min(fits, key=lambda k: fits[k].bic)
        best = fits[best_key]
        p = _lr_p(current, best, len(fits))
        ok = best.bic < current.bic and p < alpha
        single = {k: f for k, f in fits.items() if k not in groups}
        equiv, chosen_info = _equivalents(single, best_key) if ok and best_key in single else (), None
        if equiv:
            best_key, equiv, p, chosen_info = _choose(stage, current, single, best_key, equiv, p, alpha)
            best = fits[best_key]
        members = tuple(m.key for m in groups.get(best_key, ()))
        steps.append(Step(current, fits, best_key, p, structure, ok, equiv, chosen_info, members))
        if not ok:
            stop = "residual at the noise level" if structure.p_value >= alpha else "nothing pays"
            break
        if members:  # the cause on every actuator still in play at once
            accepted.extend(groups[best_key])
            excluded |= set(members)
            current = best
            continue
        spec = next(s for s in remaining if s.key == best_key)
        accepted.append(spec)
        excluded |= {best_key, *equiv}
        current = best
    final = current
    return Selection(baseline, final, steps, accepted, _entries(final, steps, accepted), stop, tuple(specs))


def _fit_candidates(stage: Stage, base: Effects, accepted: list, remaining: list, current: MeanFit,
                    data: DiagnosisData, weights, progress) -> tuple[dict, dict]:
    """One step's fits: every remaining candidate jointly with the accepted causes (warm-started),
    then the shared candidates (:func:`_shared_groups`). Fits that lift a ball without a cause
    that may are left out. Returns (fits by key, shared groups by key)."""
    fits: dict[str, MeanFit] = {}
    for s in remaining:
        theta0 = np.concatenate([current.theta, s.start_from(base)])  # warm start
        f = fit_mean(stage, base, [*accepted, s], data, theta0=theta0, nuisance0=current.nuisance,
                     weights=weights)
        if progress is not None:
            progress(s.key)
        if f.unphysical:  # lifts a ball though no cause of the set may: not these causes
            continue
        fits[s.key] = f
    groups = _shared_groups(remaining, fits)
    for key, members in groups.items():
        theta0 = np.concatenate([current.theta, *(m.start_from(base) for m in members)])
        f = fit_mean(stage, base, [*accepted, *members], data, theta0=theta0, nuisance0=current.nuisance,
                     weights=weights)
        if progress is not None:
            progress(key)
        if not f.unphysical:
            fits[key] = f
    return fits, groups


def _equivalents(fits: dict, best_key: str) -> tuple:
    """Keys whose fit is within 2Δℓ < :data:`EQUIV_LR` of the best's (same data within the noise)."""
    best = fits[best_key]
    return tuple(k for k, f in fits.items()
                 if k != best_key and f.n * np.log(max(f.rss, 1e-300) / max(best.rss, 1e-300)) < EQUIV_LR)


def _choose(stage, current: MeanFit, fits: dict, best_key: str, equiv: tuple, p: float,
            alpha: float) -> tuple[str, tuple, float, dict]:
    """The data cannot separate ``best_key`` from ``equiv``: accept the one the physics makes most
    plausible (:func:`~microctl.diagnosis.separate.choose_plausible`) if it pays on its own.

    Returns (accepted key, its equivalents, its LR p-value, the report's ``chosen``)."""
    chosen, info = choose_plausible(best_key, equiv, fits, stage)
    p_c = _lr_p(current, fits[chosen], len(fits))
    if chosen != best_key and fits[chosen].bic < current.bic and p_c < alpha:
        return chosen, tuple(k for k in (best_key, *equiv) if k != chosen), p_c, info
    return best_key, equiv, p, {**info, "by": "lowest BIC (also the most plausible, or the most plausible "
                                              "does not pay on its own)"}


#: The one definition of ΔBIC in the report (mean and noise tables, causes.png).
DELTA_BIC = ("ΔBIC = BIC(the model with the cause added) − BIC(the model it was added to): for an accepted "
             "cause and its equivalents the model before the step that accepted it, for another candidate the "
             "configured model (mean causes) or the final noise model (noise causes); negative = the cause pays")


def _entries(final: MeanFit, steps: list[Step], accepted: list[CauseSpec]) -> list[dict]:
    """Report entries with ΔBIC as :data:`DELTA_BIC` defines it."""
    out: list[dict] = []
    split = final.split()
    for j, (spec, theta, se) in enumerate(split):
        step = next(s for s in steps if s.accepts(spec.key))
        cur_bic = step.current.bic
        eq = []
        for k in step.equivalent:
            f = step.fits[k]
            s2, th2, se2 = f.split()[-1]
            eq.append(cause_entry(s2, th2, se2, delta_bic=float(f.bic - cur_bic),
                                  rank_deficient=bool(f.rank_deficient),
                                  **({"nuisance": {n: float(v) for n, v in f.nuisance.items()}} if f.nuisance else {})))
        out.append(cause_entry(spec, theta, se, delta_bic=float(step.fits[step.best].bic - cur_bic),
                               p_value=float(step.p_value), rank_deficient=bool(final.rank_deficient),
                               equivalent=eq, accepted=True, step=steps.index(step) + 1,
                               **({"chosen": step.chosen} if step.chosen else {}),
                               nuisance={k: float(v) for k, v in step.fits[step.best].nuisance.items()}))
    # the other candidates of the first step, against the configured model, best first
    first = steps[0]
    if first.fits:
        listed = {cause_label(e) for e in out} | set().union(*[set(s.equivalent) for s in steps])
        for k, f in sorted(first.fits.items(), key=lambda kv: kv[1].bic):
            if k in listed:
                continue
            s2, th2, se2 = f.split()[-1]
            out.append(cause_entry(s2, th2, se2, delta_bic=float(f.bic - first.current.bic),
                                   rank_deficient=bool(f.rank_deficient), equivalent=[], accepted=False,
                                   **({"nuisance": {n: float(v) for n, v in f.nuisance.items()}} if f.nuisance else {})))
    return out


def withdraw(sel: Selection, keys: Sequence[str], stage: Stage, data: DiagnosisData, *,
             weights: np.ndarray | None = None, reason: str = "") -> Selection:
    """``sel`` without the accepted causes ``keys``: the others refitted jointly, entries rebuilt.

    The withdrawn causes stay in ``entries`` (``accepted: false``, ``withdrawn: reason``).
    """
    keys = set(keys)
    if not keys:
        return sel
    kept = [s for s in sel.accepted if s.key not in keys]
    split = {s.key: th for s, th, _ in sel.final.split()}
    theta0 = np.concatenate([split[s.key] for s in kept]) if kept else None
    final = fit_mean(stage, stage.corrections, kept, data, theta0=theta0, nuisance0=sel.final.nuisance,
                     weights=weights)
    entries = _entries(final, sel.steps, kept)
    gone = []
    accepted_at = {cause_label(e): e for e in sel.entries if e.get("accepted")}
    for s, th, se in sel.final.split():
        if s.key in keys:
            e = accepted_at.get(s.key, {})
            gone.append(cause_entry(s, th, se, delta_bic=e.get("delta_bic"), rank_deficient=bool(sel.final.rank_deficient),
                                    equivalent=e.get("equivalent", []), accepted=False, withdrawn=reason))
    entries = entries[:len(kept)] + gone + [e for e in entries[len(kept):]
                                            if cause_label(e) not in keys]
    return replace(sel, final=final, accepted=kept, entries=entries, withdrawn=tuple(sel.withdrawn) + tuple(keys))


def cause_label(e: dict) -> str:
    """``cause[actuator]`` of a report entry (``cause`` for a global one): how entries are named
    and matched in the selection, the report and the figures."""
    a = e.get("params", {}).get("actuator")
    return e["cause"] if a is None else f"{e['cause']}[{a}]"


def backward(sel: Selection, stage: Stage, data: DiagnosisData, *, weights: np.ndarray | None = None,
             alpha: float = 1e-3) -> list[str]:
    """Accepted causes that no longer pay once the others are in the model (backward elimination).

    Each cause of the final model is removed in turn (the others refitted, warm-started); its
    likelihood-ratio test against the full model, Bonferroni over the causes, must have p < α.
    The worst failing cause is dropped and the rest tested again.

    Returns
    -------
    list of str
        Keys to withdraw (may be empty).
    """
    kept = list(sel.accepted)
    split = {s.key: th for s, th, _ in sel.final.split()}
    current = sel.final
    out: list[str] = []
    while len(kept) >= 2:
        worst, worst_p, worst_fit = None, -1.0, None
        for spec in kept:
            others = [s for s in kept if s is not spec]
            f0 = fit_mean(stage, stage.corrections, others, data, theta0=np.concatenate([split[s.key] for s in others]),
                          nuisance0=current.nuisance, weights=weights)
            p = _lr_p(f0, current, len(kept))
            if p > worst_p:
                worst, worst_p, worst_fit = spec, p, f0
        if worst_p < alpha:
            break
        out.append(worst.key)
        kept.remove(worst)
        current = worst_fit
        split = {s.key: th for s, th, _ in current.split()}
    return out
