"""events.log: every event, one line each, in a size-limited text file (like MODAQ 2's supervisor
log: rotated at `max_bytes`, `backups` old files kept), also to Python logging, and the latest
ones and the counts per level in the read model. A subscriber of the event bus.

Events a node spooled are acked only once their line is in events.log and fsynced
(`fleetdaq.hub.nodes.event_delivery`): the event log says what it wrote and lends its fsync."""

from __future__ import annotations

import datetime as dt
import logging
import logging.handlers
import os
import sys
from collections import deque
from pathlib import Path

from fleetdaq.contract.messages import Event
from fleetdaq.hub.bus import EventBus, worth_telling, writable
from fleetdaq.hub.nodes.event_delivery import EventDelivery
from fleetdaq.hub.read_model import EVENT_COUNTS, RECENT_EVENTS, ReadModel

log = logging.getLogger("fleetdaq.events")


def format_event(e: Event) -> str:
    when = dt.datetime.fromtimestamp(e.time_ns / 1e9, tz=dt.UTC).isoformat(timespec="milliseconds")
    tag = f" [{e.tag}]" if e.tag else ""
    return f"{when} {e.level_name.upper():8} {e.node}/{e.source}{tag}: {e.message}"


class _QuietRotatingFile(logging.handlers.RotatingFileHandler):
    """A size-limited file that counts write failures (a full disk) instead of printing a
    traceback for every event."""

    write_failures = 0
    last_error = ""

    def handleError(self, record: logging.LogRecord) -> None:
        self.write_failures += 1
        self.last_error = str(sys.exc_info()[1])
        n = self.write_failures
        if worth_telling(n):
            log.error("events.log cannot be written: %s (%d so far)", self.last_error, n)


class EventLog:
    name = "event-log"

    def __init__(
        self,
        path: Path,
        bus: EventBus,
        model: ReadModel,
        max_bytes: int = 10_000_000,
        backups: int = 5,
        tail: int = 200,
        delivery: EventDelivery | None = None,
    ) -> None:
        """`delivery`: told which events are written (it acks the nodes' spooled events only
        once they are); it fsyncs through `sync`."""
        self.path = path
        self.max_bytes = max_bytes
        self.backups = backups
        self.model = model
        self.recent: deque[Event] = deque(maxlen=tail)
        self.counts: dict[str, int] = {}
        self._file: _QuietRotatingFile | None = None
        self.delivery = delivery
        self._sub = bus.subscribe(self.name, self._on_event)

    def start(self) -> None:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        # backslashreplace: a line holding text no encoder writes (a lone surrogate) is kept,
        # escaped, instead of being lost as a write failure.
        self._file = _QuietRotatingFile(
            self.path,
            maxBytes=self.max_bytes,
            backupCount=self.backups,
            encoding="utf-8",
            errors="backslashreplace",
        )
        self._file.setFormatter(logging.Formatter("%(message)s"))

    def sync(self) -> bool:
        """fsync events.log (the current file; a rotated one was closed whole). False if the
        file is not open or the fsync failed."""
        f = self._file
        if f is None:
            return False
        with f.lock:  # type: ignore[union-attr]  # emit and rotation hold it too
            stream = f.stream
            if stream is None:
                return False
            try:
                os.fsync(stream.fileno())
            except (OSError, ValueError) as err:
                f.handleError(logging.makeLogRecord({"msg": f"fsync: {err}"}))
                return False
        return True

    def _on_event(self, e: Event) -> None:
        line = writable(format_event(e))  # and so the hub's own log (any handler) takes it
        if self._file is not None:
            failures = self._file.write_failures
            self._file.emit(logging.makeLogRecord({"msg": line, "levelno": e.level}))
            if self.delivery is not None and self._file.write_failures == failures:
                self.delivery.logged(e)
        log.log(e.level, "%s", line)
        self.recent.append(e)
        self.counts[e.level_name] = self.counts.get(e.level_name, 0) + 1
        self.model.put(RECENT_EVENTS, tuple(self.recent))
        self.model.put(EVENT_COUNTS, dict(self.counts))

    def stop(self) -> None:
        self._sub.stop()
        if self._file is not None:
            self._file.close()
            self._file = None

    def failure(self) -> str | None:
        return None if self._sub.alive or self._file is None else "its bus thread died"
