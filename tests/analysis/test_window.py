"""Times as people write them, to integer UTC ns; windows that make sense or one-line errors."""

from __future__ import annotations

import datetime as dt

import numpy as np
import pandas as pd
import pytest

from fleetdaq.analysis.errors import BadWindow
from fleetdaq.analysis.window import format_ns, parse_time, resolve_window

T = 1_795_000_000_123_456_789  # 2026-11-18T11:06:40.123456789Z
ORIGIN = 1_795_000_000_000_000_000


@pytest.mark.parametrize(
    "value",
    [
        T,
        np.int64(T),
        "2026-11-18T11:06:40.123456789Z",
        "2026-11-18 11:06:40.123456789",
        "2026-11-18T12:06:40.123456789+01:00",
        "2026-11-18T06:06:40.123456789-0500",
        np.datetime64(T, "ns"),
        pd.Timestamp(T, unit="ns", tz="UTC"),
        pd.Timestamp(T, unit="ns"),
        "+123456789ns",
        "+0.123456789s",
    ],
)
def test_every_way_of_writing_a_time_gives_the_same_ns(value: object):
    assert parse_time(value, ORIGIN) == T


def test_datetimes_naive_are_utc_and_aware_are_converted():
    aware = dt.datetime(2026, 11, 18, 12, 6, 40, 123456, tzinfo=dt.timezone(dt.timedelta(hours=1)))
    naive = dt.datetime(2026, 11, 18, 11, 6, 40, 123456)
    assert parse_time(aware) == parse_time(naive) == T - 789


def test_relative_times_and_session_folder_names():
    assert parse_time("+5min", ORIGIN) == ORIGIN + 300 * 10**9
    assert parse_time("+1.5h", ORIGIN) == ORIGIN + 5400 * 10**9
    assert parse_time("+250ms", ORIGIN) == ORIGIN + 250_000_000
    assert parse_time("2026-11-18T11-06-40Z") == ORIGIN
    assert parse_time("2026-11-18") == ORIGIN - (11 * 3600 + 6 * 60 + 40) * 10**9


@pytest.mark.parametrize(
    ("value", "says"),
    [
        ("+90", "is not a time"),
        ("tomorrow", "is not a time"),
        ("2026-02-30T00:00:00Z", "day is out of range"),
        (1.5, "ambiguous"),
        (True, "is not a time"),
        (None, "is not a time"),
        (np.datetime64("NaT"), "NaT"),
    ],
)
def test_what_is_not_a_time_says_so(value: object, says: str):
    with pytest.raises(BadWindow, match=says):
        parse_time(value, ORIGIN)


def test_a_relative_time_needs_a_start():
    with pytest.raises(BadWindow, match="needs one"):
        parse_time("+5s")


def test_windows_are_ordered_and_open_ended():
    assert resolve_window(None, None) == (None, None)
    assert resolve_window("+1s", None, ORIGIN) == (ORIGIN + 10**9, None)
    with pytest.raises(BadWindow, match="empty window: start 2026-11-18T11:06:41"):
        resolve_window("+1s", "+1s", ORIGIN)
    assert format_ns(T) == "2026-11-18T11:06:40.123456789Z"
