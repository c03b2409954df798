"""Noise models of the VHGPR: how g's prior mean is built from the noise features, by name.

A noise model is one class (a subclass of :class:`NoiseModel` decorated with
:func:`register_noise_model`) that knows

- its ``name`` (what ``microctl train --noise-model`` and the model file say);
- whether it uses noise features (:class:`~microctl.gp.noise_prior.NoiseFeatures`, the
  linear maps ``z_j = a_j . x + b_j``) and how it turns them into the features ``phi_j =
  transform(z_j)`` of g's prior mean ``m(x) = log(c_0 + sum_j c_j phi_j(x))``
  (:mod:`microctl.gp.noise_prior` eq. 1), for the trainer (:meth:`NoiseModel.design`) and for
  prediction (:meth:`NoiseModel.prior_mean`, NumPy and CasADi);
- which model-file arrays it stores (:attr:`NoiseModel.stored_arrays`); the model file
  (:mod:`microctl.gp.modelfile`) stores its name explicitly.

Three are registered here: ``dictionary`` (each feature its own smooth shape of its linear
quantity, :mod:`microctl.gp.shaped_features`: the sources a selection chose from the stage's
dictionary, :mod:`microctl.models.noise_dictionary`), ``physical`` (``phi = z^2``: a floor plus per-actuator stick-slip
whose standard deviation grows with the step, the default of :mod:`microctl.models.training`)
and ``hgp`` (the paper's constant prior mean ``mu0``, no features).
"""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np

from microctl.gp.noise_prior import LogVarianceMean, NoiseFeatures, square
from microctl.gp.shaped_features import ShapeTransform

__all__ = ["FEATURE_ARRAYS", "NoiseModel", "PhysicalNoise", "ConstantNoise", "register_noise_model",
           "noise_model_class", "noise_model_names"]

#: The feature arrays of a model file (fields of :class:`~microctl.gp.fitted.FittedVHGPR`).
FEATURE_ARRAYS = ("g_feature_matrix", "g_feature_offset", "g_log_feature_coef")

_REGISTRY: dict[str, type["NoiseModel"]] = {}


class NoiseModel:
    """Base class of the noise models (see the module docstring).

    A subclass with features sets ``name`` and overrides :meth:`transform`; one without
    features sets ``uses_features = False`` and ``stored_arrays = ()``.
    """

    #: Name in settings, on the command line and in the model file.
    name: ClassVar[str] = ""
    #: Whether g's prior mean has features (then the trainer needs ``noise_features``).
    uses_features: ClassVar[bool] = True
    #: Model-file arrays of g's prior mean this model stores (all of them present together).
    stored_arrays: ClassVar[tuple[str, ...]] = FEATURE_ARRAYS
    #: Whether a fitted model may also hold none of them (a constant prior mean).
    features_optional: ClassVar[bool] = False

    @staticmethod
    def transform(z: Any) -> Any:
        """``phi = transform(z)`` elementwise, for a NumPy array or a CasADi expression."""
        raise NotImplementedError

    def for_features(self, features: NoiseFeatures, y_scale: float) -> "NoiseModel":
        """This model for training with ``features`` on outputs of scale ``y_scale`` (the
        models whose transform depends on the features return a bound copy; default itself)."""
        return self

    def design(self, Xs: np.ndarray, As: np.ndarray, bs: np.ndarray,
               gate: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
        """The features ``phi`` at the standardised training inputs, shape (n, p).

        Parameters
        ----------
        Xs : ndarray, shape (n, d)
        As, bs : ndarray, shapes (p, d) and (p,)
            The standardised linear maps (:meth:`~microctl.gp.noise_prior.NoiseFeatures.standardised`).
        gate : (ndarray, ndarray), optional
            The standardised gates (G_s (p, d), h_s (p,),
            :meth:`~microctl.gp.noise_prior.NoiseFeatures.standardised_gate`) of gated features.
        """
        lin = Xs @ As.T + bs
        return self.transform(lin) if gate is None else self.transform(lin, Xs @ gate[0].T + gate[1])

    def prior_mean(self, model: Any) -> LogVarianceMean:
        """g's prior mean from the fields of a fitted model (a :class:`~microctl.gp.fitted.FittedVHGPR`)."""
        return LogVarianceMean(model.g_feature_matrix, model.g_feature_offset, model.g_mu0, model.g_log_feature_coef,
                               model.g_mean_coef_cov, transform=self.transform)


def register_noise_model(cls: type[NoiseModel]) -> type[NoiseModel]:
    """Class decorator: make ``cls`` available by its ``name`` (a name can be registered once)."""
    if not cls.name:
        raise ValueError(f"noise model {cls.__name__} has no name")
    if _REGISTRY.get(cls.name, cls) is not cls:
        raise ValueError(f"noise model name {cls.name!r} is already registered ({_REGISTRY[cls.name].__name__})")
    _REGISTRY[cls.name] = cls
    return cls


def noise_model_class(name: str) -> type[NoiseModel]:
    """The registered noise model called ``name``; KeyError (with the known names) otherwise."""
    try:
        return _REGISTRY[name]
    except KeyError:
        raise KeyError(f"unknown noise model {name!r}; known: {', '.join(noise_model_names())}") from None


def noise_model_names() -> tuple[str, ...]:
    """Names of the registered noise models, in registration order."""
    return tuple(_REGISTRY)


@register_noise_model
class PhysicalNoise(NoiseModel):
    """``m(x) = log(c_0 + sum_j c_j z_j^2)``: a floor plus stick-slip (``noise_prior`` eq. 1)."""

    name = "physical"
    transform = staticmethod(square)


@register_noise_model
class ConstantNoise(NoiseModel):
    """The paper's ``g ~ GP(mu0, K_g)``: a constant prior mean, no features."""

    name = "hgp"
    uses_features = False
    stored_arrays = ()

    def design(self, Xs: np.ndarray, As: np.ndarray, bs: np.ndarray,
               gate: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
        raise ValueError("the constant noise model has no features")

    def prior_mean(self, model: Any) -> LogVarianceMean:
        d = int(model.X.shape[1])
        return LogVarianceMean(np.zeros((0, d)), np.zeros(0), model.g_mu0, np.zeros(0), model.g_mean_coef_cov)


@register_noise_model
class DictionaryNoise(NoiseModel):
    """``m(x) = log(c_0 + sum_j c_j shape_j(a_j . x + b_j))``: each selected source its own shape
    (``sq``, ``abs``, ``sat``, ``up``, ``down``, ``bump``, ``exp``; :mod:`microctl.gp.shaped_features`)."""

    name = "dictionary"
    #: A selection that found no source leaves the constant prior mean (no feature arrays).
    features_optional: ClassVar[bool] = True

    def __init__(self, transform: ShapeTransform | None = None):
        self._transform = transform

    def for_features(self, features: NoiseFeatures, y_scale: float) -> "DictionaryNoise":
        if not features.shapes:
            raise ValueError("the dictionary noise model needs shaped features (NoiseFeatures.shapes)")
        return DictionaryNoise(ShapeTransform(features.shapes, features.params, y_scale))

    def transform(self, z: Any, gate: Any = None) -> Any:  # type: ignore[override]
        if self._transform is None:
            raise ValueError("the dictionary noise model is not bound to its features (for_features)")
        return self._transform(z, gate)

    def prior_mean(self, model: Any) -> LogVarianceMean:
        p = 0 if model.g_feature_matrix is None else int(np.asarray(model.g_feature_matrix).shape[0])
        if p == 0:  # no source selected: the paper's constant prior mean
            d = int(model.X.shape[1])
            return LogVarianceMean(np.zeros((0, d)), np.zeros(0), model.g_mu0, np.zeros(0), model.g_mean_coef_cov)
        if len(model.g_feature_shapes) != p or len(model.g_feature_params) != p:
            raise ValueError(f"dictionary noise model: {len(model.g_feature_shapes)} shapes and "
                             f"{len(model.g_feature_params)} parameter pairs for {p} features")
        tr = ShapeTransform(model.g_feature_shapes, model.g_feature_params, model.y_scale)
        return LogVarianceMean(model.g_feature_matrix, model.g_feature_offset, model.g_mu0, model.g_log_feature_coef,
                               model.g_mean_coef_cov, transform=tr, gate_matrix=model.g_feature_gate,
                               gate_offset=model.g_feature_gate_offset)
