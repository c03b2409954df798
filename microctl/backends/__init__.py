"""Stage backends: the simulated stage and serial hardware, behind one interface.

Use :func:`make_backend` to get the backend a stage config names (``backend.kind``).
"""

from __future__ import annotations

from microctl.backends.base import Measurement, StageBackend
from microctl.errors import ConfigError
from microctl.stage.config import StageConfig


def make_backend(config: StageConfig, **kwargs) -> StageBackend:
    """The backend ``config.backend.kind`` names, opened and ready to move.

    Parameters
    ----------
    config : StageConfig
    **kwargs
        Passed to the backend's constructor (e.g. ``seed`` for the simulated stage).

    Returns
    -------
    StageBackend
    """
    kind = config.backend.kind
    if kind == "simulated":
        from microctl.backends.simulated import SimulatedStage

        return SimulatedStage(config, **kwargs)
    if kind == "serial":
        from microctl.backends.serial import SerialStage

        return SerialStage(config, **kwargs)
    raise ConfigError(f"{config.source}: backend.kind: '{kind}' is not a backend; valid: simulated, serial")


__all__ = ["Measurement", "StageBackend", "make_backend"]
