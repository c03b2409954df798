"""Controllers on a forward model: objectives, the optimal (IPOPT) controller and its baselines,
the sequence controller, and the oracle that knows the simulator's truth.

Modules, bottom up: ``registry`` (named registries of objective classes), ``noise_summaries``
(the r_e summaries of eq. 4), ``objectives`` (what an EAFM controller minimises),
``sequence_objectives`` (sum / max over the moves), ``settings`` (``ControllerSettings``),
``result`` (``ControlResult``, ``SequenceResult``, ``NoiseComparison``, the ``Controller``
protocol), ``ipopt``, ``redundant`` (the redundant set and its seeding grid), ``base`` (state
parsing and range checks), ``surface`` (the EAFM-mean surface: Newton projection, seeds,
reachable interval), ``baseline`` (the AFM controller, ``compare_noise``), ``controller`` (the
EAFM controllers; re-exports the names above that other packages use), ``sequence`` and
``oracle``.
"""
