"""The gauge transfer: one object for the reading of a tool displacement (forward, derivative, inverse).

The AFM's tool map (paper eq. 13) gives the linear displacement d of the tool point along the
gauge direction, relative to the zero state. The gauge reads

    t = scale·d + quad_per_um·d² + drift_um_per_s·time_s

(``sensor_scale``, ``sensor_nonlinearity`` and ``drift`` of the cause vocabulary,
:mod:`microctl.stage.causes`; a healthy gauge has scale 1, quad 0, drift 0). Every model of the
package reads the gauge through this object: the AFM (:mod:`microctl.models.afm`), the contact
physics (:mod:`microctl.stage.physics`), the extended model (:mod:`microctl.models.extended`).

:meth:`Sensor.forward` and :meth:`Sensor.derivative` use arithmetic only, so they accept
NumPy arrays, floats and CasADi symbols alike.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["Sensor"]


@dataclass(frozen=True)
class Sensor:
    """Gauge reading of a tool displacement.

    Attributes
    ----------
    scale : float
        Reading per µm of displacement (1 when healthy).
    quad_per_um : float
        Quadratic coefficient, 1/µm (0 when healthy).
    drift_um_per_s : float
        Linear creep of the reading with time, µm/s (0 when healthy).
    """

    scale: float = 1.0
    quad_per_um: float = 0.0
    drift_um_per_s: float = 0.0

    @property
    def is_linear(self) -> bool:
        """Whether the transfer is linear in d (no quadratic term)."""
        return self.quad_per_um == 0.0

    def forward(self, d_um, time_s=None):
        """Reading for displacements ``d_um`` (any shape, or a CasADi expression).

        Parameters
        ----------
        d_um : float, ndarray or casadi.MX/SX
            Linear tool displacement relative to the zero state, µm.
        time_s : float or ndarray broadcastable to ``d_um``, optional
            Time since the zero state, s; without it the drift term is left out.

        Returns
        -------
        Same type and shape as ``d_um``: scale·d + quad·d² (+ drift·time).
        """
        out = self.scale * d_um + self.quad_per_um * d_um * d_um
        if time_s is not None and self.drift_um_per_s != 0.0:
            out = out + self.drift_um_per_s * np.asarray(time_s, dtype=float)
        return out

    def derivative(self, d_um):
        """d reading / d d = scale + 2·quad·d, same shape as ``d_um`` (time does not enter)."""
        return self.scale + 2.0 * self.quad_per_um * d_um

    def vertex_um(self) -> float | None:
        """Displacement where the quadratic transfer turns (derivative 0), or None if linear."""
        if self.is_linear:
            return None
        return -self.scale / (2.0 * self.quad_per_um)

    def inverse(self, t_um, time_s=None):
        """Displacement whose reading is ``t_um`` (scalar or ndarray).

        The root of scale·d + quad·d² = t − drift·time nearest the linear answer t/scale (the
        branch a healthy gauge is on). A reading beyond the turning point of the quadratic has
        no root; the turning point (:meth:`vertex_um`, the closest reachable reading) is
        returned there.

        Parameters
        ----------
        t_um : float or ndarray
        time_s : float or ndarray, optional
            Subtract the drift accumulated by then.

        Returns
        -------
        float or ndarray (shape of ``t_um``)
        """
        t = np.asarray(t_um, dtype=float)
        if time_s is not None and self.drift_um_per_s != 0.0:
            t = t - self.drift_um_per_s * np.asarray(time_s, dtype=float)
        a, b = self.quad_per_um, self.scale
        if a == 0.0:
            out = t / b
        else:
            disc = b * b + 4.0 * a * t
            root = np.sqrt(np.maximum(disc, 0.0))
            r1, r2 = (-b + root) / (2 * a), (-b - root) / (2 * a)
            lin = t / b
            out = np.where(np.abs(r1 - lin) <= np.abs(r2 - lin), r1, r2)
            out = np.where(disc < 0, -b / (2 * a), out)
        return float(out) if np.ndim(out) == 0 else out

    def reading_range(self, d_lo_um: float, d_hi_um: float) -> tuple[float, float]:
        """Smallest and largest reading over displacements in [d_lo, d_hi] (drift left out)."""
        cands = [float(self.forward(d_lo_um)), float(self.forward(d_hi_um))]
        v = self.vertex_um()
        if v is not None and d_lo_um < v < d_hi_um:
            cands.append(float(self.forward(v)))
        return min(cands), max(cands)

