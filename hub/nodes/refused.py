"""Traffic on keys the site file does not define: refused where it arrives, counted per key
(bounded), raised as an event (once a minute per key at most), in the read model."""

from __future__ import annotations

import logging
import threading
import time

from fleetdaq.hub.bus import EventBus
from fleetdaq.hub.read_model import REFUSED_KEYS, REFUSED_TOTAL, ReadModel

_MAX_KEYS = 256
_REPORT_EVERY_S = 60.0
_VIEW_EVERY_S = 0.5


class RefusedKeys:
    def __init__(self, bus: EventBus, model: ReadModel) -> None:
        self.bus = bus
        self.model = model
        self.counts: dict[str, int] = {}
        self.total = 0
        self._reported: dict[str, float] = {}
        self._last_view = 0.0
        self._lock = threading.Lock()

    def refuse(
        self, key: str, what: str, why: str = "the site file defines no such node or stream"
    ) -> None:
        """Count one refused message on `key` (called on Zenoh's threads: cheap, never blocks)."""
        now = time.monotonic()
        with self._lock:
            self.total += 1
            slot = key if key in self.counts or len(self.counts) < _MAX_KEYS else "(other keys)"
            n = self.counts.get(slot, 0) + 1
            self.counts[slot] = n
            last = self._reported.get(slot)
            report = last is None or now - last >= _REPORT_EVERY_S
            if report:
                self._reported[slot] = now
            view = now - self._last_view >= _VIEW_EVERY_S
            if view:
                self._last_view = now
                counts, total = tuple(sorted(self.counts.items())), self.total
        if view:
            self.model.put(REFUSED_KEYS, counts)
            self.model.put(REFUSED_TOTAL, total)
        if report:
            self.bus.emit(
                logging.WARNING,
                "hub",
                "refused_key",
                f"refused {what} on {slot}: {why} ({n} refused on it so far; none of it is "
                "recorded)",
                key=slot,
                count=n,
            )

    def publish(self) -> None:
        with self._lock:
            counts, total = tuple(sorted(self.counts.items())), self.total
        self.model.put(REFUSED_KEYS, counts)
        self.model.put(REFUSED_TOTAL, total)
