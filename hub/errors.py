"""Errors raised by the hub package."""

from __future__ import annotations


class HubError(Exception):
    """Base of every error the hub raises on purpose."""


class RouterError(HubError):
    """The embedded Zenoh router could not start (e.g. the listen port is taken)."""


class SecretError(HubError):
    """A secret the site file points to (a password environment variable or file) is missing,
    unreadable, or readable by other users. The message is one line saying which and why."""


class NotifyError(HubError):
    """The e-mail notifier cannot start (its outbox directory, or the CA file it is told to
    trust); one line saying which and why."""
