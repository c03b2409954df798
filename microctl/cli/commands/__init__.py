"""Sub-commands of ``microctl``: one module per command group, each with ``register()``."""
