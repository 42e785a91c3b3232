"""Plain-text figures for the terminal (the CLI's tables, `fleetdaq fleet status`): times,
sizes, durations, aligned columns. No dependencies: an operator's laptop with the base install
prints them."""

from __future__ import annotations

import datetime as dt
from collections.abc import Sequence


def when_text(ns: int) -> str:
    """A wall-clock time in ns as ``2026-11-24 03:12:40Z`` ("-" for none)."""
    if not ns:
        return "-"
    try:
        return dt.datetime.fromtimestamp(ns / 1e9, tz=dt.UTC).strftime("%Y-%m-%d %H:%M:%SZ")
    except (OverflowError, ValueError, OSError):  # a time no calendar holds
        return "?"


def size_text(n: int | None) -> str:
    """Bytes as ``812 B``, ``12.3 MB`` ("-" for none)."""
    if n is None:
        return "-"
    x = float(n)
    for unit in ("B", "kB", "MB", "GB", "TB"):
        if x < 1000 or unit == "TB":
            return f"{x:.0f} {unit}" if unit == "B" else f"{x:.1f} {unit}"
        x /= 1000
    raise AssertionError("unreachable")


def duration_text(seconds: float | None) -> str:
    """Seconds as ``2d 3h``, ``1h 02m``, ``4m 05s`` ("-" for none)."""
    if seconds is None:
        return "-"
    s = int(seconds)
    days, s = divmod(s, 86400)
    hours, s = divmod(s, 3600)
    minutes, s = divmod(s, 60)
    if days:
        return f"{days}d {hours}h"
    if hours:
        return f"{hours}h {minutes:02d}m"
    return f"{minutes}m {s:02d}s"


def text_table(rows: Sequence[Sequence[str]], right: frozenset[int] = frozenset()) -> list[str]:
    """Rows (the first the header) as aligned lines, two spaces apart; the columns in `right`
    right-aligned (numbers)."""
    widths = [max(len(row[k]) for row in rows) for k in range(len(rows[0]))]
    return [
        "  ".join(
            c.rjust(w) if k in right else c.ljust(w)
            for k, (c, w) in enumerate(zip(row, widths, strict=True))
        ).rstrip()
        for row in rows
    ]
