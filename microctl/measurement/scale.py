"""Readings on the wrong scale: a log whose gauge readings are not in µm (e.g. mm)."""

from __future__ import annotations

import numpy as np

from microctl.errors import DataError
from microctl.measurement.log import MeasurementLog
from microctl.models.afm import AnalyticForwardModel

__all__ = ["READING_SCALE_FLOOR", "READING_SCALE_CEILING", "check_reading_scale", "check_spread"]


#: ``check_reading_scale`` refuses readings whose spread is below this fraction of the AFM's.
READING_SCALE_FLOOR = 0.02


#: ... and readings whose spread exceeds this multiple of the AFM's.
READING_SCALE_CEILING = 5.0


def check_reading_scale(log: MeasurementLog, afm: AnalyticForwardModel, *, min_spread_um: float = 1.0) -> None:
    """Refuse a log whose gauge readings are on another scale than µm (e.g. mm, nm).

    The AFM predicts t from the logged control signals; where it predicts a spread of at least
    ``min_spread_um`` but the readings spread less than :data:`READING_SCALE_FLOOR` of it or
    more than :data:`READING_SCALE_CEILING` times it, the readings are in another unit (mm:
    1000 times smaller) or come from another stage, or the gauge did not follow the tool.

    Raises
    ------
    DataError
        Naming the file, both spreads and the likely cause.
    """
    check_spread(log.path, log.t, log.u, afm, min_spread_um=min_spread_um)


def check_spread(path, t: np.ndarray, u: np.ndarray, afm: AnalyticForwardModel, *, min_spread_um: float = 1.0) -> None:
    """:func:`check_reading_scale` on arrays: readings ``t`` (µm) after control signals ``u``."""
    if len(t) < 3:
        return
    predicted = float(np.std(afm.t_of(u)))
    measured = float(np.std(t))
    if predicted < min_spread_um:
        return
    if measured < READING_SCALE_FLOOR * predicted:
        raise DataError(
            f"{path}: column '{afm.stage.tool.name}': the readings spread {measured:.3g} µm (std) while the AFM "
            f"predicts {predicted:.3g} µm for these moves: are they in mm? readings must be in µm "
            f"(docs/measurement-log.md), or the gauge did not follow the tool")
    if measured > READING_SCALE_CEILING * predicted:
        raise DataError(
            f"{path}: column '{afm.stage.tool.name}': the readings spread {measured:.3g} µm (std) while the AFM "
            f"predicts {predicted:.3g} µm for these moves: are they in another unit (nm?) or from another stage? "
            "readings must be in µm (docs/measurement-log.md)")
