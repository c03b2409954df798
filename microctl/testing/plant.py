"""Simulated measurement runs with a planted effect (tests, the confusion script, docs).

A run is the simulated stage (:class:`~microctl.backends.simulated.SimulatedStage`) with its
effects replaced by the planted ones, driven through space-filling moves
(:func:`microctl.backends.collect.space_filling_moves`), exactly as ``microctl collect`` would.
:func:`random_cause` draws one vocabulary cause with a realistic magnitude.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Callable

import numpy as np

from microctl.backends.collect import space_filling_moves
from microctl.backends.simulated import SimulatedStage
from microctl.diagnosis.data import DiagnosisData, data_from_arrays
from microctl.measurement.log import MeasurementLogWriter
from microctl.models.afm import AnalyticForwardModel
from microctl.stage.causes import REGISTRY, Effects, preload_compression_um
from microctl.stage.config import StageConfig

#: Planted causes of :func:`random_cause`: the registry, in vocabulary order.
PLANTABLE = tuple(REGISTRY)


def with_effects(config: StageConfig, effects: Effects, seed: int | None = None) -> StageConfig:
    """``config`` whose simulated stage has exactly ``effects`` (and optionally another seed)."""
    sim = replace(config.backend.simulated, effects=effects)
    if seed is not None:
        sim = replace(sim, seed=int(seed))
    return replace(config, backend=replace(config.backend, simulated=sim))


def simulate(
    config: StageConfig,
    effects: Effects,
    n: int,
    seed: int,
    *,
    extra: Callable[[np.ndarray, np.ndarray], np.ndarray] | None = None,
    log_path=None,
) -> DiagnosisData:
    """Run ``n`` space-filling moves on the simulated stage with ``effects`` planted.

    Parameters
    ----------
    config : StageConfig
        Stage and simulator settings (noise levels).
    effects : Effects
        The planted truth (replaces the config's).
    n : int
    seed : int
        Seed of the moves and of the simulator's noise.
    extra : callable (u (n, n_p), q (n, n_q)) -> (n,), optional
        An effect outside the vocabulary added to the readings (e.g. a sinusoid in rx).
    log_path : path, optional
        Also write the run as a measurement log there.

    Returns
    -------
    DiagnosisData
    """
    cfg = with_effects(config, effects, seed)
    afm = AnalyticForwardModel(cfg.stage)
    moves = space_filling_moves(afm, n, seed=seed)
    sim = SimulatedStage(cfg)
    rows = []
    for u in moves:
        s_prev = sim.state.copy()
        m = sim.move(u)
        rows.append((m, s_prev))
    u = np.array([m.u for m, _ in rows])
    q = np.array([m.q_um for m, _ in rows])
    t = np.array([m.t_um for m, _ in rows])
    if extra is not None:
        t = t + np.asarray(extra(u, q), dtype=float)
    s_prev = np.array([s for _, s in rows])
    # t_prev as the stage saw it: the previous (possibly augmented) reading
    t_prev = np.concatenate([[s_prev[0, 0]], t[:-1]])
    time_s = np.array([m.time_s for m, _ in rows])
    if log_path is not None:
        from microctl.backends.base import Measurement

        with MeasurementLogWriter(log_path, cfg.stage, fsync=False) as w:
            for k, (m, sp) in enumerate(rows):
                sp = np.concatenate([[t_prev[k]], sp[1:]])
                w.write(Measurement(t_um=float(t[k]), q_um=m.q_um, u=m.u, time_s=m.time_s), sp)
    return data_from_arrays(u, q, t, q_prev=s_prev[:, 1:], t_prev=t_prev, time_s=time_s, source="<simulated>")


def with_noise_of(config: StageConfig, noise_from: StageConfig) -> StageConfig:
    """``config`` with the simulator noise (gauge, driver) of ``noise_from``.

    The hidden-effect tests run on the Table I stage with its healthy default physics and
    sim_paper.yaml's noise: sim_paper's own rig is preloaded far harder to carry its large
    PZT 4 defect, which would hide a realistic contact loss.
    """
    sim = replace(
        config.backend.simulated,
        gauge_noise_std_um=noise_from.backend.simulated.gauge_noise_std_um,
        driver_accuracy_um=noise_from.backend.simulated.driver_accuracy_um,
    )
    return replace(config, backend=replace(config.backend, simulated=sim))


def parameter_bar(name: str, true: float) -> float:
    """The issue's tolerance for a recovered parameter: 10 % of the deviation from healthy for
    gain-like ones (``gain``, ``scale``), 0.2 mm for offsets (``*_mm``), else 10 % of the value."""
    if name in ("gain", "scale"):
        return 0.1 * abs(true - 1.0)
    if name.endswith("_mm"):
        return 0.2
    return 0.1 * abs(true)


def compression_um(config: StageConfig) -> float:
    """Total contact compression the preload provides, µm (preload / contact stiffness)."""
    return preload_compression_um(config.stage)


def random_cause(name: str, rng: np.random.Generator, n_act: int = 4, *,
                 compression_um: float = 5.0) -> tuple[Effects, dict]:
    """One planted cause of realistic magnitude (:meth:`microctl.stage.causes.Cause.draw`).

    Parameters
    ----------
    name : str
        One of :data:`PLANTABLE` (the registry).
    rng : numpy Generator
        Draws the actuator (uniform) and the magnitude.
    n_act : int
    compression_um : float
        What the preload can make up: the total elastic compression of the contacts,
        ``physics.preload_n / physics.contact_stiffness_n_per_um`` (5 µm with the defaults).

    Returns
    -------
    effects : Effects
    truth : dict
        ``{"cause", "actuator" (or None), "params": {...}}`` in report names.
    """
    if name not in REGISTRY:
        raise ValueError(f"unknown cause {name!r}; plantable: {', '.join(PLANTABLE)}")
    cls = REGISTRY[name]
    act = int(rng.integers(1, n_act + 1))
    cause = cls.draw(rng, act if cls.per_actuator else None, compression_um=compression_um)
    params = cause.report_params()
    params.pop("actuator", None)
    return Effects.of([cause]), {"cause": name, "actuator": act if cls.per_actuator else None, "params": params}
