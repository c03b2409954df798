"""The package's exception hierarchy.

Every error a user can cause (a bad YAML field, a malformed CSV row, an unreachable
target) derives from :class:`MicroctlError`; the command line turns the input errors
(:class:`ConfigError`, :class:`DataError`) into one line on stderr and exit status 2.
"""

from __future__ import annotations


class MicroctlError(Exception):
    """Base class of every error raised on purpose by microctl."""


class ConfigError(MicroctlError, ValueError):
    """A configuration file or value is invalid.

    The message names the file and the field path (``stage.actuators[2].normal``) and
    says what would be valid.
    """


class DataError(MicroctlError, ValueError):
    """A data file (measurement log, table, model file) is invalid.

    The message names the file and, where it applies, the row and column.
    """


class BackendError(MicroctlError):
    """The stage backend refused a move or a device misbehaved."""


class SolveError(MicroctlError):
    """The controller could not produce a valid control signal."""


class UnreachableTargetError(SolveError, ValueError):
    """The target tool pose lies outside what the stage can reach from the given state.

    The message gives the reachable interval; the CLI treats it as an input error (exit 2).
    """


#: Errors that are the user's input's fault: the CLI exits with status 2 for these.
INPUT_ERRORS = (ConfigError, DataError, UnreachableTargetError)
