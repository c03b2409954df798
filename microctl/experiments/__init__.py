"""The paper's experiments (Su et al., section IV): training, absolute and incremental movement.

Modules:

- :mod:`~microctl.experiments.config` — the experiment YAML → frozen dataclasses, validated
  (with the stage config it names) before any move is made;
- :mod:`~microctl.experiments.design` — training move designs (IV-A);
- :mod:`~microctl.control.oracle` — the controller that optimises against the simulator's
  true mean and variance (the limit any learned model can reach);
- :mod:`~microctl.experiments.controllers` — the registry of the controllers an experiment can
  compare (name, label, plot style, factory): adding a controller is one registration;
- :mod:`~microctl.experiments.runner` — executes the phases, logging every move row by row;
- :mod:`~microctl.experiments.report` — statistics (Table II, the t-tests), results.json, report.md;
- :mod:`~microctl.experiments.figures` — Fig. 5 and Fig. 6 analogues (PNG, matplotlib optional).
"""

from microctl.experiments.config import ExperimentConfig, load_experiment_config

__all__ = ["ExperimentConfig", "load_experiment_config"]
