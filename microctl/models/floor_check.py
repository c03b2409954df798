"""Does the mean correction pass through readings that the noise model calls floor-only?

The noise floor c_0 of g's prior mean (``noise_prior`` eq. 1) is identified by the training
moves where no selected source is active. When only a few such moves exist, the VHGPR bound
has a degenerate direction: the mean correction f passes through their readings while the
floor shrinks towards zero, and the bound grows without limit (-1/2 log c_0 per reading passed
through), until the optimiser stops near the box bound of mu0 (:data:`microctl.gp.bound.BOUNDS`).
The floor is then not an estimate, and the repeatability the model predicts at quiet moves
(the poses the controller seeks) is far below what the stage does.

The symptom is measured without the truth, by each training move's *hat value*, how much of
its own reading the fitted f follows. For an exact GP posterior with (effective) noise R,
f's posterior mean at the training inputs is ``H y`` with ``H = K (K + R)^-1``, and its
posterior variance there is ``[K (K + R)^-1 R]_ii = H_ii R_ii``, so

    H_ii = f_var_i / R_ii,       R_ii = exp(mu_i - Sigma_ii / 2)

(the VHGPR's effective noise, Lázaro-Gredilla & Titsias 2011, with mu, Sigma q(g)'s mean and
variance at the training inputs). A reading the fit treats as independent scatter has
``H_ii`` well below 1 (each reading is one of many that inform f there); ``H_ii`` near 1
means f passes through it. :func:`interpolated_floor` reports the moves whose predicted noise
is within a factor :data:`FLOOR_FACTOR` of the floor and whose hat value exceeds
:data:`HAT_LIMIT`.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

__all__ = ["FloorCheck", "interpolated_floor", "with_floor_check", "HAT_LIMIT", "FLOOR_FACTOR", "CONSEQUENCE", "ADVICE"]

#: A training move whose reading f follows by more than this share (hat value) is interpolated:
#: most of the reading is then in f, and the reading hardly informs the floor. (At 1/2, fits with a
#: sound floor are flagged too: an isolated move can carry that much of f.)
HAT_LIMIT = 0.8
#: A move counts as floor-only where the predicted noise variance is within this factor of c_0.
FLOOR_FACTOR = 2.0


@dataclass(frozen=True)
class FloorCheck:
    """What :func:`interpolated_floor` found.

    Attributes
    ----------
    rows : tuple of int
        0-based training rows: floor-only and interpolated by f.
    hat : tuple of float
        Their hat values H_ii.
    floor_std_um : float
        The fitted floor's standard deviation sqrt(c_0), µm.
    floor_rows : int
        Training rows whose predicted noise is within :data:`FLOOR_FACTOR` of the floor.
    """

    rows: tuple[int, ...]
    hat: tuple[float, ...]
    floor_std_um: float
    floor_rows: int

    @property
    def degenerate(self) -> bool:
        """Whether f passes through a reading that only the floor should scatter."""
        return bool(self.rows)

    def describe(self) -> str:
        """One line for ``microctl train``."""
        return (f"the mean correction passes through {len(self.rows)} of the {self.floor_rows} training reading(s) "
                f"that the noise model gives only its floor (hat values up to {max(self.hat):.2f}): the floor std "
                f"{self.floor_std_um:.3g} µm is then not an estimate, and {CONSEQUENCE}. {ADVICE} and train again")


#: What a floor that is not an estimate does, and what to collect then (``describe`` and the
#: experiment's report.md say both).
CONSEQUENCE = ("the repeatability predicted at quiet moves can be far too small, and so can the mean correction's "
               "stated uncertainty (the readings it passes through weigh as if noise-free)")
ADVICE = "Collect more moves that leave every actuator nearly still (or re-read a pose a few times)"


def interpolated_floor(model, X: np.ndarray) -> FloorCheck | None:
    """The floor-only training moves that f passes through (module docstring).

    Parameters
    ----------
    model : FittedVHGPR
        A trained residual model with an exact posterior.
    X : ndarray, shape (n, d)
        Its training inputs as the model reads them (the move's context appended when the model
        reads it).

    Returns
    -------
    FloorCheck or None
        None for a sparse posterior (its f is not H y) or a model without a floor parameter.
    """
    if getattr(model, "posterior_form", "exact") != "exact" or getattr(model, "g_mu0", None) is None:
        return None
    p = model.predict(np.atleast_2d(np.asarray(X, dtype=float)))
    floor_var = float(np.exp(model.g_mu0)) * float(model.y_scale) ** 2
    noise = np.exp(p.g_mean + 0.5 * p.g_var)
    R = np.exp(p.g_mean - 0.5 * p.g_var)
    hat = np.clip(p.f_var / R, 0.0, 1.0)
    floor_only = noise <= FLOOR_FACTOR * floor_var
    rows = np.flatnonzero(floor_only & (hat > HAT_LIMIT))
    return FloorCheck(tuple(int(i) for i in rows), tuple(float(h) for h in hat[rows]),
                      float(np.sqrt(floor_var)), int(np.sum(floor_only)))


def with_floor_check(model, data):
    """``model`` with a degenerate :func:`interpolated_floor` result kept in its
    ``info["floor_check"]`` (rows, hat values, floor std), and that result.

    Parameters
    ----------
    model : FittedVHGPR
    data : ResidualData
        The data it was trained on.

    Returns
    -------
    model : FittedVHGPR
    check : FloorCheck or None
        The check when it is degenerate, else None (nothing to report).
    """
    check = interpolated_floor(model, data.inputs_for(model))
    if check is None or not check.degenerate:
        return model, None
    model = replace(model, info={**model.info, "floor_check": {"rows": list(check.rows), "hat": list(check.hat),
                                                               "floor_std_um": check.floor_std_um}})
    return model, check
