"""The variational heteroscedastic GP (VHGPR): kernels, the noise model of g, the bound and
its trainer, the fitted posterior and its model file. Knows nothing of stages.
"""
