"""The serial rig the serial-backend tests run against: sim_paper.yaml's stage with two GCS
controllers (q1-q3 on driver1, q4 on driver2) and a gauge, at placeholder URLs that
:meth:`microctl.backends.emulator.Emulator.pointed_at` replaces with the started emulator's."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

from microctl.stage.config import (
    AxisMap,
    Gauge,
    SerialBackend,
    SerialController,
    StageConfig,
    load_stage_config,
)

ROOT = Path(__file__).resolve().parents[1]
TIMEOUT_S = 0.3  # short read timeouts: every reply is local
START_Q = (19.0, 4.4, 16.3, 31.0)  # where issue 12 found the rig before a second collect


def serial_config(**gauge) -> StageConfig:
    """sim_paper.yaml with the serial backend above; ``gauge`` overrides :class:`Gauge` fields."""
    c = load_stage_config(ROOT / "configs/stage/sim_paper.yaml")
    ser = SerialBackend(
        controllers=(
            SerialController("driver1", "socket://127.0.0.1:1", timeout_s=TIMEOUT_S),
            SerialController("driver2", "socket://127.0.0.1:1", timeout_s=TIMEOUT_S),
        ),
        axes=(
            ("q1", AxisMap("driver1", "1")),
            ("q2", AxisMap("driver1", "2")),
            ("q3", AxisMap("driver1", "3")),
            ("q4", AxisMap("driver2", "A")),
        ),
        gauge=Gauge(url="socket://127.0.0.1:1", timeout_s=TIMEOUT_S, **gauge),
        on_target_timeout_s=1.0,
        poll_interval_s=0.001,
        retries=1,
    )
    return replace(c, backend=replace(c.backend, serial=ser))
