"""The one error tree of the `ptp` package."""

from __future__ import annotations


class PtpError(Exception):
    """Every error the time-sync status code raises."""


class ManagementError(PtpError):
    """ptp4l's management interface did not answer, or answered with an error."""


class ManagementTimeout(ManagementError):
    """No (complete) answer from ptp4l within the timeout."""


class ParseError(PtpError):
    """Text or bytes that are not what linuxptp or chrony print / send."""


class ChronyError(PtpError):
    """chronyc is missing, failed, or chronyd did not answer."""
