"""Small shared helpers with no knowledge of stages or models: settings fields, JSON/CSV I/O,
progress lines, BLAS threads, statistics.
"""
