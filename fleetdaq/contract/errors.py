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


class DeviceError(DriverError):
    """A device, its bus or its vendor library reported an error.

    `code` keeps the vendor's code (an LJM error code, an errno) when there is one; the vendor
    exception itself is the ``__cause__``."""

    def __init__(self, message: str, code: int | None = None) -> None:
        super().__init__(message)
        self.code = code


class DeviceNotFound(DeviceError):
    """The device (or its bus) is not there: not plugged in, wrong address, bus not enabled."""


class DeviceDisconnected(DeviceError):
    """The device went away while in use (unplugged, link lost): the agent reopens it."""
