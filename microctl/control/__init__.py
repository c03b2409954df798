"""Controllers on a forward model: objectives, the optimal (IPOPT) controller and its baselines,
the sequence controller, and the oracle that knows the simulator's truth.
"""
