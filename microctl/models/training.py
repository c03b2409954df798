"""Residual data set of the EAFM (paper eq. 3), the fit, and binding the model to a stage.

``x = [s_prev; u]`` and ``y = t' - T_t f_a(s_prev, u)`` for every row of a measurement log
(``shared/spec/measurement-log.md``); :func:`train_residual_model` fits the VHGPR and
records ``geometry_hash = stage.geometry_hash()`` and the input names, so that the model is
refused for another stage geometry (:class:`~microctl.models.eafm.EAFM`).

The test fixture that builds a model from fixed hyperparameters (no fit) is
:func:`microctl.testing.fixed_hyperparameter_model`.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from microctl.errors import ConfigError, DataError
from microctl.gp.noise_models import noise_model_class, noise_model_names
from microctl.gp.noise_prior import NoiseFeatures
from microctl.gp.shaped_features import ShapedFeatures
from microctl.gp.vhgpr import VHGPR, FittedVHGPR
from microctl.models.afm import AnalyticForwardModel
from microctl.models.alternatives import alternatives_record
from microctl.models.declared_sources import declared_selection
from microctl.models.direction import log_directions
from microctl.models.eafm import bind_to_stage, context_names
from microctl.models.g_gp_selection import select_g_gp
from microctl.models.mean_shift import trend_features, with_mean_shift
from microctl.models.noise_dictionary import candidate_features, select_features
from microctl.models.noise_inputs import G_INPUTS, G_STARTS, g_input_map, step_map
from microctl.models.noise_summary import noise_summary
from microctl.models.outlier_screen import SCREEN_ALPHA, bonferroni_bound, max_screened, screen_rows, screening_sources, sources_without_row, tail_bound
from microctl.util.fields import setting, validate_settings

__all__ = ["AUTO_SPARSE_ROWS", "GP_FORMS", "MAX_SPARSE_ROWS", "max_train_rows", "uses_sparse", "NOISE_MODELS", "ResidualModelSettings", "ResidualData", "residual_dataset", "actuator_step_features",
           "noise_features_for", "train_residual_model", "noise_summary", "save_model"]


@dataclass(frozen=True)
class ResidualData:
    """The training set of eq. 3.

    Attributes
    ----------
    X : ndarray, shape (n, n_s + n_p)
        ``[s_prev; u]`` per row.
    y : ndarray, shape (n,)
        ``t' - T_t f_a(s_prev, u)`` (µm); with hysteresis corrections f_a includes the loop.
    x_names : tuple of str
    direction : ndarray, shape (n, n_q), or None
        The move's context: each actuator's last direction of motion before the move (+1 or
        -1, :mod:`microctl.models.direction`), which only a reversal noise source reads; None
        when not known (then every row counts as +1, as if every actuator had last moved up).
    """

    X: np.ndarray
    y: np.ndarray
    x_names: tuple[str, ...]
    direction: np.ndarray | None = None

    def context_inputs(self, n_q: int) -> np.ndarray:
        """``[s_prev; u; c]`` per row (c: ``direction``, +1 where unknown), shape (n, n_s + n_p + n_q)."""
        c = np.ones((self.X.shape[0], n_q)) if self.direction is None else self.direction
        return np.hstack([self.X, c])

    def inputs_for(self, model) -> np.ndarray:
        """The rows as ``model`` reads them: :meth:`context_inputs` for a model with context columns
        (``model.n_context``), else X."""
        n = int(getattr(model, "n_context", 0) or 0)
        return self.context_inputs(n) if n else self.X

    def rows(self, idx) -> "ResidualData":
        """The rows ``idx`` (indices or a mask), in that order."""
        return ResidualData(X=self.X[idx], y=self.y[idx], x_names=self.x_names,
                            direction=None if self.direction is None else self.direction[idx])

    def with_context(self, n_q: int) -> "ResidualData":
        """The same rows with the context as trailing input columns (:meth:`context_inputs`)."""
        return ResidualData(X=self.context_inputs(n_q), y=self.y, x_names=self.x_names + context_names(n_q))


def residual_dataset(log: Any, afm: AnalyticForwardModel) -> ResidualData:
    """Residual data of eq. 3 from a :class:`~microctl.measurement.log.MeasurementLog`.

    Parameters
    ----------
    log : MeasurementLog
        With arrays ``u`` (n, n_p), ``t`` (n,), ``s_prev`` (n, n_s).
    afm : AnalyticForwardModel
        With hysteresis corrections (``afm.memory.active``) the AFM's prediction includes the
        loop, its play states run from the zero state along the rows in execution order (each
        row fed its previous command q_prev, then its command: :mod:`microctl.models.memory`).
    """
    u = np.asarray(log.u, dtype=float)
    s = np.asarray(log.s_prev, dtype=float)
    t = np.asarray(log.t, dtype=float)
    if u.ndim != 2 or u.shape[1] != afm.n_p or s.shape != (u.shape[0], afm.n_s) or t.shape != (u.shape[0],):
        raise DataError(f"measurement log arrays have shapes u {u.shape}, s_prev {s.shape}, t {t.shape}; "
                        f"expected (n, {afm.n_p}), (n, {afm.n_s}), (n,)")
    t_afm = np.asarray(afm.t_of(u))
    if afm.memory.active:  # the hysteresis loop, run along the log's commands in execution order
        t_afm = t_afm + afm.memory.reading_shift(u @ afm.w_pred, afm.memory.run_shift(afm.q_of(u), s[:, 1:]))
    y = t - t_afm  # eq. 3: y = t' - T_t f_a(s, u)
    names = tuple(f"{n}_prev" for n in afm.state_names) + tuple(f"u_{n}" for n in afm.dof)
    return ResidualData(X=np.hstack([s, u]), y=y, x_names=names, direction=log_directions(s[:, 1:], afm.q_of(u)))


#: Most rows the exact VHGPR is trained on: its cost grows as n³ (``python scripts/bench_vhgpr.py --scale``
#: times it by n; 200 000 rows do not fit in memory); ``gp: exact`` refuses a larger log
#: before any work with the advice to subsample it.
MAX_TRAIN_ROWS = 2000
#: Most rows the sparse model is trained on (its n x M matrices: ~3 GB at M = 256).
MAX_SPARSE_ROWS = 100_000
#: Rows of the seeded random subset on which the sparse model's hyperparameters are fitted.
SPARSE_SUBSET = 1000
#: ``gp: auto`` fits the exact VHGPR up to this many rows and the sparse form above: up to it the
#: sparse form would fit its hyperparameters on every row exactly anyway; above it the exact fit
#: grows as n³ and the exact posterior makes the controller's cost grow with n (its epistemic
#: variance is O(n p) per evaluation with f's SE part off, O(n²) with it on) while the sparse
#: one stays at its inducing points.
#: ``scripts/bench_vhgpr.py``'s stage rows compare the two forms at 2000 moves (fit time, NLPD
#: on held-out moves, controller time; docs/generated/bench_vhgpr.md).
AUTO_SPARSE_ROWS = SPARSE_SUBSET
#: The residual GP's forms: ``exact`` (VHGPR), ``sparse`` (inducing points), ``auto`` (exact up to
#: :data:`AUTO_SPARSE_ROWS` rows, sparse above).
GP_FORMS = ("auto", "exact", "sparse")

#: Prior variance of the affine trend's coefficients (standardised units: a trend of about
#: three output standard deviations per input standard deviation is a priori plausible; the
#: vague-prior limit in which the trend is the generalised-least-squares estimate).
LINEAR_PRIOR_VAR = 10.0

#: Noise models of the residual GP, as registered in :mod:`microctl.gp.noise_models`:
#: ``dictionary`` (the default: sources selected by the data, :func:`train_residual_model`),
#: ``physical`` (g's prior mean is the stage's stick-slip physics, :mod:`microctl.gp.noise_prior`)
#: and ``hgp`` (the paper's constant prior mean). A noise model with features
#: gets the stage's actuator steps (:func:`noise_features_for`).
NOISE_MODELS = noise_model_names()

#: Family-wise level of each entry step of the noise-source selection (``dictionary``).
SELECTION_ALPHA = 0.05
#: Rounds of the corrupt-reading screen (:mod:`microctl.models.outlier_screen`): after rows are set
#: aside the first fit and the selection are redone, and the screen looks again.
SCREEN_ROUNDS = 3


@dataclass(frozen=True)
class ResidualModelSettings:
    """How the residual VHGPR of eq. 3 is built and fitted (one definition for every command).

    Attributes
    ----------
    noise_model : str
        ``"dictionary"`` (default): the noise sources are selected by the data among the stage's
        candidates (:mod:`microctl.models.noise_dictionary`) and become g's prior mean, each with
        its own shape (:mod:`microctl.gp.shaped_features`); nothing selected: the constant prior
        mean. ``"physical"``: ``g ~ GP(m(x), K_g)`` with ``m(x) = log(c_0 + sum_i c_i dq_i^2)``,
        ``dq_i = K_i u - q_i,prev`` (eq. 12): a noise floor plus per-actuator stick-slip
        (:mod:`microctl.gp.noise_prior`). ``"hgp"``: the paper's ``g ~ GP(mu0, K_g)``.
    linear_trend : bool
        An affine trend in the pose u inside f's kernel (default True): Bayesian linear
        regression with the vague prior :data:`LINEAR_PRIOR_VAR` (R&W 2.7), estimated by
        generalised least squares with the noise model's weights. Calibration errors (actuator
        gains, contact and tool offsets, sensor scale) make the AFM residual affine in u to
        first order (through q = K u, eq. 12), and a trend extrapolates to the workspace's
        faces where an SE kernel reverts to the mean. False: the paper's SE kernel alone.
    se : str
        f's SE (nonlinear) part: ``"auto"`` (default: kept only where the data pay for its
        hyperparameters, :class:`~microctl.gp.vhgpr.VHGPR`; without the trend it is always on),
        ``"on"``, ``"off"`` (needs the trend).
    noise_parameter_uncertainty : bool
        Propagate the physical noise model's parameter uncertainty into g's variance (and so
        into the cautious objective). Default False (measured worse; see
        :class:`~microctl.gp.vhgpr.VHGPR`); the standard errors are reported either way.
    restarts : int
        VHGPR optimisation runs (>= 1).
    max_iter : int or None
        L-BFGS-B iterations per run (None: the trainer's size-dependent default).
    seed : int
        Seed of the restarts.
    gp : str
        The GP's form: ``"auto"`` (default: the exact VHGPR up to :data:`AUTO_SPARSE_ROWS` rows,
        the sparse one above), ``"exact"``, ``"sparse"`` (:mod:`microctl.gp.sparse`:
        hyperparameters from :data:`SPARSE_SUBSET` rows, the posterior on ``inducing`` points).
    inducing : int
        Inducing points of the sparse form (the controller's cost grows with them, not with n).
    mean_shift : bool
        True (default): with the ``dictionary`` noise model, the mean correction f gets a trend
        in the selected noise sources' features (:mod:`microctl.models.mean_shift`: the mean
        shift that scatter causes); False: none.
    g_inputs : str
        What g's GP reads (:mod:`microctl.models.noise_inputs`): ``"raw"`` (default: x = [s; u],
        eq. 3) or ``"actuators"`` (each actuator's position q_i and step dq_i, ARD on each).
    g_start : str
        Where the exact form's fit starts g (:class:`~microctl.gp.trainer.VHGPR`): ``"f"``
        (default: at the homoscedastic GP) or ``"residuals"`` (one more run, from a GP on the log
        squared residuals, :mod:`microctl.gp.noise_start`).
    g_gp : str
        g's GP on x beside its prior mean: ``"auto"`` (default: with the ``dictionary`` noise model
        kept only where the bound pays for its hyperparameters, :mod:`microctl.models.g_gp_selection`;
        the other noise models and the sparse form keep it), ``"on"`` (always kept) or ``"off"``
        (g is its prior mean).
    noise_sources : tuple of str or None
        With the ``dictionary`` noise model: None (default) lets the data select the noise
        sources; a list names them instead (candidates such as ``dq4:sat@4`` or quantities such as
        ``dq4``, ``drx``; an empty list: none), each kept in the model
        (:mod:`microctl.models.declared_sources`).
    """

    noise_model: str = setting("dictionary", choices=NOISE_MODELS)
    linear_trend: bool = setting(True)
    se: str = setting("auto", choices=("auto", "on", "off"))
    noise_parameter_uncertainty: bool = setting(False)
    restarts: int = setting(2, lo=1, hi=100)
    max_iter: int | None = setting(500, lo=1, hi=100_000, none_ok=True, kind="int")
    seed: int = setting(0, lo=0, hi=2**63 - 1)
    gp: str = setting("auto", choices=GP_FORMS)
    inducing: int = setting(256, lo=2, hi=5000)
    mean_shift: bool = setting(True)
    g_inputs: str = setting("raw", choices=tuple(G_INPUTS))
    g_start: str = setting("f", choices=G_STARTS)
    g_gp: str = setting("auto", choices=("auto", "on", "off"))
    noise_sources: tuple[str, ...] | None = setting(None, kind="names", none_ok=True)

    def __post_init__(self) -> None:
        validate_settings(self, "residual model setting")
        if self.noise_sources is not None and self.noise_model != "dictionary":
            raise ConfigError(f"residual model setting noise_sources: names sources of the 'dictionary' noise model, "
                              f"not of {self.noise_model!r}; use noise_model: dictionary or leave it unset")
        if self.se == "off" and not self.linear_trend:
            raise ConfigError("residual model setting se: 'off' needs linear_trend: true (without the trend and "
                              "the SE part the mean correction would be a constant); use se: auto or on")


def uses_sparse(n: int, settings: ResidualModelSettings) -> bool:
    """Whether a residual model of n rows is fitted in the sparse form (``gp``, :data:`GP_FORMS`)."""
    return settings.gp == "sparse" or (settings.gp == "auto" and n > AUTO_SPARSE_ROWS)


def max_train_rows(settings: ResidualModelSettings) -> int:
    """Most rows a residual model with these settings is trained on."""
    return MAX_TRAIN_ROWS if settings.gp == "exact" else MAX_SPARSE_ROWS


def actuator_step_features(afm: AnalyticForwardModel, actuators: Sequence[int] | None = None) -> NoiseFeatures:
    """The actuator steps ``dq_i = K_i u - q_i,prev`` (eq. 12) as linear maps of x = [s; u] (eq. 3).

    Parameters
    ----------
    afm : AnalyticForwardModel
    actuators : sequence of int, optional
        1-based actuator numbers to include (default: every actuator).

    Returns
    -------
    NoiseFeatures
        ``matrix`` shape (p, n_s + n_p): row j has -1 at ``q_i,prev`` and K_i on u.
    """
    idx = np.arange(afm.n_q) if actuators is None else np.array(sorted(set(actuators)), dtype=int) - 1
    return NoiseFeatures(step_map(afm)[idx], np.zeros(idx.size), tuple(f"d{afm.actuator_names[i]}" for i in idx))


def noise_features_for(afm: AnalyticForwardModel) -> NoiseFeatures:
    """The physical noise model's features for a stage.

    Every actuator's step, unless the stage's corrections carry diagnosed stick-slip
    (``stage.corrections.actuator_friction``, written into ``extended.yaml`` by ``microctl
    diagnose``): then exactly the actuators the diagnosis found it on, so the model does not
    spend data on (or fear) a friction the diagnosis ruled out; g's GP still models what the
    diagnosed physics leaves.
    """
    diagnosed = afm.stage.corrections.actuator_friction
    return actuator_step_features(afm, [c.actuator for c in diagnosed] if diagnosed else None)


def train_residual_model(data: ResidualData, afm: AnalyticForwardModel,
                         settings: ResidualModelSettings | None = None, *,
                         max_time: float | None = None) -> FittedVHGPR:
    """Fit the VHGPR to the residual data and bind it to the stage geometry.

    Parameters
    ----------
    data : ResidualData
    afm : AnalyticForwardModel
    settings : ResidualModelSettings, optional
        Default :class:`ResidualModelSettings()` (the physical noise model, linear trend).
    max_time : float, optional
        Wall-clock budget of the fit (s).

    Returns
    -------
    FittedVHGPR
        With ``geometry_hash = afm.stage.geometry_hash()``, ``x_names`` = state (``*_prev``)
        and ``u_*`` names, ``y_name = "residual_um"``.
    """
    st = settings or ResidualModelSettings()
    if st.noise_model == "dictionary":
        return bind_to_stage(_fit_dictionary(data, afm, st, max_time), afm)
    features = noise_features_for(afm) if noise_model_class(st.noise_model).uses_features else None
    return bind_to_stage(_fit(data, afm, st, features, st.noise_model, max_time), afm)


def _fit(data: ResidualData, afm: AnalyticForwardModel, st: ResidualModelSettings,
         features: NoiseFeatures | None, noise_model: str, max_time: float | None,
         warm_start: FittedVHGPR | None = None, mean_features: ShapedFeatures | None = None) -> FittedVHGPR:
    """One VHGPR fit of the residual with the settings' mean model (and f's trend of
    ``mean_features``, :mod:`microctl.models.mean_shift`) and the given noise model (from
    ``warm_start``'s hyperparameters when given: :class:`~microctl.gp.trainer.VHGPR`)."""
    # the trend acts on the pose u = x[n_s:] (eq. 3: x = [s; u])
    linear = tuple(range(afm.n_s, afm.n_s + afm.n_p)) if st.linear_trend else False
    sparse = uses_sparse(len(data.y), st)
    g_map, g_names = g_input_map(st.g_inputs, afm)
    trainer = VHGPR(g_input_map=g_map, g_input_names=g_names,
                    linear=linear, linear_prior_var=LINEAR_PRIOR_VAR if st.linear_trend else None,
                    se=st.se if st.linear_trend else "on", noise_features=features, noise_model=noise_model,
                    mean_features=mean_features,
                    n_restarts=st.restarts,
                    propagate_noise_parameter_uncertainty=st.noise_parameter_uncertainty,
                    max_iter=st.max_iter, random_state=st.seed, max_time=max_time,
                    g_start="both" if sparse else st.g_start, warm_start=warm_start, g_gp=st.g_gp != "off")
    if sparse:
        from microctl.gp.sparse import SparseVHGPR

        return SparseVHGPR(n_inducing=st.inducing, subset=SPARSE_SUBSET, hyper=trainer,
                           random_state=st.seed).fit(data.X, data.y)
    return trainer.fit(data.X, data.y)


def _fit_dictionary(data: ResidualData, afm: AnalyticForwardModel, st: ResidualModelSettings,
                    max_time: float | None) -> FittedVHGPR:
    """The ``dictionary`` noise model: which noise sources the stage has is selected by the data.

    1. the residual model with the physical noise model (every actuator's stick-slip) gives the
       mean correction f and so the residual r = y - f(x) at the training moves;
    2. :func:`~microctl.models.noise_dictionary.select_features` chooses among the stage's candidate
       sources (and a load tilt along the pose) by evidence, with a multiple-testing discipline
       (or takes the sources ``noise_sources`` names, :mod:`microctl.models.declared_sources`);
       rows whose reading is grossly off under that noise model fitted without them, and under
       the first model refitted without them, are set aside (:func:`_screened`,
       :mod:`microctl.models.outlier_screen`) and steps 1-2 redone without them;
    3. the residual model is fitted again with exactly the selected sources as g's prior mean
       (none selected: the paper's constant prior mean), their coefficients inside the bound;
    4. with ``mean_shift`` (the default), once more with the selected (ungated) sources also as
       features of a trend in f (:mod:`microctl.models.mean_shift`: the mean shift that scatter
       causes), started from step 3's model.

    The selection (names, log-likelihood gains and the gains they needed) and the rows set aside
    (``"screened"``: 0-based positions in ``data``, their deletion residuals, the bound;
    :func:`_screened`) are in
    ``info["noise_selection"]``.
    """
    sparse = uses_sparse(len(data.y), st)
    data, src, screened = _screened(data, afm, st, max_time)
    st, cands, sel = src.st, src.cands, src.sel
    mu, sd = src.pose_mean, src.pose_scale
    rows = [np.asarray(cands.matrix)[j] for j in sel.indices]
    offs = [float(np.asarray(cands.offset)[j]) for j in sel.indices]
    shapes = [cands.shapes[j] for j in sel.indices]
    params = [tuple(float(v) for v in np.asarray(cands.params)[j]) for j in sel.indices]
    names = [cands.names[j] for j in sel.indices]
    gates = [np.asarray(cands.gate)[j] for j in sel.indices]
    if sel.tilt is not None:  # exp(w . (u - mu) / sd) as a linear map of x = [s; u]
        a = np.zeros(data.X.shape[1] + afm.n_q)  # x = [s; u] and the move's context
        a[afm.n_s:afm.n_s + afm.n_p] = sel.tilt / sd
        gates.append(np.zeros_like(a))
        rows.append(a)
        offs.append(-float(sel.tilt @ (mu / sd)))
        shapes.append("exp")
        params.append((0.0, 0.0))
        names.append("tilt")
    record = {"selected": names, "gains_nats": [float(g) for g in sel.gains],
              "p_adjusted": [float(p) for p in sel.p_values], "alpha": SELECTION_ALPHA,
              "candidates": len(cands.names) + 1}
    if sel.swaps:
        record["shape_swaps"] = [list(sw) for sw in sel.swaps]
    if st.noise_sources is not None:
        record["declared"] = list(st.noise_sources)
    record["screened"] = screened
    model = _fit_selected(data, afm, st, rows, offs, names, shapes, params, gates, max_time)
    # a source the fit inside the bound does not support (its coefficient within one Laplace
    # standard error of 0, or its share of the prior variance below PRUNE_SHARE at every training
    # move) is not a source of this stage: refit without it (sources the user named are kept)
    keep = _effective_sources(model, model.X) if names and st.noise_sources is None else list(range(len(names)))
    if len(keep) < len(names):
        record["dropped_in_fit"] = [names[j] for j in range(len(names)) if j not in keep]
        record["selected"] = [names[j] for j in keep]
        record["gains_nats"] = [record["gains_nats"][j] for j in keep]
        record["p_adjusted"] = [record["p_adjusted"][j] for j in keep]
        # on many rows (sparse) the refit starts where the larger fit ended (one run)
        rows, offs, names, shapes, params, gates = ([v[j] for j in keep] for v in (rows, offs, names, shapes, params,
                                                                                  gates))
        model = _fit_selected(data, afm, st, rows, offs, names, shapes, params, gates, max_time,
                              warm_start=model if sparse else None)
    st, mf = _with_chosen_se(st, model), None  # the later fits start from this one's: f's SE part as it chose
    if st.mean_shift:  # the mean shift the selected sources' scatter causes (mean_shift)
        feats = trend_features(names, rows, offs, shapes, params, data.X.shape[1])
        model, shift = with_mean_shift(model, feats, lambda mf, warm: _fit_selected(
            data, afm, st, rows, offs, names, shapes, params, gates, max_time, warm, mf))
        if shift is not None:
            record["mean_shift"], mf = shift, feats
    if st.g_gp == "auto" and not sparse:  # g's GP must pay for its hyperparameters (g_gp_selection)
        model, record["g_gp"] = select_g_gp(model, lambda: _fit_selected(
            data, afm, replace(st, g_gp="off"), rows, offs, names, shapes, params, gates, max_time, model, mf), len(data.y))
    # the controller's least-motion rule (microctl.control.credible) weighs the alternatives by their
    # evidence (none where the user named the sources: those are the stage's, no other is weighed)
    if st.noise_sources is None:
        record["alternatives"] = alternatives_record(model, data, afm, cands)
    return replace(model, info={**model.info, "noise_selection": {**record, "n": int(len(data.y))}})


def _positions(data: ResidualData, afm: AnalyticForwardModel) -> np.ndarray:
    """The actuator positions before and after each move, ``[q_prev, K u]`` (eq. 12), standardised
    (the corrupt-reading screen's neighbourhoods), shape (n, 2 n_q)."""
    Q = np.hstack([data.X[:, 1:afm.n_s], data.X[:, afm.n_s:] @ afm.K.T])  # s = [t_prev; q_prev]
    return (Q - Q.mean(axis=0)) / np.maximum(Q.std(axis=0), 1e-12)


@dataclass(frozen=True)
class _Sources:
    """Steps 1 and 2 of :func:`_fit_dictionary` (:func:`_select_sources`).

    Attributes
    ----------
    st : ResidualModelSettings
        The settings, with f's SE part fixed where the sparse form's first fit chose it.
    first : FittedVHGPR
        The first fit (the physical noise model).
    first_rows : ndarray of int or None
        The rows of ``data`` it was fitted on (None: every row).
    r : ndarray, shape (n,)
        The residual of its mean correction.
    cands : ShapedFeatures
        The candidate sources, rescaled to ``data.X``.
    sel : Selection
    pose_mean, pose_scale : ndarray, shape (n_p,)
        The standardisation of the poses u the tilt source grows along.
    """

    st: ResidualModelSettings
    first: FittedVHGPR
    first_rows: np.ndarray | None
    r: np.ndarray
    cands: Any
    sel: Any
    pose_mean: np.ndarray
    pose_scale: np.ndarray

    def tilt_inputs(self, data: ResidualData, n_s: int) -> np.ndarray:
        """The standardised poses of ``data``, shape (n, n_p)."""
        return (data.X[:, n_s:] - self.pose_mean) / self.pose_scale


def _select_sources(data: ResidualData, afm: AnalyticForwardModel, st: ResidualModelSettings,
                    max_time: float | None) -> _Sources:
    """Steps 1 and 2 of :func:`_fit_dictionary`: the first fit's residual and the selection."""
    idx = None
    if uses_sparse(len(data.y), st):
        from microctl.gp.sparse import subset_rows

        # the first fit only gives f for the residuals: an exact fit on the rows the sparse model's
        # hyperparameters are fitted on does (the selection still reads all n residuals), from
        # one start; f's SE part is chosen there (BIC) once for the fits that follow
        idx = subset_rows(np.random.default_rng(st.seed), len(data.y), SPARSE_SUBSET)
        sub = data.rows(idx)
        first = _fit(sub, afm, replace(st, gp="exact", restarts=1), noise_features_for(afm), "physical", max_time)
        st = _with_chosen_se(st, first)
    else:
        first = _fit(data, afm, st, noise_features_for(afm), "physical", max_time)
    r = data.y - first.predict(data.X).f_mean
    Xc = data.context_inputs(afm.n_q)  # x = [s; u] and the move's context
    cands = candidate_features(afm, context=True).rescaled(Xc)
    U = data.X[:, afm.n_s:]
    mu, sd = U.mean(axis=0), np.maximum(U.std(axis=0), 1e-12)
    if st.noise_sources is None:
        sel = select_features(r, cands.values(Xc), cands.names, tilt_inputs=(U - mu) / sd, alpha=SELECTION_ALPHA)
    else:  # named by the user: no test, kept (microctl.models.declared_sources)
        sel = declared_selection(r, cands.values(Xc), cands.names, st.noise_sources)
    return _Sources(st, first, idx, r, cands, sel, mu, sd)


def _with_chosen_se(st: ResidualModelSettings, model: FittedVHGPR) -> ResidualModelSettings:
    """``st`` with f's SE part fixed to what ``model``'s fit chose (``se: auto``), else ``st``."""
    chosen = model.info.get("se_selection")
    return st if chosen is None else replace(st, se="on" if chosen["kept_se"] else "off")


def _screened(data: ResidualData, afm: AnalyticForwardModel, st: ResidualModelSettings,
              max_time: float | None) -> tuple[ResidualData, _Sources, dict]:
    """Steps 1 and 2 of :func:`_fit_dictionary` with the corrupt-reading screen
    (:mod:`microctl.models.outlier_screen`): suspects beyond the bound under the sources selected
    without each (:func:`~microctl.models.outlier_screen.sources_without_row`) are confirmed with
    the whole first model refitted without it (:func:`_deletion_z`) against the same bound; rows
    confirmed are set aside and steps 1-2 redone, up to :data:`SCREEN_ROUNDS` times.

    Returns
    -------
    data : ResidualData
        Without the rows set aside.
    sources : _Sources
        Steps 1-2 on it.
    record : dict
        ``rows`` set aside (0-based positions in the given data), their ``z`` (the whole model's
        deletion residual), ``bound`` (:func:`~microctl.models.outlier_screen.tail_bound`, with
        its ``tail_nu``; ``gaussian_bound`` beside it), ``alpha``, and ``withheld``: how many rows
        the screen found beyond the bound when that was more than it may set aside (else 0).
    """
    n0 = len(data.y)
    original = np.arange(n0)
    tails, nu = bonferroni_bound(n0), float("inf")
    src = _select_sources(data, afm, st, max_time)
    rows: list[int] = []
    zs: list[float] = []
    withheld = 0
    for _ in range(SCREEN_ROUNDS):  # a second corrupt reading can hide behind the first
        room = max_screened(n0) - len(rows)
        if room <= 0:
            break
        reselect, pool = st.noise_sources is None, (src.r, src.cands.values(data.context_inputs(afm.n_q)), src.cands.names,
                                                    src.tilt_inputs(data, afm.n_s))  # sources named by the user are kept
        suspects, Phi, Z, tilt = screening_sources(*pool, src.sel, reselect=reselect, alpha=SELECTION_ALPHA)
        found = screen_rows(src.r, Phi, tilt_inputs=Z, tilt=tilt, suspects=suspects, local_inputs=_positions(data, afm),
                            max_rows=room, own_sources=sources_without_row(*pool, alpha=SELECTION_ALPHA) if reselect else None)
        withheld = found.exceeding if found.withheld else 0
        tails, nu = found.bound, found.nu
        confirmed = [(i, z) for i in found.rows if abs(z := _deletion_z(data, afm, src, i, max_time)) > tails]
        if not confirmed:
            break
        rows += [int(original[i]) for i, _ in confirmed]
        zs += [float(z) for _, z in confirmed]
        keep = np.setdiff1d(np.arange(len(data.y)), [i for i, _ in confirmed])
        data, original = data.rows(keep), original[keep]
        src = _select_sources(data, afm, st, max_time)
    order = np.argsort(rows)
    return data, src, {"rows": [rows[k] for k in order], "z": [zs[k] for k in order], "bound": float(tails),
                       "gaussian_bound": float(bonferroni_bound(n0)), "tail_nu": float(nu),
                       "alpha": SCREEN_ALPHA, "withheld": int(withheld)}


def _deletion_z(data: ResidualData, afm: AnalyticForwardModel, src: _Sources, i: int,
                max_time: float | None) -> float:
    """Row i's residual against the first model refitted without it (from the fit with it: a warm
    start, a fraction of a fit's time), standardised by that model's predictive variance there,
    ``f_var + E[exp(g)]``. With the sparse form's subset fit, a row outside the subset is judged
    by the first fit as it is (it was not fitted on it)."""
    model = src.first
    rows = np.arange(len(data.y)) if src.first_rows is None else np.asarray(src.first_rows)
    if i in rows:
        keep = rows[rows != i]
        st = _with_chosen_se(replace(src.st, gp="exact", restarts=1), model)
        model = _fit(data.rows(keep), afm, st,
                     noise_features_for(afm), "physical", max_time, warm_start=model)
    p = model.predict(data.X[i:i + 1])
    return float((data.y[i] - p.f_mean[0]) / np.sqrt(p.f_var[0] + np.exp(p.g_mean[0] + 0.5 * p.g_var[0])))


#: a selected source whose fitted share of g's prior variance stays below this at every training
#: move is dropped (the fit inside the bound switched it off; keeping it would only name it)
PRUNE_SHARE = 1e-3
#: ... and so is one whose fitted coefficient is below this many of its Laplace standard errors
#: (the bound, where g's GP can take up what the parametric selection saw, does not support it)
PRUNE_Z = 1.0


def _fit_selected(data, afm, st, rows, offs, names, shapes, params, gates, max_time, warm_start=None,
                  mean_features=None) -> FittedVHGPR:
    """The residual model with exactly the given sources as g's prior mean (none: the constant).

    The sources act on x = [s; u] and the move's context; when none reads the context (no
    reversal source), the model is trained on x alone."""
    if not names:  # the constant prior mean, under the dictionary's name (it chose no source)
        return replace(_fit(data, afm, st, None, "hgp", max_time, warm_start), noise_model_name="dictionary")
    A, G, d = np.array(rows), np.array(gates), data.X.shape[1]
    if not np.any(G):
        feats = NoiseFeatures(A[:, :d], np.array(offs), tuple(names), tuple(shapes), tuple(params))
        return _fit(data, afm, st, feats, "dictionary", max_time, warm_start, mean_features)
    feats = NoiseFeatures(A, np.array(offs), tuple(names), tuple(shapes), tuple(params), gate=G,
                          context=A.shape[1] - d)
    return _fit(data.with_context(afm.n_q), afm, st, feats, "dictionary", max_time, warm_start, mean_features)


def _effective_sources(model: FittedVHGPR, X: np.ndarray) -> list[int]:
    """Indices of the sources whose share ``c_j phi_j(x) / V(x)`` of the fitted prior variance
    (:mod:`microctl.gp.noise_prior` eq. 1) reaches :data:`PRUNE_SHARE` at some row of X (the
    model's own training inputs ``model.X``, in the coordinates its prior mean reads) and whose
    coefficient is at least :data:`PRUNE_Z` Laplace standard errors (``info["noise_parameters"]``)."""
    prior = model.g_prior_mean
    D = prior.design(X)
    share = D * prior.coef / (D @ prior.coef)[:, None]
    par = model.info.get("noise_parameters") or {}
    c, c_std = np.asarray(par.get("c", prior.coef)), np.asarray(par.get("c_std", np.zeros(prior.p + 1)))
    return [j for j in range(prior.p)
            if float(np.max(share[:, j + 1])) >= PRUNE_SHARE and c[j + 1] >= PRUNE_Z * c_std[j + 1]]


def save_model(model: FittedVHGPR, path: str | Path) -> None:
    """Write the model (``.npz``)."""
    model.save(path)
