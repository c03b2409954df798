"""Variational heteroscedastic Gaussian process regression (VHGPR): the public front.

The model and the marginalised variational ("MV") bound of Lázaro-Gredilla & Titsias
(ICML 2011), written from the equations in ``notes/vhgpr.md``:

    y_i = f(x_i) + e_i,   e_i ~ N(0, exp(g(x_i))),   f ~ GP(0, K_f),   g ~ GP(mu0, K_g)

The implementation is split by concept, and this module re-exports its public names:

- :mod:`microctl.gp.kernels` (covariance functions, :func:`ard_se`),
- :mod:`microctl.gp.linalg` (Cholesky factors and inverses),
- :mod:`microctl.gp.bound` (the bound and its gradient), :mod:`microctl.gp.homoscedastic`
  (the initialisation), :mod:`microctl.gp.trainer` (:class:`VHGPR` and its fit),
- :mod:`microctl.gp.noise_prior` and :mod:`microctl.gp.noise_models` (g's prior mean, by name),
- :mod:`microctl.gp.posterior` (the posterior of f and g, NumPy and CasADi),
- :mod:`microctl.gp.fitted` (:class:`FittedVHGPR`, :class:`VHGPRPrediction`) and
  :mod:`microctl.gp.modelfile` (its ``.npz`` file).
"""

from __future__ import annotations

from microctl.gp.fitted import FittedVHGPR, VHGPRPrediction
from microctl.gp.kernels import ard_se
from microctl.gp.modelfile import FORMAT_VERSION
from microctl.gp.posterior import G_GP_VAR_NEGLIGIBLE
from microctl.gp.trainer import VHGPR

__all__ = ["FORMAT_VERSION", "G_GP_VAR_NEGLIGIBLE", "VHGPR", "FittedVHGPR", "VHGPRPrediction", "ard_se"]
