"""Errors that reach the user as one clear line."""

from __future__ import annotations


class ConfigError(ValueError):
    """A configuration value is invalid; the message names the value and what is allowed."""


class CheckpointError(ValueError):
    """A checkpoint is missing, unreadable or does not fit the set-up it is loaded into."""


class TelemetryError(ValueError):
    """A telemetry file is missing arrays, has wrong shapes or holds non-finite values."""


def require(condition: bool, message: str) -> None:
    """Raise :class:`ConfigError` with ``message`` unless ``condition`` holds."""
    if not condition:
        raise ConfigError(message)


class DivergedError(RuntimeError):
    """A loop that had to stay stable (recording training data) diverged; the message names where."""
