"""The fitted VHGPR: its stored quantities, prediction and model file.

:class:`FittedVHGPR` holds everything a prediction needs and nothing else (see
``docs/vhgpr.md``), in standardised units except where a field says otherwise; its
posterior (``notes/vhgpr.md`` [N prediction]) is :class:`~microctl.gp.posterior.Posterior`,
its file format :mod:`microctl.gp.modelfile`, its noise model
:mod:`microctl.gp.noise_models`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields, replace
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np

from microctl.errors import DataError
from microctl.gp.arrays import as_float_array, check_finite
from microctl.gp.kernels import Kernel
from microctl.gp.linalg import LOG_2PI
from microctl.gp.modelfile import read_model, write_model
from microctl.gp.noise_models import noise_model_class
from microctl.gp.noise_prior import LogVarianceMean
from microctl.gp.posterior import Posterior
from microctl.gp.shaped_features import ShapedFeatures
from microctl.gp.trend import FeatureTrend

__all__ = ["VHGPRPrediction", "FittedVHGPR"]


@dataclass(frozen=True, eq=False)
class VHGPRPrediction:
    """Predictive distribution at m test inputs, in the ORIGINAL units of y.

    Attributes
    ----------
    f_mean : ndarray, shape (m,)
        ``y_mean + y_scale * a*``.
    f_var : ndarray, shape (m,)
        ``y_scale**2 * c*^2`` (epistemic variance of f).
    g_mean : ndarray, shape (m,)
        Mean of the log noise variance: ``mu* + 2 log(y_scale)``.
    g_var : ndarray, shape (m,)
        ``s*^2``, variance of the log noise variance.
    y_mean : ndarray, shape (m,)
        Equal to ``f_mean``.
    y_var : ndarray, shape (m,)
        ``f_var + exp(g_mean + g_var / 2)``.
    """

    f_mean: np.ndarray
    f_var: np.ndarray
    g_mean: np.ndarray
    g_var: np.ndarray
    y_mean: np.ndarray
    y_var: np.ndarray


def _stored(role: str, *, shape: tuple[str, ...] | None = None, log: bool = False, **kw: Any) -> Any:
    """A dataclass field with its storage role in the model file (see :meth:`FittedVHGPR.stored`),
    its shape in the dimensions ``n`` (training points), ``d`` (inputs), ``k`` (the inputs the
    kernels read: the first k of d), ``kg`` (g's lengthscales: k, or the rows of g's input
    map), ``p`` and ``p+1`` (noise features) and whether it is a log-parameter (both checked at load)."""
    return field(metadata={"store": role, "shape": shape, "log": log}, **kw)


@dataclass(frozen=True, eq=False)
class FittedVHGPR:
    """A fitted VHGPR: everything a prediction needs (standardised units unless stated).

    Attributes
    ----------
    x_mean, x_scale : ndarray, shape (d,)
        Input standardisation ``xs = (x - x_mean) / x_scale``.
    y_mean, y_scale : float
        Output standardisation ``ys = (y - y_mean) / y_scale``.
    X : ndarray, shape (n, d)
        Standardised training inputs.
    f_log_lengthscales, f_log_signal_var, f_log_bias_var
        Kernel of f (see :func:`ard_se`); the bias is None when not used. The lengthscales have
        shape (k,), k <= d: the kernels read the first k inputs, the columns beyond only g's
        prior mean (a move's context, :attr:`n_context`).
    g_log_lengthscales, g_log_signal_var, g_log_bias_var
        Kernel of g; the lengthscales have shape (kg,): k, or the rows of ``g_input_map``.
    g_mu0 : float
        Prior mean of g (standardised units).
    log_lambda : ndarray, shape (n,)
        Variational parameters log Lambda.
    f_alpha : ndarray, shape (n,)
        ``(K_f + R)^-1 ys``.
    f_chol : ndarray, shape (n, n)
        Lower Cholesky factor of ``K_f + R``.
    g_beta : ndarray, shape (n,)
        ``(Lambda - I/2) 1``.
    g_chol : ndarray, shape (n, n)
        Lower Cholesky factor of ``K_g + Lambda^-1``.
    bound : float
        The MV bound at the optimum (standardised data).
    training_hash : str
        sha256 hex of the original X and y as float64 bytes.
    geometry_hash : str or None
        Set by callers (``dataclasses.replace``) for residual models.
    x_names : tuple of str
        Input column names, if known.
    y_name : str
        Output column name, if known.
    info : dict
        Fit diagnostics: jitter, restarts tried/failed, iterations, time.
    f_log_linear_vars : ndarray, shape (d,), or None
        ARD linear part of f's kernel (:mod:`microctl.gp.kernels`); None when not used.
    g_feature_matrix, g_feature_offset : ndarray, shapes (p, d) and (p,), or None
        Features of g's parametric prior mean (:mod:`microctl.gp.noise_prior` eq. 1) in
        standardised units; None: the constant prior mean ``g_mu0``.
    g_log_feature_coef : ndarray, shape (p,), or None
        log c_j of that mean (``g_mu0`` is log c_0).
    g_mean_coef_cov : ndarray, shape (p + 1, p + 1), or None
        Laplace covariance of (c_0, .., c_p), propagated into g's posterior variance.
    g_feature_names : tuple of str
        Names of the features (``dq1``, ...).
    g_feature_shapes, g_feature_params : tuple
        The shape of each feature and its two parameters (``dictionary`` noise model,
        :mod:`microctl.gp.shaped_features`); empty for the others.
    noise_model_name : str or None
        The noise model (:mod:`microctl.gp.noise_models`) that built g's prior mean; None (a
        model built in memory, or a file of format 1 or 2 written before the name was stored):
        ``"physical"`` when there are features, else ``"hgp"``.
    g_feature_gate, g_feature_gate_offset : ndarray, shapes (p, d) and (p,), or None
        The gates of gated features (``rev``, :mod:`microctl.gp.shaped_features`) in
        standardised inputs, ``c = G . xs + h`` in the gate's own units; None: no gated feature.
    f_trend_matrix, f_trend_offset, f_trend_params, f_trend_scale : ndarray, or None
        f's feature trend (:mod:`microctl.gp.trend`) on the standardised inputs the kernels
        read, shapes (t, k), (t,), (t, 2), (t,); None: no trend.
    f_trend_log_var : float or None
        log of the trend coefficients' prior variance.
    f_trend_names, f_trend_shapes : tuple of str
        The trend features' names (the noise sources they come from) and shapes.
    g_input_map : ndarray, shape (kg, k), or None
        g's kernel reads ``M xs[:k]`` (standardised inputs), not ``xs[:k]``
        (:mod:`microctl.gp.kernels`: the actuators' positions and steps,
        :func:`microctl.models.noise_inputs.actuator_inputs`); None: the raw inputs.
    g_input_names : tuple of str
        Names of the rows of ``g_input_map`` (``q1``, ``dq1``, ...); empty without one.
    posterior_form : {"exact", "sparse"}
        ``"exact"``: the fields above as a VHGPR fit writes them. ``"sparse"``
        (:mod:`microctl.gp.sparse`): ``X`` holds the M inducing inputs, ``f_chol``/``g_chol``
        the factors of ``K(Z, Z) + R`` with R the full pseudo-noise covariance of the sparse
        posterior (same prediction formulas), ``log_lambda`` zeros (unused).

    Every field is declared once with its storage role (:meth:`stored`); the model file
    (:mod:`microctl.gp.modelfile`) derives its arrays from them.
    """

    x_mean: np.ndarray = _stored("array", shape=("d",))
    x_scale: np.ndarray = _stored("array", shape=("d",))
    y_mean: float = _stored("float")
    y_scale: float = _stored("float")
    X: np.ndarray = _stored("array")
    f_log_lengthscales: np.ndarray = _stored("array", shape=("k",), log=True)
    f_log_signal_var: float = _stored("float", log=True)
    f_log_bias_var: float | None = _stored("optional_float", log=True)
    g_log_lengthscales: np.ndarray = _stored("array", shape=("kg",), log=True)
    g_log_signal_var: float = _stored("float", log=True)
    g_log_bias_var: float | None = _stored("optional_float", log=True)
    g_mu0: float = _stored("float", log=True)
    log_lambda: np.ndarray = _stored("array", shape=("n",), log=True)
    f_alpha: np.ndarray = _stored("array", shape=("n",))
    f_chol: np.ndarray = _stored("array", shape=("n", "n"))
    g_beta: np.ndarray = _stored("array", shape=("n",))
    g_chol: np.ndarray = _stored("array", shape=("n", "n"))
    bound: float = _stored("float")
    training_hash: str = _stored("meta")
    geometry_hash: str | None = _stored("meta", default=None)
    x_names: tuple[str, ...] = _stored("meta", default=())
    y_name: str = _stored("meta", default="")
    info: dict = _stored("meta", default_factory=dict)
    f_log_linear_vars: np.ndarray | None = _stored("optional_array", shape=("k",), log=True, default=None)
    g_feature_matrix: np.ndarray | None = _stored("optional_array", shape=("p", "d"), default=None)
    g_feature_offset: np.ndarray | None = _stored("optional_array", shape=("p",), default=None)
    g_log_feature_coef: np.ndarray | None = _stored("optional_array", shape=("p",), log=True, default=None)
    g_mean_coef_cov: np.ndarray | None = _stored("optional_array", shape=("p+1", "p+1"), default=None)
    g_feature_names: tuple[str, ...] = _stored("meta", default=())
    noise_model_name: str | None = _stored("meta", default=None)
    g_feature_shapes: tuple[str, ...] = _stored("meta", default=())
    g_feature_params: tuple = _stored("meta", default=())
    posterior_form: str = _stored("meta", default="exact")
    g_feature_gate: np.ndarray | None = _stored("optional_array", shape=("p", "d"), default=None)
    g_feature_gate_offset: np.ndarray | None = _stored("optional_array", shape=("p",), default=None)
    f_trend_matrix: np.ndarray | None = _stored("optional_array", shape=("t", "k"), default=None)
    f_trend_offset: np.ndarray | None = _stored("optional_array", shape=("t",), default=None)
    f_trend_params: np.ndarray | None = _stored("optional_array", shape=("t", "2"), default=None)
    f_trend_scale: np.ndarray | None = _stored("optional_array", shape=("t",), default=None)
    f_trend_log_var: float | None = _stored("optional_float", log=True, default=None)
    f_trend_names: tuple[str, ...] = _stored("meta", default=())
    f_trend_shapes: tuple[str, ...] = _stored("meta", default=())
    g_input_map: np.ndarray | None = _stored("optional_array", shape=("kg", "k"), default=None)
    g_input_names: tuple[str, ...] = _stored("meta", default=())

    @classmethod
    def stored(cls, role: str) -> tuple[str, ...]:
        """Names of the fields with storage role ``role`` (``array``, ``float``, ``optional_float``,
        ``optional_array``, ``meta``), in declaration order: the model file's layout."""
        return tuple(f.name for f in fields(cls) if f.metadata.get("store") == role)

    @classmethod
    def shapes(cls) -> dict[str, tuple[str, ...]]:
        """The stored arrays' shapes in the dimensions ``n``, ``d``, ``p``, ``p+1`` (see :func:`_stored`)."""
        return {f.name: f.metadata["shape"] for f in fields(cls) if f.metadata.get("shape") is not None}

    @classmethod
    def log_parameters(cls) -> tuple[str, ...]:
        """The fields holding log-parameters (log variances, log lengthscales, mu0, log Lambda)."""
        return tuple(f.name for f in fields(cls) if f.metadata.get("log"))

    @property
    def n_inputs(self) -> int:
        """Number of input dimensions d."""
        return int(self.X.shape[1])

    @property
    def n_context(self) -> int:
        """Trailing input columns only g's prior mean reads (d - k; 0 for most models)."""
        return int(self.X.shape[1]) - int(np.size(self.f_log_lengthscales))

    @property
    def f_kernel(self) -> Kernel:
        """The kernel of f (:class:`~microctl.gp.kernels.Kernel`)."""
        return Kernel(self.f_log_lengthscales, self.f_log_signal_var, self.f_log_bias_var, self.f_log_linear_vars,
                      trend=self.f_trend)

    @property
    def f_trend(self) -> FeatureTrend | None:
        """f's feature trend (:mod:`microctl.gp.trend`), or None."""
        if self.f_trend_matrix is None:
            return None
        features = ShapedFeatures(self.f_trend_matrix, self.f_trend_offset, tuple(self.f_trend_shapes),
                                  self.f_trend_params, self.f_trend_scale, tuple(self.f_trend_names))
        return FeatureTrend(features, float(self.f_trend_log_var))

    @property
    def g_kernel(self) -> Kernel:
        """The kernel of g."""
        return Kernel(self.g_log_lengthscales, self.g_log_signal_var, self.g_log_bias_var, input_map=self.g_input_map)

    @property
    def g_prior_mean(self) -> LogVarianceMean:
        """The prior mean of g, as its noise model builds it (constant ``g_mu0``, or
        :mod:`microctl.gp.noise_prior` eq. 1)."""
        return noise_model_class(self.noise_model)().prior_mean(self)

    @property
    def g_prior_mean_with_uncertainty(self) -> LogVarianceMean:
        """g's prior mean carrying its parameters' covariance whether or not the model propagates
        it into g's variance (from ``info["noise_parameters"]``): for questions of evidence (is a
        pose credibly quieter, where is the noise model least certain), not for the objective."""
        gm = self.g_prior_mean
        params = self.info.get("noise_parameters") or {}
        if gm.coef_cov is not None or self.g_feature_matrix is None or "c_cov" not in params:
            return gm
        return replace(gm, coef_cov=np.asarray(params["c_cov"], dtype=float))

    @property
    def g_gp_var_negligible(self) -> bool:
        """g's GP part has prior variance <= :data:`~microctl.gp.posterior.G_GP_VAR_NEGLIGIBLE`
        (its variance is then that bound)."""
        return self.posterior.g_gp_var_negligible

    @property
    def noise_model(self) -> str:
        """Name of the noise model (:mod:`microctl.gp.noise_models`): ``noise_model_name``, or for
        a model without one ``"physical"`` when g has a parametric prior mean, else ``"hgp"``."""
        if self.noise_model_name is not None:
            return self.noise_model_name
        return "physical" if self.g_feature_matrix is not None else "hgp"

    @cached_property
    def posterior(self) -> Posterior:
        """The posterior of f and g (:class:`~microctl.gp.posterior.Posterior`), built once."""
        return Posterior(self)

    def check_inputs(self, X: Any, name: str = "X") -> np.ndarray:
        """``X`` as a float array of shape (m, d) with this model's d, finite; DataError naming ``name``."""
        X = as_float_array(X, name)
        d = self.n_inputs
        if X.ndim == 1 and d == 1:
            X = X[:, None]
        if X.ndim != 2 or X.shape[1] != d:
            raise DataError(f"{name} has shape {X.shape}; this model expects shape (m, {d})")
        check_finite(X, name)
        return X

    def predict(self, X: Any) -> VHGPRPrediction:
        """Predictive distribution at the rows of ``X`` ([N prediction], :class:`Posterior`).

        Parameters
        ----------
        X : array_like, shape (m, d), original units

        Returns
        -------
        VHGPRPrediction
            All fields of shape (m,), in original units of y.
        """
        X = self.check_inputs(X)
        xs = (X - self.x_mean) / self.x_scale
        a, c2, mu, s2 = self.posterior.predict_std(xs)
        np.maximum(c2, 0.0, out=c2)
        np.maximum(s2, 0.0, out=s2)
        f_mean = self.y_mean + self.y_scale * a
        f_var = self.y_scale**2 * c2
        g_mean = mu + 2.0 * math.log(self.y_scale)
        g_var = s2
        y_var = f_var + np.exp(g_mean + 0.5 * g_var)
        return VHGPRPrediction(f_mean=f_mean, f_var=f_var, g_mean=g_mean, g_var=g_var,
                               y_mean=f_mean.copy(), y_var=y_var)

    def nlpd(self, X: Any, y: Any) -> float:
        """Mean negative log predictive density (nats) under the Gaussian N(y_mean, y_var).

        Parameters
        ----------
        X : array_like, shape (m, d)
        y : array_like, shape (m,)
        """
        X = self.check_inputs(X)
        y = as_float_array(y, "y")
        if y.ndim != 1 or y.shape[0] != X.shape[0]:
            raise DataError(f"y has shape {y.shape}; expected ({X.shape[0]},) to match X")
        check_finite(y, "y")
        p = self.predict(X)
        return float(np.mean(0.5 * (LOG_2PI + np.log(p.y_var)) + 0.5 * (y - p.y_mean) ** 2 / p.y_var))

    # ----------------------------------------------------------------------- persistence

    def save(self, path: str | Path) -> None:
        """Write the model to a ``.npz`` file (:func:`microctl.gp.modelfile.write_model`).

        Raises
        ------
        DataError
            If the file cannot be written.
        """
        write_model(self, path)

    @classmethod
    def load(cls, path: str | Path) -> "FittedVHGPR":
        """Read a model written by :meth:`save` (:func:`microctl.gp.modelfile.read_model`).

        Raises
        ------
        DataError
            Naming the file: unreadable, not an ``.npz``, unknown format version, missing or
            malformed arrays, numbers no fit can produce.
        """
        return read_model(cls, path)
