"""The analysis package's errors: bad input from a person, said in one line.

The CLI turns any `AnalysisError` into that line on stderr and exit code 2 (no traceback);
library users can catch the base class or the specific one.
"""

from __future__ import annotations


class AnalysisError(Exception):
    """Something the caller asked for cannot be done as asked (the message says what)."""


class NoRecording(AnalysisError):
    """The source names no readable recording (missing path, no MCAP files)."""


class UnknownStream(AnalysisError):
    """No such stream in the recording (the message lists the streams there are)."""


class UnknownChannel(AnalysisError):
    """No such channel in the stream (the message lists its channels)."""


class BadWindow(AnalysisError):
    """A time or a time window that cannot be understood, or an empty one."""


class DamagedRecording(AnalysisError):
    """A file could not be read (the message names it; `fleetdaq verify` says more)."""
