"""Times and time windows as people give them, turned into integer UTC nanoseconds.

A time is an int (ns since the epoch, UTC), a `datetime` (naive ones are taken as UTC, like
everything in a recording), a `numpy.datetime64`, a pandas `Timestamp`, or text: ISO 8601
(``2026-11-21T05:04:06.25Z``, an offset such as ``+02:00``, no zone = UTC; a session folder's
name ``2026-11-21T05-04-06Z`` works too) or an offset from the start of the recording
(``+90s``, ``+5min``, ``+1.5h``). A window is half-open: ``start <= t < end``.
"""

from __future__ import annotations

import calendar
import datetime as dt
import re
from typing import Final

import numpy as np

from fleetdaq.analysis.errors import BadWindow

TimeLike = int | np.integer | str | dt.datetime | np.datetime64
"""What `start` / `end` accept (see the module's docstring)."""

_UNITS: Final = {
    "ns": 1,
    "us": 1_000,
    "µs": 1_000,
    "ms": 1_000_000,
    "s": 1_000_000_000,
    "min": 60_000_000_000,
    "m": 60_000_000_000,
    "h": 3_600_000_000_000,
    "d": 86_400_000_000_000,
}
_RELATIVE = re.compile(r"^\+\s*(\d+(?:\.\d+)?)\s*(ns|us|µs|ms|s|min|m|h|d)$")
_ISO = re.compile(
    r"^(\d{4})-(\d{2})-(\d{2})"
    r"(?:[T ](\d{2})[:-](\d{2})(?:[:-](\d{2})(?:[.,](\d{1,9}))?)?)?"
    r"\s*(Z|[+-]\d{2}:?\d{2})?$"
)


def parse_time(value: object, origin_ns: int | None = None) -> int:
    """`value` as integer UTC ns. `origin_ns` is what ``+90s`` counts from (the recording's
    start); without one a relative time is an error.

    Raises:
        BadWindow: a value that is not a time.
    """
    if isinstance(value, bool):
        raise BadWindow(f"{value!r} is not a time")
    if isinstance(value, int | np.integer):
        return int(value)
    if isinstance(value, np.datetime64):
        if np.isnat(value):
            raise BadWindow("NaT is not a time")
        return int(value.astype("datetime64[ns]").astype(np.int64))
    if isinstance(value, dt.datetime):
        return _from_datetime(value)
    if isinstance(value, str):
        return _from_text(value.strip(), origin_ns)
    if isinstance(value, float):
        raise BadWindow(
            f"{value!r}: give a time as integer ns, ISO 8601 text, a datetime or '+90s'"
            " (a float is ambiguous)"
        )
    raise BadWindow(f"{value!r} ({type(value).__name__}) is not a time")


def _from_datetime(t: dt.datetime) -> int:
    nanos = int(getattr(t, "nanosecond", 0))  # pandas Timestamp keeps ns beyond datetime's µs
    utc = t.replace(tzinfo=dt.UTC) if t.tzinfo is None else t.astimezone(dt.UTC)
    seconds = calendar.timegm(utc.utctimetuple())
    return seconds * 1_000_000_000 + utc.microsecond * 1_000 + nanos


def _from_text(text: str, origin_ns: int | None) -> int:
    rel = _RELATIVE.match(text)
    if rel:
        if origin_ns is None:
            raise BadWindow(f"{text!r}: a time relative to the recording's start needs one")
        amount, unit = rel.groups()
        return origin_ns + round(float(amount) * _UNITS[unit])
    m = _ISO.match(text)
    if not m:
        raise BadWindow(
            f"{text!r} is not a time (ISO 8601 such as 2026-11-21T05:04:06Z, or +90s / +5min"
            " from the start of the recording)"
        )
    year, month, day, hour, minute, second, frac, zone = m.groups()
    try:
        t = dt.datetime(
            int(year),
            int(month),
            int(day),
            int(hour or 0),
            int(minute or 0),
            int(second or 0),
            tzinfo=dt.UTC,
        )
    except ValueError as err:
        raise BadWindow(f"{text!r}: {err}") from None
    ns = calendar.timegm(t.utctimetuple()) * 1_000_000_000
    if frac:
        ns += int(frac.ljust(9, "0"))
    if zone and zone != "Z":
        sign = 1 if zone[0] == "+" else -1
        digits = zone[1:].replace(":", "")
        ns -= sign * (int(digits[:2]) * 3600 + int(digits[2:]) * 60) * 1_000_000_000
    return ns


def resolve_window(
    start: TimeLike | None, end: TimeLike | None, origin_ns: int | None = None
) -> tuple[int | None, int | None]:
    """(start_ns, end_ns), each None when not given.

    Raises:
        BadWindow: a bad time, or start not before end.
    """
    a = None if start is None else parse_time(start, origin_ns)
    b = None if end is None else parse_time(end, origin_ns)
    if a is not None and b is not None and a >= b:
        raise BadWindow(f"empty window: start {format_ns(a)} is not before end {format_ns(b)}")
    return a, b


def format_ns(t_ns: int) -> str:
    """ISO 8601 UTC with nanoseconds: ``2026-11-21T05:04:06.123456789Z``."""
    seconds, nanos = divmod(int(t_ns), 1_000_000_000)
    t = dt.datetime.fromtimestamp(seconds, tz=dt.UTC)
    return t.strftime("%Y-%m-%dT%H:%M:%S") + f".{nanos:09d}Z"


def in_window(t_ns: int, start: int | None, end: int | None) -> bool:
    return (start is None or t_ns >= start) and (end is None or t_ns < end)
