"""The variational heteroscedastic GP (VHGPR). Knows nothing of stages.

One module per concept: :mod:`~microctl.gp.kernels` (covariance functions),
:mod:`~microctl.gp.linalg` (Cholesky factors), :mod:`~microctl.gp.arrays` (input checks),
:mod:`~microctl.gp.noise_prior` and :mod:`~microctl.gp.noise_models` (g's prior mean and the
registry of noise models), :mod:`~microctl.gp.bound` (the MV bound and its gradient),
:mod:`~microctl.gp.homoscedastic` (the initialisation), :mod:`~microctl.gp.trainer` (the fit),
:mod:`~microctl.gp.posterior` (the posterior, NumPy and CasADi), :mod:`~microctl.gp.fitted`
(the fitted model) and :mod:`~microctl.gp.modelfile` (its file); :mod:`~microctl.gp.vhgpr` is
the public front that re-exports the names other packages use.
"""
