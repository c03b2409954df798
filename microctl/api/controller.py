"""The EAFM optimal controller for one stage and residual model (:mod:`microctl.api`, docs/api.md)."""

from __future__ import annotations

import math
from typing import Any, Sequence

import numpy as np

from microctl.api.stage import Stage
from microctl.control.context import ByDirection
from microctl.control.controller import AFMController, ControllerSettings, OptimalController, with_baseline
from microctl.control.memory import MemoryCompensated, with_memory
from microctl.control.result import ControlResult
from microctl.errors import ConfigError
from microctl.models.eafm import EAFM


class Controller:
    """The EAFM optimal controller of eq. 4 for one stage and residual model.

    Parameters
    ----------
    stage : Stage
    model : path or FittedVHGPR
        A model file from ``microctl train`` / :func:`train` (checked against the stage geometry).
    settings : ControllerSettings, optional
        r_e, kappa and the solver settings (default: the package's).
    """

    def __init__(self, stage: Stage, model: Any, settings: ControllerSettings | None = None):
        self.stage = stage
        self.settings = settings or ControllerSettings()
        self._load(model)

    def _load(self, model: Any) -> None:
        eafm = EAFM(self.stage.afm, model)
        # with hysteresis corrections the controller meets the target with the play states; a
        # model that reads the actuators' last directions gets a controller per direction
        self._by_direction = ByDirection(eafm, lambda e: with_memory(OptimalController(e, self.settings),
                                                                     self.stage.afm))
        self.eafm, self.optimal = eafm, self._by_direction(None)
        self.model_source = eafm.source
        self._baseline: AFMController | None = None

    def reload(self, model: Any | None = None) -> None:
        """Load the model again (default: the same file, e.g. after a refit) and rebuild the solver."""
        if model is None:
            if self.model_source.startswith("<"):
                raise ConfigError("reload: the controller's model was given in memory; give a model file")
            model = self.model_source
        self._load(model)

    @property
    def n_train(self) -> int:
        """Number of moves the residual model was trained on."""
        return self.eafm.n_train

    def reachable_interval(self, state: Sequence[float] | np.ndarray | None = None) -> tuple[float, float]:
        """EAFM-mean tool poses reachable from ``state`` (µm; default the zero state)."""
        return self.optimal.reachable_interval(self.stage.check_state(state))

    def solve(self, target_um: float, state: Sequence[float] | np.ndarray | None = None, *,
              baseline: bool = False, memory: np.ndarray | None = None,
              direction: np.ndarray | None = None) -> ControlResult:
        """The optimal control signal for ``target_um`` from ``state`` (default the zero state).

        Parameters
        ----------
        target_um : float
        state : array_like, shape (n_s,), optional
        baseline : bool
            Also solve the AFM baseline from the same state and say whether the chosen pose is
            credibly quieter (``result.baseline``, ``result.vs_baseline``).
        memory : ndarray, shape (n_q, N_PLAY), optional
            The hysteresis play states before the move, for a stage with hysteresis corrections
            (:mod:`microctl.control.memory`; default: one move from the zero state to the
            state's q). :class:`Operator` passes them from the commands it sent.
        direction : ndarray, shape (n_q,), optional
            Each actuator's last direction of motion (+1 or -1), read by a model with a reversal
            noise source (:mod:`microctl.models.direction`; default: the zero state's, all +1).
            :class:`Operator` passes it from the commands it sent.

        Returns
        -------
        ControlResult
            ``u`` (n_p,), ``q`` (n_q,) inside the ranges, ``predicted_um`` ± ``predicted_std_um``.

        Raises
        ------
        ConfigError
            A target that is not a finite number, an impossible state.
        UnreachableTargetError
            The target is outside what the stage reaches from ``state`` (the message gives the interval).
        """
        target = _finite(target_um, "target_um")
        s = self.stage.check_state(state)
        optimal = self._by_direction(direction)
        carries = isinstance(optimal, MemoryCompensated)
        if carries and memory is None:
            memory = optimal.default_memory(s)
        res = optimal.solve(target, s, memory=memory) if carries else optimal.solve(target, s)
        if baseline:
            if self._baseline is None:
                self._baseline = with_memory(AFMController(self.stage.afm, self.settings, reporter=self.eafm),
                                             self.stage.afm)
            res = with_baseline(self.eafm.with_direction(direction), res, self._baseline, self.settings.credible_level,
                                memory=memory if carries else None)
        return res

    def to_dict(self, res: ControlResult) -> dict:
        """A result as the JSON object ``microctl solve --json`` prints (docs/cli.md)."""
        afm, dof = self.stage.afm, self.stage.dof
        out = {
            "target_um": res.target_um, "state": dict(zip(afm.state_names, map(float, res.state))),
            "u": dict(zip(dof, map(float, res.u))), "q_um": res.q.tolist(), "predicted_um": res.predicted_um,
            "predicted_std_um": res.predicted_std_um, "noise_std_um": res.noise_std_um,
            "noise_upper_std_um": res.noise_upper_std_um, "bias_std_um": res.bias_std_um,
            "hysteresis_um": res.hysteresis_um,
            "objective": res.objective, "r_e": self.settings.r_e, "kappa": self.settings.kappa,
            "status": res.status, "success": res.success, "iterations": res.iterations,
            "solve_time_s": res.solve_time_s, "model": {"noise_model": self.eafm.model.noise_model},
        }
        if res.vs_baseline is not None and res.baseline is not None:
            b = res.baseline
            out["credibly_quieter_than_baseline"] = res.vs_baseline.credible
            out["vs_baseline"] = res.vs_baseline.to_dict()
            out["baseline"] = {"controller": "afm", "u": dict(zip(dof, map(float, b.u))), "q_um": b.q.tolist(),
                               "predicted_um": b.predicted_um, "predicted_std_um": b.predicted_std_um,
                               "predicted_by": "eafm", "status": b.status}
        return out


def _finite(value: Any, name: str) -> float:
    """``value`` as a finite float; ConfigError naming ``name`` otherwise (bools are refused)."""
    if isinstance(value, bool):
        raise ConfigError(f"{name}: expected a number of µm, got {value!r}")
    try:
        v = float(value)
    except (TypeError, ValueError, OverflowError):
        raise ConfigError(f"{name}: expected a number of µm, got {value!r}") from None
    if not math.isfinite(v):
        raise ConfigError(f"{name}: {value!r} is not a finite number")
    return v
