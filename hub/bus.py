"""The hub's event bus: every event (from the nodes and from the hub's own services) reaches
every subscriber, each on its own thread, never on the thread that raised it.

`publish` never blocks: each subscription has a bounded queue, and an event that finds it full
is dropped *for that subscriber only*, counted, and raised as a ``bus_overflow`` event to the
others (at most once per `overflow_report_s` per subscriber, with the count). So a slow or
failing subscriber (an e-mail notifier waiting for a dead server, a dashboard) never delays the
recorder, its acks, or any other subscriber. A handler that raises is logged and counted; the
subscriber goes on with the next event."""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

from fleetdaq.contract.messages import Event, make_event
from fleetdaq.runtime.threads import NamedThread

log = logging.getLogger("fleetdaq.bus")

Handler = Callable[[Event], None]


def worth_telling(count: int, first: int = 1) -> bool:
    """Whether the `count`-th of a repeated problem (malformed payloads, failed writes) is said
    again, as an event or a log line: the first `first`, then every 1000th, each with the count
    so far. Enough to know it goes on; never a flood."""
    return count <= first or count % 1000 == 0


def writable(text: str) -> str:
    """`text` as UTF-8 can write it: a lone surrogate (which no encoder writes) becomes its
    ``\\udXXX`` escape. Requester text is refused before it gets here
    (`fleetdaq.contract.requester_text`); this is the last line of defence, so that a string that
    slipped through is still recorded, visibly, instead of stopping a log line or a record half
    way."""
    if text.isascii():
        return text
    try:
        text.encode("utf-8")
    except UnicodeEncodeError:
        return text.encode("utf-8", "backslashreplace").decode("utf-8")
    return text


@dataclass(frozen=True, slots=True)
class _Flush:
    """Set `done` once every event queued before it was handled."""

    done: threading.Event


class _Stop:
    """The subscriber's thread ends here."""


_STOP = _Stop()
_Item = Event | _Flush | _Stop


@dataclass(frozen=True, slots=True)
class SubscriberStats:
    name: str
    delivered: int
    dropped: int
    errors: int
    queued: int


class Subscription:
    """One subscriber's queue and thread."""

    def __init__(self, bus: EventBus, name: str, handler: Handler, maxsize: int) -> None:
        self.bus = bus
        self.name = name
        self.handler = handler
        self._queue: queue.Queue[_Item] = queue.Queue(maxsize)
        self._thread = NamedThread(target=self._run, name=f"bus-{name}", daemon=True)
        self.delivered = 0
        self.dropped = 0
        self.errors = 0
        self._unreported = 0
        self._last_report = 0.0

    def offer(self, item: Event) -> bool:
        try:
            self._queue.put_nowait(item)
            return True
        except queue.Full:
            self.dropped += 1
            self._unreported += 1
            return False

    def start(self) -> None:
        if not self._thread.is_alive():
            self._thread.start()

    def flush(self, timeout: float = 10.0) -> bool:
        """Wait until every event published before this call was handled (bounded)."""
        if not self._thread.is_alive():
            return self._queue.empty()
        done = threading.Event()
        deadline = time.monotonic() + timeout
        while True:
            try:
                self._queue.put(_Flush(done), timeout=0.1)
                break
            except queue.Full:
                if time.monotonic() > deadline:
                    return False
        return done.wait(max(0.0, deadline - time.monotonic()))

    def stop(self, timeout: float = 10.0) -> None:
        if self._thread.is_alive():
            self.flush(timeout)
            try:
                self._queue.put(_STOP, timeout=timeout)
            except queue.Full:
                log.error("bus subscriber %s is stuck; leaving it", self.name)
                return
            self._thread.join(timeout)

    @property
    def alive(self) -> bool:
        return self._thread.is_alive()

    def stats(self) -> SubscriberStats:
        return SubscriberStats(
            self.name, self.delivered, self.dropped, self.errors, self._queue.qsize()
        )

    def _run(self) -> None:
        while True:
            item = self._queue.get()
            if isinstance(item, _Stop):
                return
            if isinstance(item, _Flush):
                item.done.set()
                continue
            try:
                self.handler(item)
                self.delivered += 1
            except Exception:
                self.errors += 1
                if worth_telling(self.errors, first=10):
                    log.exception("bus subscriber %s failed on an event (%d so far)", self.name,
                                  self.errors)  # fmt: skip


class EventBus:
    """Publish from any thread; each subscriber gets every event on its own thread."""

    def __init__(self, node: str = "hub", overflow_report_s: float = 10.0) -> None:
        self.node = node
        self.overflow_report_s = overflow_report_s
        self._subs: list[Subscription] = []
        self._lock = threading.Lock()
        self._started = False
        self._stopping = False
        self.published = 0

    def subscribe(self, name: str, handler: Handler, maxsize: int = 10_000) -> Subscription:
        """Subscribe before `start` to see every event from the start."""
        sub = Subscription(self, name, handler, maxsize)
        with self._lock:
            self._subs.append(sub)
            started = self._started
        if started:
            sub.start()
        return sub

    def start(self) -> None:
        with self._lock:
            self._started = True
            subs = list(self._subs)
        for sub in subs:
            sub.start()

    def publish(self, event: Event) -> None:
        """Hand `event` to every subscriber's queue. Never blocks."""
        self.published += 1
        overflowed: list[Subscription] = []
        for sub in self._subs:
            if not sub.offer(event):
                overflowed.append(sub)
        now = time.monotonic()
        for sub in overflowed:
            if now - sub._last_report >= self.overflow_report_s:
                sub._last_report = now
                n, sub._unreported = sub._unreported, 0
                note = make_event(
                    time.time_ns(),
                    self.node,
                    logging.ERROR,
                    "bus",
                    "bus_overflow",
                    f"event subscriber {sub.name} is not keeping up: {n} event(s) dropped for "
                    f"it ({sub.dropped} in all); the other subscribers got them",
                    subscriber=sub.name,
                    dropped=n,
                )
                for other in self._subs:
                    if other is not sub:
                        other.offer(note)

    def emit(self, level: int, source: str, tag: str, message: str, /, **fields: object) -> None:
        """Raise a hub event. Its text is made writable first (`writable`), so that no
        subscriber (events.log, the recording, an e-mail) fails on it half way."""
        values = {k: writable(str(v)) for k, v in fields.items()}
        self.publish(
            make_event(time.time_ns(), self.node, level, source, tag, writable(message), **values)
        )

    def emit_counted(
        self, count: int, level: int, source: str, tag: str, message: str, /, **fields: object
    ) -> None:
        """The event of the `count`-th of a repeated problem (a payload refused, ...): raised
        for the first, then every 1000th (`worth_telling`), saying how many so far."""
        if worth_telling(count):
            self.emit(level, source, tag, f"{message}; {count} so far", count=count, **fields)

    def stop(self) -> None:
        """Deliver what is queued, then stop every subscriber thread. Idempotent."""
        with self._lock:
            self._stopping = True
            subs = list(self._subs)
        for sub in subs:
            sub.stop()

    def stats(self) -> list[SubscriberStats]:
        return [s.stats() for s in self._subs]

    def dead(self) -> list[str]:
        """Subscribers whose thread died (never expected: handlers' errors are caught)."""
        with self._lock:
            running = self._started and not self._stopping
        return [s.name for s in self._subs if running and not s.alive]
