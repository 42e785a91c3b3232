"""Errors of the fleet package (one tree). Every message is one line a person can act on."""

from __future__ import annotations

from enum import Enum


class FleetError(Exception):
    """Base of every error the fleet package raises on purpose."""


class InventoryError(FleetError):
    """The inventory is unreadable or invalid: ``file: key.path: problem``."""


class Unreachable(Enum):
    """Why a host could not be reached or logged into, in the words an operator uses."""

    DNS = "dns"
    REFUSED = "refused"
    TIMEOUT = "timeout"
    NO_ROUTE = "no route"
    AUTH = "auth failed"
    HOST_KEY_UNKNOWN = "host key unknown"
    HOST_KEY_CHANGED = "host key changed"
    HOST_KEY_REVOKED = "host key revoked"
    SSH = "ssh error"


class SshError(FleetError):
    """A host could not be reached over SSH; `kind` says why, the message says it plainly
    (and what to do where there is something to do)."""

    def __init__(self, kind: Unreachable, message: str) -> None:
        super().__init__(message)
        self.kind = kind


class CommandTimeout(FleetError):
    """A command on a host did not finish within the host's time budget."""
