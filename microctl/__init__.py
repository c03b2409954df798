"""microctl: accurate and repeatable position control of piezo micromanipulators.

The package implements the Enhanced Analytic Forward Model (EAFM) of Su et al.:
a contact-model analytic forward model (AFM) of a flexure platform corrected by a
variational heteroscedastic Gaussian process (VHGPR), and an optimal controller that
reaches a target tool pose with the smallest predicted noise variance.

The public Python API is :mod:`microctl.api` (``from microctl import api``; docs/api.md): load a
stage, train, build a controller, solve, move a stage with a measurement log. It is not imported
here, so ``import microctl`` (and ``microctl --version``) stays cheap.
"""

from microctl._version import __version__
from microctl.errors import (
    BackendError,
    ConfigError,
    DataError,
    MicroctlError,
    SolveError,
    UnreachableTargetError,
)


__all__ = [
    "BackendError",
    "ConfigError",
    "DataError",
    "MicroctlError",
    "SolveError",
    "UnreachableTargetError",
    "__version__",
]
