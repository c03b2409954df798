"""The stage geometry: frozen dataclasses of paper Table I (actuators, tool, contact physics).

Built and validated from YAML by :mod:`microctl.stage.config`; the model corrections a stage
carries are an :class:`~microctl.stage.causes.Effects` (the cause registry).

Units: lengths of the platform motion and actuators in µm, rotations in mrad, geometry
(contact points, tool point) in mm, so that mrad × mm = µm.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

from microctl.stage.causes import Effects

#: Twist components of a rigid body, in the paper's order v = [v; ω] (eq. 5): translations
#: in µm, rotations in mrad.
TWIST_COMPONENTS = ("x", "y", "z", "rx", "ry", "rz")

# --------------------------------------------------------------------------------------
# dataclasses
# --------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Actuator:
    """One PZT pushing one ball against the platform.

    Attributes
    ----------
    name : str
        Column name of its displacement in measurement logs (``q1``).
    contact_mm : tuple of 3 float
        Contact point c_i of the ball on the platform (eq. 6), mm.
    normal : tuple of 3 float
        Unit normal n_i of the contact tangent plane, pointing into the platform.
    direction : tuple of 3 float
        Unit direction in which the actuator moves its ball (J_i, eq. 7).
    range_um : tuple of 2 float
        Commanded displacement range used, (lo, hi), µm. Moves outside are refused.
    limit_um : tuple of 2 float
        Hardware limit, (lo, hi), µm; contains ``range_um``.
    """

    name: str
    contact_mm: tuple[float, float, float]
    normal: tuple[float, float, float] = (0.0, 0.0, 1.0)
    direction: tuple[float, float, float] = (0.0, 0.0, 1.0)
    range_um: tuple[float, float] = (0.0, 32.0)
    limit_um: tuple[float, float] = (0.0, 38.0)


@dataclass(frozen=True)
class Tool:
    """The measured tool point and the gauge direction (eq. 13).

    Attributes
    ----------
    name : str
        Column name of the measured tool pose (``t``).
    point_mm : tuple of 3 float
        Tool point t0 in the world frame, mm.
    direction : tuple of 3 float
        Unit direction the gauge measures along (T_s).
    """

    name: str = "t"
    point_mm: tuple[float, float, float] = (0.0, 0.0, 0.0)
    direction: tuple[float, float, float] = (0.0, 0.0, 1.0)


@dataclass(frozen=True)
class Physics:
    """Elastic contact physics of the stage (used by the simulator and the diagnosis).

    The flexure presses the platform onto the balls with ``preload_n`` and resists motion
    with ``flexure_stiffness``; each ball is a one-sided spring of ``contact_stiffness``.

    Attributes
    ----------
    contact_stiffness_n_per_um : float
        Stiffness of one ball contact (ball + PZT in series), N/µm.
    preload_n : float
        Force with which the flexure presses the platform down at the zero pose, N.
    flexure_stiffness : tuple of float
        Flexure stiffness per hinge DoF, in N/µm for translations and N·µm/mrad² for
        rotations (so energy is in N·µm), one per ``Stage.dof``.
    """

    contact_stiffness_n_per_um: float = 20.0
    preload_n: float = 100.0
    flexure_stiffness: tuple[float, ...] = (0.01, 5.0, 5.0)


# ---- causes / effects: the vocabulary lives in microctl.stage.causes (one registry); the config
# entries are its classes, re-exported here for the config's users.


@dataclass(frozen=True)
class Stage:
    """The stage geometry and model (paper Table I and eq. 5-14).

    Attributes
    ----------
    name : str
        Free-text name.
    dof : tuple of str
        Hinge DoF allowed by the flexure, a subset of ``TWIST_COMPONENTS`` (J_h, eq. 5).
    actuators : tuple of Actuator
        One per PZT/ball, at least ``len(dof)``.
    tool : Tool
        Tool point and gauge direction.
    physics : Physics
        Elastic contact physics.
    corrections : Effects
        Model corrections accepted from a diagnosis (empty for a CAD model).
    """

    name: str
    dof: tuple[str, ...]
    actuators: tuple[Actuator, ...]
    tool: Tool
    physics: Physics = field(default_factory=Physics)
    corrections: Effects = field(default_factory=Effects)

    @property
    def n_dof(self) -> int:
        """Number of hinge DoF (the size of u = p)."""
        return len(self.dof)

    @property
    def n_act(self) -> int:
        """Number of actuators (the size of q)."""
        return len(self.actuators)

    @property
    def actuator_names(self) -> tuple[str, ...]:
        """Actuator names in config order."""
        return tuple(a.name for a in self.actuators)

    @property
    def range_lo(self) -> np.ndarray:
        """Lower actuator range, µm, shape (n_act,)."""
        return np.array([a.range_um[0] for a in self.actuators], dtype=float)

    @property
    def range_hi(self) -> np.ndarray:
        """Upper actuator range, µm, shape (n_act,)."""
        return np.array([a.range_um[1] for a in self.actuators], dtype=float)

    def geometry_hash(self) -> str:
        """SHA-256 of everything the forward model depends on (not the name, not physics)."""
        payload = {
            "dof": list(self.dof),
            "actuators": [asdict(a) for a in self.actuators],
            "tool": asdict(self.tool),
            "corrections": self.corrections.to_dict(),
        }
        text = json.dumps(payload, sort_keys=True, default=float)
        return hashlib.sha256(text.encode()).hexdigest()

    def shape_hash(self) -> str:
        """SHA-256 of the geometry alone (DoF, actuators, tool): :meth:`geometry_hash` without the corrections."""
        payload = {"dof": list(self.dof), "actuators": [asdict(a) for a in self.actuators], "tool": asdict(self.tool)}
        return hashlib.sha256(json.dumps(payload, sort_keys=True, default=float).encode()).hexdigest()

    def physics_hash(self) -> str:
        """SHA-256 of the contact physics (stiffness, preload, flexure), which the geometry hash leaves out."""
        text = json.dumps(asdict(self.physics), sort_keys=True, default=float)
        return hashlib.sha256(text.encode()).hexdigest()

    def to_dict(self) -> dict[str, Any]:
        """The YAML form of the ``stage`` section."""
        out: dict[str, Any] = {
            "name": self.name,
            "dof": list(self.dof),
            "tool": {
                "name": self.tool.name,
                "point_mm": list(self.tool.point_mm),
                "direction": list(self.tool.direction),
            },
            "actuators": [
                {
                    "name": a.name,
                    "contact_mm": list(a.contact_mm),
                    "normal": list(a.normal),
                    "direction": list(a.direction),
                    "range_um": list(a.range_um),
                    "limit_um": list(a.limit_um),
                }
                for a in self.actuators
            ],
            "physics": {
                "contact_stiffness_n_per_um": self.physics.contact_stiffness_n_per_um,
                "preload_n": self.physics.preload_n,
                "flexure_stiffness": list(self.physics.flexure_stiffness),
            },
        }
        if not self.corrections.is_empty():
            out["corrections"] = self.corrections.to_dict()
        return out
