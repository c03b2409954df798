"""The VHGPR trainer: settings, the fit (L-BFGS-B on the MV bound) and its restarts.

:class:`VHGPR` holds the settings and :meth:`VHGPR.fit` maximises the bound ``F`` of
:mod:`microctl.gp.bound` with analytic gradients (over log Lambda, log kernel
hyperparameters and g's prior mean log c), starting from a homoscedastic GP
(:mod:`microctl.gp.homoscedastic`); it returns a frozen :class:`~microctl.gp.fitted.FittedVHGPR`.
Inputs and outputs are standardised (``notes/vhgpr.md``, cited as [N]).
"""

from __future__ import annotations

import math
import time
from dataclasses import replace
from typing import Any

import numpy as np
from scipy.optimize import minimize

from microctl.errors import ConfigError, DataError, MicroctlError
from microctl.gp.arrays import freeze, training_hash, validate_training
from microctl.gp.bound import BOUNDS, Layout, mean_coef_covariance, mv_bound
from microctl.gp.fitted import FittedVHGPR
from microctl.gp.homoscedastic import fit_homoscedastic, init_mean_coef
from microctl.gp.kernels import KernelSpec
from microctl.gp.noise_models import NoiseModel, noise_model_class
from microctl.gp.noise_prior import NoiseFeatures
from microctl.gp.noise_start import log_residual_start
from microctl.gp.shaped_features import ShapedFeatures
from microctl.gp.trend import FeatureTrend
from microctl.util.bic import bic_penalty
from microctl.util.blas import single_thread_blas

__all__ = ["VHGPR", "default_max_iter", "G_STARTS"]

G_STARTS = ("f", "both", "residuals")  # where g starts (VHGPR g_start)
#: The residual run wins only by this many BIC penalties of g's kernel, (kg + 1)/2 log n (docs/vhgpr.md).
RESIDUAL_RUN_HANDICAP = 1.0


def default_max_iter(n: int) -> int:
    """Iterations per run when ``max_iter`` is None: 100 up to n = 200, then 100 (200/n)^0.6, at least 25.

    Each iteration costs O(n^3), and with more points fewer iterations are needed: how the
    bound and the hold-out NLPD move with the cap is measured by ``python scripts/bench_vhgpr.py
    --iter-sweep 20,40,60,100,200,400`` (docs/generated/bench_vhgpr.md, "iteration sweep").
    The formula gives 58 at n = 500, 38 at n = 1000 and 25 at n = 2000.
    """
    return int(max(25, min(100, round(100 * (200 / n) ** 0.6))))


def _noise_model(name: str | None, features: NoiseFeatures | None) -> NoiseModel:
    """The noise model named ``name`` (None: ``"physical"`` with features, ``"hgp"`` without)."""
    if name is None:
        name = "hgp" if features is None else "physical"
    try:
        noise = noise_model_class(name)()
    except KeyError as exc:
        raise ConfigError(f"VHGPR: {exc.args[0]}") from None
    if noise.uses_features != (features is not None):
        raise ConfigError(f"VHGPR: noise model {name!r} {'needs' if noise.uses_features else 'takes no'} "
                          "noise_features")
    return noise


def _standardise(X: np.ndarray, y: np.ndarray) -> dict:
    """Training hash and standardisation of (X, y): ``x_mean, x_scale, y_mean, y_scale, Xs, ys``.

    A constant input column keeps ``x_scale = 1``.
    """
    x_mean = X.mean(axis=0)
    x_scale = X.std(axis=0)
    x_scale[x_scale <= 1e-12 * np.maximum(1.0, np.abs(x_mean))] = 1.0  # constant input column
    y_mean = float(y.mean())
    y_scale = float(y.std())
    Xs = (X - x_mean) / x_scale
    ys = (y - y_mean) / y_scale
    return {"training_hash": training_hash(X, y), "x_mean": x_mean, "x_scale": x_scale, "y_mean": y_mean,
            "y_scale": y_scale, "Xs": Xs, "ys": ys}


#: Prior variance of f's feature-trend coefficients (fixed; standardised outputs per unit of a
#: feature scaled to its training mean: the vague limit, as :data:`~microctl.models.training.LINEAR_PRIOR_VAR`).
TREND_PRIOR_VAR = 10.0


def trend_fields(trend: FeatureTrend | None) -> dict[str, Any]:
    """The :class:`FittedVHGPR` arrays of f's feature trend (all None without one)."""
    if trend is None:
        return {"f_trend_matrix": None, "f_trend_offset": None, "f_trend_params": None, "f_trend_scale": None,
                "f_trend_log_var": None}
    f = trend.features
    return {"f_trend_matrix": np.array(f.matrix, dtype=float), "f_trend_offset": np.array(f.offset, dtype=float),
            "f_trend_params": np.array(f.params, dtype=float), "f_trend_scale": np.array(f.scale, dtype=float),
            "f_trend_log_var": float(trend.log_var)}


# --------------------------------------------------------------------------- the trainer


class VHGPR:
    """Settings of the VHGPR trainer (scikit-learn style); :meth:`fit` returns a :class:`FittedVHGPR`.

    Parameters
    ----------
    bias : bool
        Add a constant (bias) term to both kernels.
    linear : bool or sequence of int
        Add a linear part to f's kernel (:mod:`microctl.gp.kernels`): Bayesian linear
        regression inside the GP, so the mean extrapolates along a fitted trend and its
        variance includes the trend's uncertainty. The noise model weights every point, so
        noisy points do not dominate the trend. True: on every input; a sequence: on those
        input columns (0-based) only.
    linear_prior_var : float or None
        None: the linear part's variances are fitted (ARD, log space). A number: the prior
        variance of every linear coefficient, fixed (standardised units; a large value is
        the vague-prior limit of R&W 2.7, where the trend is estimated by generalised least
        squares and no hyperparameter can switch it off).
    mean_features : ShapedFeatures, optional
        Fixed features of f's feature trend (:mod:`microctl.gp.trend`), ungated maps of the
        inputs the kernels read in their original units, each rescaled to its mean over the
        training inputs here; their coefficients' prior variance is :data:`TREND_PRIOR_VAR`.
        None (default): no trend of features.
    noise_features : NoiseFeatures, optional
        Features of a parametric prior mean of g (:mod:`microctl.gp.noise_prior` eq. 1), in the
        units of the inputs and of y. None (default): the paper's constant mu0.
    noise_model : str, optional
        Name of the noise model (:mod:`microctl.gp.noise_models`) that turns the features into
        g's prior mean. None (default): ``"physical"`` with features, ``"hgp"`` without.
    n_restarts : int
        Number of optimisation runs in total (>= 1).  The first starts from the
        homoscedastic GP fit; the others from seeded random perturbations of it.  The run
        with the largest bound wins; runs that fail numerically are recorded and skipped.
    max_iter : int or None
        L-BFGS-B iterations per run (function evaluations are capped at 1.25 times this).
        None (default): 100 for n <= 200, then 100 (200/n)^0.6 but at least 25 (58 at
        n = 500, 25 at n = 2000), since each iteration costs O(n^3) and more data need fewer.
    random_state : int or None
        Seed of the perturbations and of the initialisation subset (None: fresh entropy).
    tol : float
        L-BFGS-B ``ftol`` (relative decrease of the negative bound).
    max_time : float or None
        Wall-clock budget in seconds for all runs together; a run that reaches it stops
        and keeps its best point so far.  None: no budget.
    se : {"on", "off", "auto"}
        f's squared-exponential (nonlinear) part. ``"auto"`` (with a linear trend): fit f
        with and without it and keep it only if it raises the MV bound by more than its
        d + 1 hyperparameters cost, ``(d + 1)/2 log n`` (the BIC penalty): on data whose
        mean the trend explains, a free SE part with d lengthscales fits the noise (on
        simulated rigs: a few nats of bound for a larger error at the workspace's faces),
        while a real nonlinear effect (backlash, contact loss) pays far more.
        ``"off"`` needs a linear trend.
    propagate_noise_parameter_uncertainty : bool
        Add the Laplace variance of g's parametric prior mean (``noise_prior`` eq. 2) to g's
        posterior variance. Default False: the covariance is always computed and kept in
        ``info["noise_parameters"]`` (standard errors), but g's variance is the GP's alone.
        Measured on 24 simulated rigs (scripts/bench_rigs.py, docs/controller.md): a
        Gaussian approximation cannot tell a small friction from zero on an actuator the data
        barely isolate, and the quantile objective then avoids the truly quietest poses.
    g_start : {"both", "f", "residuals"}
        Where g's lengthscales start. ``"both"`` (default): the runs above start at the
        homoscedastic fit's lengthscales of f, and one more run starts from unit lengthscales
        (standardised inputs). ``"f"``: only the former. A noise that depends on an input the mean
        ignores is out of reach from f's lengthscales (there, the lengthscale starts at the upper
        bound and the gradient vanishes): on the 3-D synthetic of ``scripts/bench_vhgpr.py``
        (``planted3d``) the extra run finds the heteroscedastic optimum ``"f"`` misses at n = 2000,
        for one more run's time (docs/generated/bench_vhgpr.md, the scale rows). The stage's
        residual model (:mod:`microctl.models.training`) sets it explicitly: ``"f"`` for the exact
        form, where its noise model's parametric prior mean carries the physical inputs,
        ``"both"`` for the sparse form's hyperparameters. ``"residuals"``: as ``"f"``, and one more
        run starts g from a GP fitted to the log squared residuals of the start's f
        (:mod:`microctl.gp.noise_start`): from the usual start g's signal variance tends to
        collapse to its bound before g's mean has moved, whatever the noise does. That run
        wins only if its bound beats the others' by g's kernel's BIC penalty, (kg + 1)/2 log n.
    warm_start : FittedVHGPR, optional
        A model fitted to the same kind of data whose hyperparameters start the fit instead of
        the homoscedastic GP: one run (``n_restarts`` and ``g_start`` are not used), f's and g's
        kernels as they are, g's prior-mean coefficients matched by feature name (so a refit
        with some noise sources dropped starts where the larger fit ended), the variational
        parameters from the start when it was fitted to these very points, else at their usual
        start. Needs ``se`` "on" or "off" (the start's choice), and kernels of the same form.
    g_input_map : array_like, shape (kg, k), optional
        g's kernel reads ``A x``, not the k inputs x (original units; :mod:`microctl.gp.kernels`,
        :mod:`microctl.models.noise_inputs`), stored standardised with each row scaled to unit
        spread over the training inputs. None (default): the raw inputs.
    g_input_names : sequence of str, optional
        A name per row of ``g_input_map``.
    g_gp : bool
        False: g's GP is switched off (lengthscales at the wide bound, signal variance at the
        floor), so g is its prior mean; the dictionary model's test of whether it pays for itself.
    """

    def __init__(
        self,
        *,
        bias: bool = False,
        linear: bool | tuple[int, ...] = False,
        linear_prior_var: float | None = None,
        mean_features: ShapedFeatures | None = None,
        noise_features: NoiseFeatures | None = None,
        noise_model: str | None = None,
        n_restarts: int = 2,
        max_iter: int | None = None,
        random_state: int | None = 0,
        tol: float = 1e-9,
        max_time: float | None = None,
        se: str = "on",
        propagate_noise_parameter_uncertainty: bool = False,
        g_start: str = "both",
        warm_start: FittedVHGPR | None = None,
        g_input_map: Any = None,
        g_input_names: tuple[str, ...] = (),
        g_gp: bool = True,
    ) -> None:
        if int(n_restarts) != n_restarts or n_restarts < 1:
            raise ConfigError(f"VHGPR: n_restarts must be an integer >= 1, got {n_restarts!r}")
        if max_iter is not None and (int(max_iter) != max_iter or max_iter < 1):
            raise ConfigError(f"VHGPR: max_iter must be an integer >= 1, got {max_iter!r}")
        if not (tol > 0):
            raise ConfigError(f"VHGPR: tol must be positive, got {tol!r}")
        if max_time is not None and not (max_time > 0):
            raise ConfigError(f"VHGPR: max_time must be positive or None, got {max_time!r}")
        if mean_features is not None and not isinstance(mean_features, ShapedFeatures):
            raise ConfigError(f"VHGPR: mean_features must be a ShapedFeatures or None, got {type(mean_features).__name__}")
        if noise_features is not None and not isinstance(noise_features, NoiseFeatures):
            raise ConfigError(f"VHGPR: noise_features must be a NoiseFeatures or None, got {type(noise_features).__name__}")
        if linear_prior_var is not None and not (isinstance(linear_prior_var, (int, float))
                                                 and math.isfinite(linear_prior_var) and linear_prior_var > 0):
            raise ConfigError(f"VHGPR: linear_prior_var must be a positive number or None, got {linear_prior_var!r}")
        if not isinstance(linear, bool):
            linear = tuple(int(i) for i in linear)
            if not linear or min(linear) < 0:
                raise ConfigError(f"VHGPR: linear must be a bool or non-empty input indices, got {linear!r}")
        if g_start not in G_STARTS:
            raise ConfigError(f"VHGPR: g_start must be one of {', '.join(map(repr, G_STARTS))}, got {g_start!r}")
        if se not in ("on", "off", "auto"):
            raise ConfigError(f"VHGPR: se must be 'on', 'off' or 'auto', got {se!r}")
        if se != "on" and linear is False:
            raise ConfigError(f"VHGPR: se={se!r} needs a linear trend (linear=True or input indices); "
                              "without it f would be a constant")
        if warm_start is not None and se == "auto":
            raise ConfigError("VHGPR: a warm start needs se 'on' or 'off' (the start model's choice), not 'auto'")
        if g_input_map is not None:
            g_input_map = np.array(g_input_map, dtype=float)
            if g_input_map.ndim != 2 or g_input_map.shape[0] < 1 or not np.all(np.isfinite(g_input_map)):
                raise ConfigError(f"VHGPR: g_input_map must be a finite 2-D array (kg, k), got shape {g_input_map.shape}")
            if g_input_names and len(g_input_names) != g_input_map.shape[0]:
                raise ConfigError(f"VHGPR: {len(g_input_names)} g_input_names for {g_input_map.shape[0]} rows of g_input_map")
        self.g_input_map = g_input_map
        self.g_input_names = tuple(str(nm) for nm in g_input_names) if g_input_map is not None else ()
        self.se, self.g_gp = se, bool(g_gp)
        self.g_start = g_start
        self.warm_start = warm_start
        self.propagate = bool(propagate_noise_parameter_uncertainty)
        self.bias = bool(bias)
        self.linear = linear
        self.linear_prior_var = None if linear_prior_var is None else float(linear_prior_var)
        self.noise_features = noise_features
        self.mean_features = mean_features
        self.noise = _noise_model(noise_model, noise_features)
        self.n_restarts = int(n_restarts)
        self.max_iter = None if max_iter is None else int(max_iter)
        self.random_state, self.tol, self.max_time = random_state, float(tol), max_time

    def __repr__(self) -> str:
        nf = None if self.noise_features is None else list(self.noise_features.names)
        return (f"VHGPR(bias={self.bias}, linear={self.linear}, linear_prior_var={self.linear_prior_var}, se={self.se!r}, "
                f"g_gp={self.g_gp}, noise_features={nf}, n_restarts={self.n_restarts}, "
                f"max_iter={self.max_iter}, random_state={self.random_state}, tol={self.tol}, max_time={self.max_time})")

    def fit(self, X: Any, y: Any) -> FittedVHGPR:
        """Maximise the MV bound on (X, y).

        Parameters
        ----------
        X : array_like, shape (n, d)  (a 1-D array is taken as one input column)
        y : array_like, shape (n,)

        Returns
        -------
        FittedVHGPR

        Raises
        ------
        DataError
            Non-finite values, wrong shapes, n < 2, mismatched lengths, constant y, noise
            features of the wrong width.
        MicroctlError
            Every optimisation run failed numerically.
        """
        t0 = time.perf_counter()
        X, y = validate_training(X, y)
        nf = self.noise_features
        if not isinstance(self.linear, bool) and max(self.linear) >= X.shape[1]:
            raise DataError(f"linear trend on input column {max(self.linear)}; X has {X.shape[1]} columns")
        if nf is not None and np.asarray(nf.matrix).shape[1] != X.shape[1]:
            raise DataError(f"noise features act on {np.asarray(nf.matrix).shape[1]} inputs; X has {X.shape[1]} columns")
        k_read = X.shape[1] - (0 if nf is None else int(nf.context))
        if self.g_input_map is not None and self.g_input_map.shape[1] != k_read:
            raise DataError(f"g_input_map acts on {self.g_input_map.shape[1]} inputs; the kernels read {k_read} "
                            f"columns of X")
        with single_thread_blas():
            return self._fit(X, y, t0)

    def _fit(self, X: np.ndarray, y: np.ndarray, t0: float) -> FittedVHGPR:
        n, d_all = X.shape
        data = _standardise(X, y)
        Xs, ys = data["Xs"], data["ys"]
        nf, noise = self.noise_features, self.noise
        Phi = As = bs = gate = None
        if nf is not None and nf.p > 0:
            As, bs = nf.standardised(data["x_mean"], data["x_scale"], data["y_scale"])
            gate = nf.standardised_gate(data["x_mean"], data["x_scale"])
            noise = noise.for_features(nf, data["y_scale"])
            Phi = noise.design(Xs, As, bs, gate)
        else:
            noise = noise_model_class("hgp")()  # no features: the constant prior mean
        # the kernels read the first d inputs; a trailing context only g's prior mean reads
        d = d_all - (0 if nf is None else int(nf.context))

        rng = np.random.default_rng(self.random_state)
        # a linear trend is affine: f's kernel gets the constant (bias) term with it
        f_spec = KernelSpec(d=d, bias=self.bias or self.linear is not False, linear=self.linear is not False,
                            trend=self._trend(X[:, :d], data["x_mean"][:d], data["x_scale"][:d]))
        g_spec = self._g_spec(Xs[:, :d], data["x_scale"][:d])
        lin_bounds = self._linear_bounds(d)
        p = 0 if Phi is None else Phi.shape[1]
        init_cost: dict = {}  # what the homoscedastic initialisation cost (starts, evaluations, time_s)
        if self.warm_start is None:
            # the start is the homoscedastic GP without f's feature trend: a homoscedastic GP given a
            # trend along a heteroscedastic noise's direction can prefer to interpolate the data (noise
            # variance at its floor), a start the VHGPR does not leave (tests/gp/test_trend.py)
            gp, loo, used = fit_homoscedastic(Xs[:, :d], ys, replace(f_spec, trend=None), rng, lin_bounds, init_cost)
            kern = gp[:-1]
            # Initial point [N]: f's kernel from the homoscedastic GP, Lambda = 1/2 (so mu = m);
            # g's prior mean from its leave-one-out residuals (mu0 = its log noise without features);
            # g's kernel: f's lengthscales (unit ones on mapped inputs, of unit spread), unit signal variance.
            g_kern = np.concatenate([kern[:d] if g_spec.input_map is None else np.zeros(g_spec.d), [0.0],
                                     [-4.0] if self.bias else []])
            mean0 = init_mean_coef(loo, None if Phi is None else Phi[used], float(gp[-1]))
            x_init = np.concatenate([np.full(n, math.log(0.5)), kern, g_kern, mean0])
        else:
            gp = kern = None
            names = () if Phi is None else tuple(nf.names)
            x_init = self._warm_point(n, f_spec, g_spec, names, data["training_hash"])

        max_iter = self.max_iter if self.max_iter is not None else default_max_iter(n)
        deadline = None if self.max_time is None else t0 + float(self.max_time)
        layout, best, runs, selection = self._fit_variants(x_init, Xs, ys, f_spec, g_spec, p, lin_bounds, rng,
                                                           deadline, max_iter, Phi)
        F, _, state = mv_bound(theta := best[1], Xs, ys, layout, want_grad=False, want_state=True, Phi=Phi)
        log_c = theta[layout.mean_slice]
        coef_cov = mean_coef_covariance(state, log_c, Phi) if Phi is not None else None
        info = self._info(state, runs, gp, kern, selection, coef_cov, log_c, max_iter, t0, init_cost)
        kf, kg = f_spec.unpack(theta[layout.f_slice]), g_spec.unpack(theta[layout.g_slice])
        arrays = {
            "x_mean": data["x_mean"], "x_scale": data["x_scale"], "X": Xs,
            "f_log_lengthscales": np.array(kf.log_lengthscales), "g_log_lengthscales": np.array(kg.log_lengthscales),
            "log_lambda": theta[:n].copy(), "f_alpha": state["f_alpha"], "f_chol": state["f_chol"],
            "g_beta": state["g_beta"], "g_chol": state["g_chol"],
        }
        optional = {
            "f_log_linear_vars": None if kf.log_linear_vars is None else np.array(kf.log_linear_vars),
            "g_feature_matrix": As, "g_feature_offset": bs,
            "g_log_feature_coef": None if Phi is None else np.array(log_c[1:]),
            "g_mean_coef_cov": coef_cov if self.propagate else None,
            "g_feature_gate": None if gate is None else gate[0], "g_feature_gate_offset": None if gate is None else gate[1],
            "g_input_map": None if g_spec.input_map is None else np.array(g_spec.input_map, dtype=float),
            **trend_fields(f_spec.trend), "g_input_names": self.g_input_names,
        }
        for a in list(arrays.values()) + [v for v in optional.values() if isinstance(v, np.ndarray)]:
            freeze(a)
        return FittedVHGPR(
            **arrays, **optional,
            y_mean=data["y_mean"], y_scale=data["y_scale"],
            f_log_signal_var=kf.log_signal_var, f_log_bias_var=kf.log_bias_var,
            g_log_signal_var=kg.log_signal_var, g_log_bias_var=kg.log_bias_var,
            g_mu0=float(log_c[0]), bound=float(F), training_hash=data["training_hash"], info=info,
            g_feature_names=() if nf is None else tuple(nf.names), noise_model_name=noise.name,
            g_feature_shapes=() if nf is None else tuple(nf.shapes),
            g_feature_params=() if nf is None else tuple((float(a), float(b)) for a, b in nf.params),
            f_trend_names=() if f_spec.trend is None else f_spec.trend.features.names,
            f_trend_shapes=() if f_spec.trend is None else f_spec.trend.features.shapes,
        )

    def _g_spec(self, Xs: np.ndarray, x_scale: np.ndarray) -> KernelSpec:
        """g's kernel spec on the standardised inputs Xs (n, k); its input map, if any, is ``A`` in
        original units times the inputs' scales, each row divided by its spread over Xs (1 where it
        has none)."""
        if self.g_input_map is None:
            return KernelSpec(d=Xs.shape[1], bias=self.bias)
        A = self.g_input_map * x_scale[None, :]
        spread = (Xs @ A.T).std(axis=0)
        spread[spread <= 1e-12] = 1.0
        M = A / spread[:, None]
        return KernelSpec(d=M.shape[0], bias=self.bias, input_map=tuple(tuple(float(v) for v in row) for row in M))

    def _trend(self, X: np.ndarray, x_mean: np.ndarray, x_scale: np.ndarray) -> FeatureTrend | None:
        """f's feature trend from ``mean_features`` rescaled on the training inputs X (original units)."""
        mf = self.mean_features
        if mf is None:
            return None
        return FeatureTrend.from_original_units(mf.rescaled(X), x_mean, x_scale, math.log(TREND_PRIOR_VAR))

    def _warm_point(self, n: int, f_spec: KernelSpec, g_spec: KernelSpec, names: tuple[str, ...],
                    thash: str) -> np.ndarray:
        """The initial point from ``warm_start`` (see the class), shape (layout size,)."""
        w = self.warm_start
        kf, kg = w.f_kernel, w.g_kernel
        # a trend may differ, and g's input map (standardised on other rows) by its scaling
        if replace(kf.spec, trend=None) != replace(f_spec, trend=None) or (
                replace(kg.spec, input_map=None) != replace(g_spec, input_map=None)
                or (kg.spec.input_map is None) != (g_spec.input_map is None)):
            raise ConfigError(f"VHGPR: the warm start's kernels ({kf.spec}, {kg.spec}) are not of this fit's form "
                              f"({f_spec}, {g_spec})")
        coef = {} if w.g_log_feature_coef is None else dict(zip(w.g_feature_names, np.asarray(w.g_log_feature_coef)))
        missing = [nm for nm in names if nm not in coef]
        if missing:
            raise ConfigError(f"VHGPR: the warm start has no coefficient for the noise feature(s) {missing}; "
                              f"it has {sorted(coef)}")
        same = w.training_hash == thash and np.size(w.log_lambda) == n
        lam = np.array(w.log_lambda, dtype=float) if same else np.full(n, math.log(0.5))
        return np.concatenate([lam, kf.pack(), kg.pack(), [float(w.g_mu0)], [float(coef[nm]) for nm in names]])

    def _fit_variants(self, x_init: np.ndarray, Xs: np.ndarray, ys: np.ndarray, f_spec: KernelSpec,
                      g_spec: KernelSpec, p: int, lin_bounds: tuple[tuple[float, float], ...] | None,
                      rng: np.random.Generator, deadline: float | None, max_iter: int, Phi: np.ndarray | None
                      ) -> tuple[Layout, tuple[float, np.ndarray], list[dict], dict | None]:
        """Optimise with f's SE part on, off, or both (``se="auto"``, BIC selection).

        Returns the winning layout, (bound, theta), every run, and the selection record (None
        unless ``"auto"``).
        """
        n, d = Xs.shape[0], f_spec.d  # the SE part's lengthscales: the inputs the kernels read
        variants = {"on": (False,), "off": (True,), "auto": (True, False)}[self.se]
        fits = []
        for se_off in variants:
            layout = Layout(n=n, f=f_spec, g=g_spec, p=p, linear_bounds=lin_bounds, se_off=se_off, g_off=not self.g_gp)
            best, runs = self._optimise(x_init, Xs, ys, layout, rng, deadline, max_iter, Phi)
            fits.append((layout, best, runs))
        selection = None
        if len(fits) == 2:  # "auto": the SE part must pay for its d + 1 hyperparameters (BIC)
            penalty = bic_penalty(d + 1, n)
            gain = fits[1][1][0] - fits[0][1][0]
            selection = {"bound_affine": fits[0][1][0], "bound_with_se": fits[1][1][0], "penalty": penalty,
                         "kept_se": bool(gain > penalty)}
            layout, best, runs = fits[1] if gain > penalty else fits[0]
            runs = fits[0][2] + fits[1][2]
        else:
            layout, best, runs = fits[0]
        return layout, best, runs, selection

    def _info(self, state: dict, runs: list[dict], gp: np.ndarray | None, kern: np.ndarray | None, selection: dict | None,
              coef_cov: np.ndarray | None, log_c: np.ndarray, max_iter: int, t0: float, init_cost: dict) -> dict:
        """The fit's diagnostics record (``FittedVHGPR.info``)."""
        nf = self.noise_features
        noise_parameters = None
        if coef_cov is not None:
            noise_parameters = {"names": ["constant"] + list(nf.names), "c": np.exp(log_c).tolist(),
                                "c_std": np.sqrt(np.diag(coef_cov)).tolist(), "c_cov": coef_cov.tolist(),
                                "units": "standardised (y_scale^2)", "propagated": self.propagate}
        return {
            "jitter": float(state["jitter"]),
            "restarts_tried": len(runs),
            "restarts_failed": sum(r["status"] == "failed" for r in runs),
            "runs": runs,
            "iterations": int(sum(r.get("iterations", 0) for r in runs)),
            "evaluations": int(sum(r.get("evaluations", 0) for r in runs)),
            "homoscedastic_init": (None if gp is None else
                                   {"log_noise_var": float(gp[-1]), "kernel": [float(v) for v in kern], **init_cost}),
            "warm_start": self.warm_start is not None,
            "se_selection": selection,
            "noise_parameters": noise_parameters,
            "time_s": time.perf_counter() - t0,
            "settings": {"bias": self.bias, "linear": self.linear, "linear_prior_var": self.linear_prior_var,
                         "se": self.se, "g_gp": self.g_gp, "propagate_noise_parameter_uncertainty": self.propagate,
                         "n_restarts": self.n_restarts, "g_start": self.g_start,
                         "max_iter": max_iter, "random_state": self.random_state, "tol": self.tol,
                         "max_time": self.max_time,
                         "noise_features": None if nf is None else list(nf.names),
                         "mean_features": None if self.mean_features is None else list(self.mean_features.names)},
        }

    def _optimise(self, x_init: np.ndarray, Xs: np.ndarray, ys: np.ndarray, layout: Layout,
                  rng: np.random.Generator, deadline: float | None, max_iter: int, Phi: np.ndarray | None
                  ) -> tuple[tuple[float, np.ndarray], list[dict]]:
        """``n_restarts`` L-BFGS-B runs from ``x_init`` (then perturbed), and with ``g_start="both"`` one
        from unit lengthscales of g; the best (bound, theta) and the runs."""
        n = layout.n
        lo, hi = (np.array(b) for b in zip(*layout.bounds()))
        x_init = np.clip(x_init, lo, hi)
        runs: list[dict] = []
        best: tuple[float, np.ndarray] | None = None
        starts: list[int | str] = [*range(self.n_restarts), *(["g_unit"] if self.g_start == "both" else []),
                                   *(["g_resid"] if self.g_start == "residuals" else [])]
        if self.warm_start is not None:  # one run, from the warm start
            starts = [0]
        for k in starts:
            if k == 0:
                x0 = x_init
            elif k == "g_resid":  # g_start="residuals": one more run, g from the log squared residuals
                x0 = log_residual_start(x_init, Xs, ys, layout, Phi, rng)
            elif k == "g_unit":  # g_start="both": one more run from unit lengthscales of g
                x0 = x_init.copy()
                x0[layout.g_slice.start:layout.g_slice.start + layout.g.d] = 0.0
                x0 = np.clip(x0, lo, hi)
            else:
                x0 = x_init.copy()
                x0[:n] += 0.1 * rng.standard_normal(n)
                x0[n:] += 0.5 * rng.standard_normal(x0.size - n)
                x0 = np.clip(x0, lo, hi)
            if deadline is not None and time.perf_counter() >= deadline and best is not None:
                runs.append({"start": k, "status": "skipped", "reason": "time budget exhausted"})
                continue
            run = self._run(x0, Xs, ys, layout, deadline, max_iter, Phi)
            run["start"] = k
            run["se"] = not layout.se_off
            x_run = run.pop("x", None)
            runs.append(run)
            handicap = RESIDUAL_RUN_HANDICAP * bic_penalty(layout.g.d + 1, n) if k == "g_resid" else 0.0
            if run["status"] == "ok" and (best is None or run["bound"] - handicap > best[0]):
                best = (run["bound"], x_run)
        if best is None:
            reasons = "; ".join(f"run {r['start']}: {r.get('reason', r['status'])}" for r in runs)
            raise MicroctlError(f"VHGPR: every optimisation run failed ({reasons})")
        return best, runs

    def _linear_bounds(self, d: int) -> tuple[tuple[float, float], ...] | None:
        """Box bounds of f's [log bias var, log linear variances (d)]: free, fixed at the prior,
        or off (an input without a trend)."""
        if self.linear is False:
            return None
        on = set(range(d)) if self.linear is True else set(self.linear)
        free = BOUNDS["log_linear_var"]
        fixed = free if self.linear_prior_var is None else (math.log(self.linear_prior_var),) * 2
        off = (free[0], free[0])
        return (fixed,) + tuple(fixed if i in on else off for i in range(d))

    def _run(self, x0: np.ndarray, Xs: np.ndarray, ys: np.ndarray, layout: Layout, deadline: float | None,
             max_iter: int, Phi: np.ndarray | None = None) -> dict:
        """One L-BFGS-B run from ``x0``; returns a record (status, bound, iterations, x)."""
        t0 = time.perf_counter()
        n = layout.n
        best: list[Any] = [np.inf, None]  # lowest negative bound seen, and where
        counter = {"evals": 0, "failed_evals": 0}
        eval_times: list[float] = []

        class _OutOfTime(Exception):
            pass

        def fun(theta: np.ndarray) -> tuple[float, np.ndarray]:
            if deadline is not None and time.perf_counter() > deadline and best[1] is not None:
                raise _OutOfTime
            counter["evals"] += 1
            te = time.perf_counter()
            try:
                with np.errstate(all="ignore"):
                    F, g, st = mv_bound(theta, Xs, ys, layout, want_state=False, Phi=Phi)
            except np.linalg.LinAlgError:
                F, g = np.nan, None
            if not np.isfinite(F) or g is None or not np.all(np.isfinite(g)):
                # A numerically impossible point: report a huge value so the line search backs off.
                counter["failed_evals"] += 1
                return 1e25, np.zeros_like(theta)
            eval_times.append(time.perf_counter() - te)
            if -F < best[0]:
                best[0], best[1] = -F, theta.copy()
            # Minimise -F/n: per-point scaling keeps L-BFGS-B's first (unit, projected) step
            # small whatever n is, and makes ``tol`` mean the same for every n.
            return -F / n, -g / n

        record: dict[str, Any] = {}
        try:
            res = minimize(fun, x0, jac=True, method="L-BFGS-B", bounds=layout.bounds(),
                           options={"maxiter": max_iter, "maxfun": int(1.25 * max_iter) + 10,
                                    "ftol": self.tol, "gtol": 1e-6})
            record.update(iterations=int(res.nit), message=str(res.message), converged=bool(res.success))
        except _OutOfTime:
            record.update(iterations=None, message="stopped: time budget reached", converged=False)
        record.update(evaluations=counter["evals"], failed_evaluations=counter["failed_evals"],
                      time_s=time.perf_counter() - t0,
                      eval_time_median_s=float(np.median(eval_times)) if eval_times else None,
                      eval_time_max_s=float(np.max(eval_times)) if eval_times else None)
        if best[1] is None:
            record.update(status="failed", reason="no finite bound at any evaluated point")
            return record
        # Re-evaluate the winner without error suppression, to make sure it is sound.
        try:
            F, _, _ = mv_bound(best[1], Xs, ys, layout, want_grad=False, Phi=Phi)
        except np.linalg.LinAlgError as exc:
            record.update(status="failed", reason=f"final point not positive definite: {exc}")
            return record
        if not np.isfinite(F):
            record.update(status="failed", reason="non-finite bound at the final point")
            return record
        if record["iterations"] is None:
            record["iterations"] = counter["evals"]
        record.update(status="ok", bound=float(F), x=best[1])
        return record

