"""Model-discrepancy diagnosis (shared/spec/diagnosis.md): show, name, extend, measure the gain.

- :mod:`~microctl.diagnosis.data`: the measured moves as arrays;
- :mod:`~microctl.diagnosis.residuals`: residual size, structure and where it grows;
- :mod:`~microctl.diagnosis.causes`: every mean cause as a physical change of the stage
  model, fitted by nonlinear least squares with standard errors;
- :mod:`~microctl.diagnosis.selection`: greedy forward selection by BIC, equivalences, the
  backward check;
- :mod:`~microctl.diagnosis.flexible`: the vocabulary-free flexible term: leftover structure
  (``unexplained``) and the guard that withdraws causes it explains as well;
- :mod:`~microctl.diagnosis.outliers`: outlying rows, reported and left out of the fits;
- :mod:`~microctl.diagnosis.noise`: noise causes by maximum likelihood;
- :mod:`~microctl.diagnosis.gain`: held-out gain of afm, afm_gp, extended, extended_gp;
- :mod:`~microctl.diagnosis.report`, :mod:`~microctl.diagnosis.figures`: outputs;
- :mod:`~microctl.diagnosis.pipeline`: :func:`run_diagnosis`, all of it;
"""

from microctl.diagnosis.data import DiagnosisData, data_from_arrays, data_from_log
from microctl.diagnosis.pipeline import Diagnosis, run_diagnosis
from microctl.diagnosis.report import write_outputs

__all__ = ["Diagnosis", "DiagnosisData", "data_from_arrays", "data_from_log", "run_diagnosis", "write_outputs"]
