"""Stage backends: the simulated stage and serial hardware, behind one interface.

The backends form a registry by kind (:data:`BACKENDS`: ``backend.kind`` of the stage config ->
:class:`~microctl.backends.base.StageBackend` subclass); a backend class joins it with
:func:`~microctl.backends.base.register_backend`. Use :func:`make_backend` to get the backend a
stage config names.
"""

from __future__ import annotations

from microctl.backends.base import BACKENDS, Measurement, StageBackend, make_backend, register_backend
from microctl.backends.simulated import SimulatedStage  # noqa: F401  (registers "simulated")
from microctl.backends.serial import SerialStage  # noqa: F401  (registers "serial")  # isort: skip

__all__ = ["BACKENDS", "Measurement", "StageBackend", "make_backend", "register_backend"]
