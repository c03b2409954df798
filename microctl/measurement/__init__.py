"""What is measured and how it is recorded: the measurement log (contract:
``docs/measurement-log.md``) and the design of training moves.
"""
