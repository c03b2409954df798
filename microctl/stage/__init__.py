"""The stage as a physical object: geometry (paper Table I), the cause vocabulary (model
corrections and simulator defects), the gauge, the kinematic matrices (eq. 5-13), the elastic
contact physics, and the YAML reader that builds them. Imports only :mod:`microctl.util`
and :mod:`microctl.errors`.
"""
