"""The hub's event log: every system message from every node and from the hub itself.

Events arrive as `fleetdaq_msgs/msg/Event` (CDR) on ``fleetdaq/<site>/*/events``. The
recorder's writer thread hands each one here after writing it into the session's ``/events``
topic. Here it goes to a size-limited text file (like MODAQ 2's supervisor log: rotated at
`max_bytes`, `backups` old files kept), to Python logging, and to an in-memory tail for the
live table and the dashboard. Alerts hang off `listeners`.
"""

from __future__ import annotations

import datetime as dt
import logging
import logging.handlers
import threading
from collections import deque
from collections.abc import Callable
from pathlib import Path

from edge.wire import Event

log = logging.getLogger("fleetdaq.events")


def format_event(e: Event) -> str:
    when = dt.datetime.fromtimestamp(e.time_ns / 1e9, tz=dt.UTC).isoformat(timespec="milliseconds")
    tag = f" [{e.tag}]" if e.tag else ""
    return f"{when} {e.level_name.upper():8} {e.node}/{e.source}{tag}: {e.message}"


class EventLog:
    """Size-limited text log + in-memory tail of events. Thread-safe; close() is idempotent."""

    def __init__(
        self, path: Path | None, max_bytes: int = 10_000_000, backups: int = 5, tail: int = 1000
    ) -> None:
        self.recent: deque[Event] = deque(maxlen=tail)
        self.counts: dict[int, int] = {}
        self.listeners: list[Callable[[Event], None]] = []
        self.lock = threading.Lock()
        self._file: logging.handlers.RotatingFileHandler | None = None
        if path is not None:
            path.parent.mkdir(parents=True, exist_ok=True)
            self._file = logging.handlers.RotatingFileHandler(
                path, maxBytes=max_bytes, backupCount=backups, encoding="utf-8"
            )
            self._file.setFormatter(logging.Formatter("%(message)s"))

    def add(self, e: Event) -> None:
        line = format_event(e)
        with self.lock:
            self.recent.append(e)
            self.counts[e.level] = self.counts.get(e.level, 0) + 1
            if self._file is not None:
                self._file.emit(logging.makeLogRecord({"msg": line, "levelno": e.level}))
        log.log(e.level, "%s", line)
        for listener in self.listeners:
            listener(e)

    def tail(self, n: int = 20) -> list[Event]:
        with self.lock:
            return list(self.recent)[-n:]

    def close(self) -> None:
        if self._file is not None:
            self._file.close()
            self._file = None
