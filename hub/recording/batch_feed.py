"""Accepted batches, as the recorder takes them (checked, new, in arrival order), to the services
that look at the data itself: the alarms, and later the live plots and the snapshot buffer.

The recorder's writer thread only puts a reference on each consumer's queue (the payload is
shared, never copied): `publish` never blocks. Each consumer has its own thread and a queue
bounded in bytes; a batch that does not fit is dropped for that consumer only and counted (the
consumer is told how many it missed with the next one it gets).
"""

from __future__ import annotations

import logging
import queue
import threading
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from fleetdaq.contract.wire import BatchHeader
from fleetdaq.hub.bus import worth_telling
from fleetdaq.runtime.threads import NamedThread

log = logging.getLogger("fleetdaq.feed")

_STOP = object()


@dataclass(frozen=True, slots=True)
class FedBatch:
    node: str
    stream: str
    header: BatchHeader
    payload: bytes
    recv_ns: int
    late: bool
    """Filled in by a replay after newer batches were already taken."""
    missed_before: int = 0
    """Batches this consumer did not get since the previous one (its queue was full)."""


Handler = Callable[[FedBatch], None]


class FeedConsumer:
    def __init__(self, name: str, handler: Handler, max_bytes: int) -> None:
        self.name = name
        self.handler = handler
        self.max_bytes = max_bytes
        self.queued_bytes = 0
        self.dropped = 0
        self.handled = 0
        self.errors = 0
        self._missed = 0
        self._lock = threading.Lock()
        self._queue: queue.SimpleQueue[Any] = queue.SimpleQueue()
        self._thread = NamedThread(target=self._run, name=f"feed-{name}", daemon=True)

    def offer(self, b: FedBatch) -> None:
        size = len(b.payload)
        with self._lock:
            if self.queued_bytes + size > self.max_bytes:
                self.dropped += 1
                self._missed += 1
                return
            self.queued_bytes += size
            missed, self._missed = self._missed, 0
        if missed:
            b = FedBatch(b.node, b.stream, b.header, b.payload, b.recv_ns, b.late, missed)
        self._queue.put(b)

    def _run(self) -> None:
        while True:
            b = self._queue.get()
            if b is _STOP:
                return
            with self._lock:
                self.queued_bytes -= len(b.payload)
            try:
                self.handler(b)
                self.handled += 1
            except Exception:
                self.errors += 1
                if worth_telling(self.errors, first=10):
                    log.exception("batch consumer %s failed (%d so far)", self.name, self.errors)

    @property
    def alive(self) -> bool:
        return self._thread.is_alive()

    def start(self) -> None:
        if not self._thread.is_alive():
            self._thread.start()

    def stop(self, timeout: float = 10.0) -> None:
        if self._thread.is_alive():
            self._queue.put(_STOP)
            self._thread.join(timeout)


class BatchFeed:
    def __init__(self) -> None:
        self.consumers: list[FeedConsumer] = []

    def subscribe(self, name: str, handler: Handler, max_bytes: int = 64 << 20) -> FeedConsumer:
        consumer = FeedConsumer(name, handler, max_bytes)
        self.consumers.append(consumer)
        return consumer

    def attach(self, consumer: FeedConsumer) -> None:
        """Also deliver to a consumer another feed made: the same queue and thread take both
        feeds' batches, in the order they come (a partition's streams to the main hub's
        alarms and rules, `fleetdaq.hub.partitions.live`)."""
        self.consumers.append(consumer)

    def publish(self, b: FedBatch) -> None:
        for c in self.consumers:
            c.offer(b)
