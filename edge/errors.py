"""Errors raised by the edge package (one tree; vendor errors are wrapped with `from`)."""

from __future__ import annotations


class EdgeError(Exception):
    """Base of every error the edge package raises on purpose."""


class ConfigError(EdgeError):
    """A site file is unreadable or invalid. The message is one line: file, key path, problem."""


class WireError(EdgeError):
    """A payload on a fleetdaq key is not a valid message (truncated, lying lengths, ...)."""


class DriverError(EdgeError):
    """A driver could not be loaded, opened or read."""


class DriverUnavailable(DriverError):
    """A driver's vendor library is not installed on this machine."""
