"""The controllers an experiment can compare: one registry read by the runner, the config
validation, the figures and the report.

Each :class:`ControllerEntry` carries a controller's name (as written in the experiment config,
the logs and ``results.json``), its label (report.md, figures), its plot style, whether it plans
the whole target list (a sequence controller) and whether it needs the simulator's truth (the
oracles, eq. 4 on the true mean and variance), and a factory ``build(run, eafm) -> controller``.
Adding a controller to the experiments is one :func:`register` call (plus its tests).

``run`` is the runner's run state; a factory reads only ``run.afm`` (the
:class:`~microctl.models.afm.AnalyticForwardModel`) and ``run.cfg`` (the
:class:`~microctl.experiments.config.ExperimentConfig`: ``controller`` and ``oracle`` settings).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable

from microctl.control.controller import AFMController, OptimalController
from microctl.control.oracle import OracleController, OracleSequenceController
from microctl.control.sequence import SequenceController

__all__ = ["PlotStyle", "ControllerEntry", "register", "entry", "names", "label", "style",
           "default_names", "required_names", "sequence_pairs", "REGISTRY"]


@dataclass(frozen=True)
class PlotStyle:
    """How a controller is drawn (the same in every figure).

    Attributes
    ----------
    color, marker : str
        Matplotlib colour and marker.
    fill : bool
        Filled marker (else an open one).
    offset : float
        Horizontal offset (in trials) of its markers in Fig. 6, so coinciding controllers stay visible.
    """

    color: str = "0.3"
    marker: str = "^"
    fill: bool = True
    offset: float = 0.0


#: The style of a name not in the registry.
DEFAULT_STYLE = PlotStyle()


@dataclass(frozen=True)
class ControllerEntry:
    """One controller of the experiments.

    Attributes
    ----------
    name : str
        Its name in the config, the logs and ``results.json``.
    label : str
        Its name in report.md and the figures.
    build : callable
        ``build(run, eafm) -> controller``: a move-by-move controller has
        ``solve(target, s, u_init=None) -> ControlResult``; a sequence controller has
        ``plan(targets, s, ...)``.
    style : PlotStyle
    sequence : bool
        Plans over the remaining target list (see :func:`microctl.experiments.runner._sequence_step`).
    replan : bool
        A sequence controller that re-plans after every executed move (receding horizon);
        False: it plans once and executes its plan.
    needs_truth : bool
        Needs the simulator's true mean and variance (``bind(truth)`` before every trial);
        allowed only with a simulated or emulated stage.
    default : bool
        Compared when the config names no controllers.
    required : bool
        Every experiment must compare it (the paper's AFM and EAFM).
    greedy : str or None
        For a sequence controller: the move-by-move controller it is compared with in report.md
        (greedy against sequence control).
    """

    name: str
    label: str
    build: Callable[[Any, Any], Any]
    style: PlotStyle = DEFAULT_STYLE
    sequence: bool = False
    replan: bool = True
    needs_truth: bool = False
    default: bool = False
    required: bool = False
    greedy: str | None = None


#: name -> entry, in registration order (the order of the docs' list).
REGISTRY: dict[str, ControllerEntry] = {}


def register(e: ControllerEntry, *, replace: bool = False) -> ControllerEntry:
    """Add ``e`` to the registry (``replace=True`` to overwrite an entry of the same name)."""
    if e.name in REGISTRY and not replace:
        raise ValueError(f"controller '{e.name}' is registered already")
    REGISTRY[e.name] = e
    return e


def entry(name: str) -> ControllerEntry:
    """The registered entry of ``name`` (KeyError when unknown)."""
    return REGISTRY[name]


def names() -> tuple[str, ...]:
    """Every registered controller name."""
    return tuple(REGISTRY)


def default_names() -> tuple[str, ...]:
    """The controllers compared when the config names none."""
    return tuple(n for n, e in REGISTRY.items() if e.default)


def required_names() -> tuple[str, ...]:
    """The controllers every experiment must compare."""
    return tuple(n for n, e in REGISTRY.items() if e.required)


def sequence_pairs() -> tuple[tuple[str, str], ...]:
    """(greedy, sequence) name pairs compared in report.md, in registration order."""
    return tuple((e.greedy, n) for n, e in REGISTRY.items() if e.greedy is not None)


def label(name: str) -> str:
    """The label of ``name`` (the name itself when unregistered)."""
    e = REGISTRY.get(name)
    return e.label if e is not None else name


def style(name: str) -> PlotStyle:
    """The plot style of ``name`` (:data:`DEFAULT_STYLE` when unregistered)."""
    e = REGISTRY.get(name)
    return e.style if e is not None else DEFAULT_STYLE


# --------------------------------------------------------------------------------------
# the paper's controllers (eq. 4) and the sequence controllers
# --------------------------------------------------------------------------------------


def _afm(run, eafm):
    return AFMController(run.afm, run.cfg.controller, reporter=eafm)


def _eafm(run, eafm):
    # with the AFM baseline: each result says whether its pose is credibly quieter
    return OptimalController(eafm, run.cfg.controller, baseline=AFMController(run.afm, run.cfg.controller))


def _oracle(run, eafm):
    o = run.cfg.oracle
    return OracleController(run.afm, None, grid=o.grid, line_points=o.line_points, zooms=o.zooms,
                            newton_steps=o.newton_steps)


def _eafm_sequence(run, eafm):
    return SequenceController(eafm, run.cfg.controller)


def _oracle_sequence(run, eafm):
    o = run.cfg.oracle
    return OracleSequenceController(run.afm, None, grid=o.grid, line_points=o.line_points, zooms=o.zooms,
                                    newton_steps=o.newton_steps,
                                    sequence_objective=run.cfg.controller.sequence_objective)


register(ControllerEntry("afm", "AFM", _afm, PlotStyle("tab:blue", "o", True, -0.3),
                         default=True, required=True))
register(ControllerEntry("eafm", "EAFM", _eafm, PlotStyle("tab:red", "D", True, -0.1),
                         default=True, required=True))
register(ControllerEntry("oracle", "oracle", _oracle, PlotStyle("tab:green", "s", False, 0.1),
                         needs_truth=True, default=True))
register(ControllerEntry("eafm_sequence", "EAFM sequence", _eafm_sequence, PlotStyle("tab:purple", "v", True, 0.3),
                         sequence=True, greedy="eafm"))
# the truth depends on the previous state only through q, which the commands fix: a re-plan
# would return the same moves, so the oracle sequence plans once
register(ControllerEntry("oracle_sequence", "oracle sequence", _oracle_sequence,
                         PlotStyle("tab:olive", "^", False, 0.4), sequence=True, replan=False, needs_truth=True,
                         greedy="oracle"))
