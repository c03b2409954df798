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

The same floor is not an estimate either when *no* training move is floor-only, or when the fit
left it at the lower box bound of mu0: every reading then carries a selected source's variance
far above the floor (a hinge that slips with every tilt, moves that all tilt), nothing in the
data bounds c_0 from below, and the optimiser drives it to the bound. The scatter predicted
at a move the sources leave quiet (a pure lift) is then c_0 alone, orders of magnitude below the
gauge's. :func:`interpolated_floor` reports both (``floor_rows == 0``, ``at_bound``).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from microctl.gp.bound import BOUNDS

__all__ = ["FloorCheck", "finding_of", "interpolated_floor", "with_floor_check", "HAT_LIMIT", "FLOOR_FACTOR",
           "BOUND_MARGIN", "CONSEQUENCE", "ADVICE"]

#: A training move whose reading f follows by more than this share (hat value) is interpolated:
#: most of the reading is then in f, and the reading hardly informs the floor. (At 1/2, fits with a
#: sound floor are flagged too: an isolated move can carry that much of f.)
HAT_LIMIT = 0.8
#: A move counts as floor-only where the predicted noise variance is within this factor of c_0.
FLOOR_FACTOR = 2.0
#: mu0 (log c_0, standardised) within this of its lower box bound counts as at the bound.
BOUND_MARGIN = 1e-3


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
    at_bound : bool
        The fitted mu0 = log c_0 is at its lower box bound (:data:`microctl.gp.bound.BOUNDS`).
    """

    rows: tuple[int, ...]
    hat: tuple[float, ...]
    floor_std_um: float
    floor_rows: int
    at_bound: bool = False

    @property
    def unsupported(self) -> bool:
        """Whether no training move is floor-only or the floor sits at its lower bound (module docstring)."""
        return self.floor_rows == 0 or self.at_bound

    @property
    def degenerate(self) -> bool:
        """Whether the floor is not an estimate: f passes through a reading that only the floor
        should scatter, or no reading bounds it (:attr:`unsupported`)."""
        return bool(self.rows) or self.unsupported

    def describe(self) -> str:
        """One line for ``microctl train``."""
        return f"{self.finding()}: the floor std {self.floor_std_um:.3g} µm is then not an estimate, and {CONSEQUENCE}. " \
               f"{ADVICE} and train again"

    def finding(self) -> str:
        """What was found, without its consequence (the experiment's report words the rest)."""
        if self.rows:
            return (f"the mean correction passes through {len(self.rows)} of the {self.floor_rows} training reading(s) "
                    f"that the noise model gives only its floor (hat values up to {max(self.hat):.2f})")
        if self.floor_rows == 0:
            return ("no training reading is floor-only (every one has a selected source's variance above twice the "
                    "floor)" + (", and the floor sits at its lower bound" if self.at_bound else ""))
        return (f"the noise floor sits at its lower bound (the {self.floor_rows} floor-only training reading(s) do not "
                f"bound it from below)")

    def as_info(self) -> dict:
        """The JSON kept in the model's ``info["floor_check"]`` and in an experiment's results."""
        return {"rows": list(self.rows), "hat": list(self.hat), "floor_std_um": self.floor_std_um,
                "floor_rows": self.floor_rows, "at_bound": self.at_bound, "finding": self.finding()}


def finding_of(info: dict) -> str:
    """The finding of a floor check kept as JSON (:meth:`FloorCheck.as_info`), also one written
    before ``as_info`` kept its ``finding`` (then the check flagged only readings that the mean
    correction passes through, and its ``rows`` are those readings)."""
    if info.get("finding"):
        return str(info["finding"])
    return (f"the mean correction passes through {len(info['rows'])} training reading(s) that the noise model "
            f"gives only its floor")


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
    at_bound = float(model.g_mu0) <= BOUNDS["mu0"][0] + BOUND_MARGIN
    return FloorCheck(tuple(int(i) for i in rows), tuple(float(h) for h in hat[rows]),
                      float(np.sqrt(floor_var)), int(np.sum(floor_only)), bool(at_bound))


def with_floor_check(model, data):
    """``model`` with a degenerate :func:`interpolated_floor` result kept in its
    ``info["floor_check"]`` (:meth:`FloorCheck.as_info`), and that result.

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
    model = replace(model, info={**model.info, "floor_check": check.as_info()})
    return model, check
