"""Where the notifier reads the time and waits, so tests can drive an hour in a second.

Durations (digest windows, snoozes, rate limits, retry backoff) use `monotonic`; what must mean
the same after a restart (when a mail was queued, the Date: header) uses `time`.
"""

from __future__ import annotations

import threading
import time
from typing import Protocol


class Clock(Protocol):
    def monotonic(self) -> float:
        """Seconds, never going back (durations, deadlines)."""
        ...

    def time(self) -> float:
        """Seconds since the epoch (UTC)."""
        ...

    def wait(self, event: threading.Event, timeout: float) -> bool:
        """Wait until `event` is set or `timeout` seconds of this clock have passed; returns
        whether the event is set. A clock that can jump must wake its waiters when it does."""
        ...


class SystemClock:
    """The machine's clocks."""

    def monotonic(self) -> float:
        return time.monotonic()

    def time(self) -> float:
        return time.time()

    def wait(self, event: threading.Event, timeout: float) -> bool:
        return event.wait(max(0.0, timeout))


SYSTEM_CLOCK = SystemClock()
