"""The controllers' settings: one set of defaults for ``solve``, ``experiment`` and the API."""

from __future__ import annotations

from dataclasses import dataclass

from microctl.control.objectives import NoiseVariance
from microctl.control.sequence_objectives import SEQUENCE_OBJECTIVES, SequenceObjective
from microctl.util.fields import same_setting, setting, validate_settings

__all__ = ["ControllerSettings"]


@dataclass(frozen=True)
class ControllerSettings:
    """Settings of the controllers: the one set of defaults of ``solve``, ``experiment`` and the API.

    Each field is declared once with its default and its rule (:func:`microctl.util.fields.setting`):
    validated here, and read from YAML by :func:`microctl.util.fields.read_settings`.

    Attributes
    ----------
    r_e : str
        Noise summary of eq. 4, a name registered in
        :data:`~microctl.control.noise_summaries.R_E_SUMMARIES` (default ``"noise_quantile"``: the
        upper quantile, cautious where the noise model is uncertain).
    kappa : float
        Standard normal quantile of ``noise_quantile`` (1.645: the 95 % quantile).
    epistemic : bool
        Add the mean correction's posterior variance to r_e (default true: the expected squared
        error about the target is f's variance plus the noise variance).
    credible_level : float
        Probability above which the chosen pose counts as credibly quieter than the AFM
        baseline's (:func:`~microctl.control.baseline.compare_noise`).
    prefer_least_motion : bool
        The optimal controller returns the smallest actuator motion onto the EAFM-mean surface
        (:class:`~microctl.control.controller.EAFMMeanController`) unless eq. 4's optimum has the
        lower expected squared error (f's variance plus the noise variance, its posterior mean)
        once the noise sources the data did not select are weighed in
        (:mod:`microctl.control.credible`). Default true; false: eq. 4's optimum always (the
        paper's rule).
    least_motion_credible : bool
        With ``prefer_least_motion``, also require that the optimum's expected squared error is
        lower with posterior probability >= ``credible_level`` (default false; true is the rule
        of the previous release, which kept the least motion wherever g's posterior at the two
        poses is wide, also where the optimum is in truth much quieter).
    weigh_alternatives : bool
        Add to eq. 4's r_e the model-averaged extra variance of the noise sources the data did
        not select (:mod:`microctl.models.alternatives`): the optimum then weighs a plausible
        but unproven source on an actuator before moving it.
    grid : int
        Grid points per null-space axis of the global seeding (``grid**(n_p-1)`` points).
    newton_steps : int
        Newton steps along w that move each grid point onto the EAFM-mean surface.
    n_polish : int
        Largest number of grid local minima polished by IPOPT.
    polish_ratio : float
        Only local minima with seed objective ``<= polish_ratio * best`` are polished.
    constraint_tol : float
        Largest accepted ``|t_mean(s, u) - t_d|`` (µm) of a returned command.
    range_tol : float
        Largest accepted excursion of ``K u`` beyond the actuator ranges (µm) before q is
        clipped into them.
    ipopt_tol : float
        IPOPT ``tol``.
    max_iter : int
        IPOPT ``max_iter`` per start.
    fast_path : bool
        Polish each start with the small SQP of :mod:`microctl.control.fastpath` first (exact
        Hessian, enumerated active-set QP steps; its answer accepted only when the KKT
        conditions hold to ``ipopt_tol``, the target to ``constraint_tol`` and every range), IPOPT
        from the same start otherwise (default True). A start it solves reports IPOPT's status
        for the same outcome, ``Solve_Succeeded``. False: IPOPT only.
    sequence_objective : str
        What sequence control (:mod:`microctl.control.sequence`) minimises over a target list, a
        name registered in :data:`~microctl.control.sequence_objectives.SEQUENCE_OBJECTIVES`:
        ``"sum"`` (default) the cumulative r_e of the moves, ``"max"`` the worst move's.
    """

    r_e: str = same_setting(NoiseVariance, "r_e")
    kappa: float = same_setting(NoiseVariance, "kappa")
    epistemic: bool = same_setting(NoiseVariance, "epistemic")
    credible_level: float = setting(0.95, lo=0.5, hi=1.0, lo_open=True)
    prefer_least_motion: bool = setting(True)
    least_motion_credible: bool = setting(False)
    weigh_alternatives: bool = setting(False)
    grid: int = setting(15, lo=2, hi=201)
    newton_steps: int = setting(4, lo=1, hi=50)
    n_polish: int = setting(2, lo=1, hi=50)
    polish_ratio: float = setting(1.1, lo=1.0, hi=1e6)
    constraint_tol: float = setting(1e-8, lo=0.0, hi=1e-3, lo_open=True)  # µm: a command must meet the target
    range_tol: float = setting(1e-9, lo=0.0, hi=1e-3)                     # µm: round-off only
    ipopt_tol: float = setting(1e-8, lo=0.0, hi=1e-2, lo_open=True)
    max_iter: int = setting(200, lo=1, hi=100_000)
    fast_path: bool = setting(True)
    sequence_objective: str = SEQUENCE_OBJECTIVES.setting("sum")

    def __post_init__(self) -> None:
        validate_settings(self, "controller setting")

    def objective(self) -> NoiseVariance:
        """The objective of eq. 4 these settings describe."""
        return NoiseVariance(r_e=self.r_e, kappa=float(self.kappa), epistemic=self.epistemic,
                             alternatives=self.weigh_alternatives)

    def sequence(self) -> SequenceObjective:
        """The sequence objective these settings name (``sequence_objective``)."""
        return SEQUENCE_OBJECTIVES[self.sequence_objective]()
