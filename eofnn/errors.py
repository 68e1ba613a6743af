"""Errors and warnings that reach the user as one clear line."""

from __future__ import annotations


class ConfigError(ValueError):
    """A configuration value is invalid; the message names the value and what is allowed."""


class OutputExistsError(ConfigError):
    """An output path exists and ``overwrite`` was not asked for: nothing a user wrote is replaced unasked."""


class OutputError(RuntimeError):
    """An output cannot be written (its disk is full); the message names the path and the space left, and says that
    nothing was written."""


class OutputBusyError(OutputError):
    """Another eofnn process is writing the same output (it holds the lock beside it)."""


class CheckpointError(ValueError):
    """A checkpoint is missing, unreadable, names code that is not allowed, or does not fit its set-up."""


class TelemetryError(ValueError):
    """A telemetry file is missing arrays, has wrong shapes or holds non-finite values."""


class DivergedError(RuntimeError):
    """A loop that had to stay stable (recording training data) diverged; the message names where."""


class CollinearityWarning(UserWarning):
    """The regressors are (near-)collinear: the fitted filter is decided by the regularisation, not the data."""


class ShiftWarning(UserWarning):
    """A predictor is used in conditions (WFS noise, DM gain, wind) other than those it was trained in."""


def require(condition: bool, message: str) -> None:
    """Raise :class:`ConfigError` with ``message`` unless ``condition`` holds."""
    if not condition:
        raise ConfigError(message)
