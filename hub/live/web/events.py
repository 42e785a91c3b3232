"""The dashboard's event tail: the last events from the bus (every node's and the hub's), each
with a sequence number so the page can ask for what is new, and filters (level, node, source,
text) for the events panel."""

from __future__ import annotations

import logging
import threading
from collections import deque
from dataclasses import dataclass
from typing import TypedDict

from fleetdaq.contract.messages import Event
from fleetdaq.hub.bus import EventBus

LEVELS = {
    "debug": logging.DEBUG,
    "info": logging.INFO,
    "warning": logging.WARNING,
    "error": logging.ERROR,
    "critical": logging.CRITICAL,
}


class EventJson(TypedDict):
    """One event as the page gets it: the bus's `Event`, numbered in arrival order."""

    seq: int
    time_ns: int
    node: str
    level: int
    level_name: str
    source: str
    tag: str
    message: str
    fields: dict[str, str]


@dataclass(frozen=True, slots=True)
class EventFilter:
    min_level: int = 0
    node: str = ""
    source: str = ""
    text: str = ""
    """Case-insensitive, in the message or the tag."""

    def matches(self, e: EventJson) -> bool:
        if e["level"] < self.min_level:
            return False
        if self.node and e["node"] != self.node:
            return False
        if self.source and e["source"] != self.source:
            return False
        if self.text:
            needle = self.text.lower()
            return needle in e["message"].lower() or needle in e["tag"].lower()
        return True


def event_json(seq: int, e: Event) -> EventJson:
    return {
        "seq": seq,
        "time_ns": e.time_ns,
        "node": e.node,
        "level": e.level,
        "level_name": e.level_name,
        "source": e.source,
        "tag": e.tag,
        "message": e.message,
        "fields": {kv.key: kv.value for kv in e.fields},
    }


class EventTail:
    """Subscribed to the bus at construction (so it sees the hub's first events)."""

    def __init__(self, bus: EventBus, keep: int = 2000) -> None:
        self._events: deque[EventJson] = deque(maxlen=keep)
        self._lock = threading.Lock()
        self._seq = 0
        self._sub = bus.subscribe("dashboard", self._on_event)

    def _on_event(self, e: Event) -> None:
        with self._lock:
            self._seq += 1
            self._events.append(event_json(self._seq, e))

    @property
    def last_seq(self) -> int:
        return self._seq

    def since(self, seq: int, limit: int = 1000) -> list[EventJson]:
        """Events after `seq`, oldest first, at most the last `limit` of them."""
        new: list[EventJson] = []
        with self._lock:
            for e in reversed(self._events):
                if e["seq"] <= seq or len(new) >= limit:
                    break
                new.append(e)
        new.reverse()
        return new

    def query(self, f: EventFilter, limit: int = 200) -> list[EventJson]:
        """The last `limit` events that pass `f`, oldest first."""
        with self._lock:
            events = list(self._events)
        out = [e for e in reversed(events) if f.matches(e)][:limit]
        out.reverse()
        return out

    def alive(self) -> bool:
        return self._sub.alive
