"""An edge's system messages: `fleetdaq_msgs/msg/Event` on ``.../<node>/events``, and its log."""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from typing import Any

import zenoh

from edge.cdr import encode
from edge.messages import make_event

log = logging.getLogger("fleetdaq.edge")


class EventPublisher:
    """Publishes a node's events and logs them.

    Until the hub's subscription reaches this publisher a put would go nowhere, so events wait
    in a bounded queue and go out in order once it matches; any dropped from a full queue are
    counted and reported in an event of their own.
    """

    def __init__(self, session: Any | None, key: str, node: str, backlog: int = 1000) -> None:
        self._key = key
        self._pub: Any = None
        self._node = node
        self._pending: deque[bytes] = deque()
        self._backlog = backlog
        self.dropped = 0
        self._lock = threading.Lock()
        if session is not None:
            self.attach(session)

    def attach(self, session: Any) -> None:
        """Start publishing on `session` (events raised before wait in the bounded queue)."""
        self._pub = session.declare_publisher(
            self._key,
            congestion_control=zenoh.CongestionControl.BLOCK,
            reliability=zenoh.Reliability.RELIABLE,
        )
        self.flush()

    def emit(self, level: int, source: str, tag: str, message: str, /, **fields: object) -> None:
        """Raise an event; `fields` are what code reading it may react to (old/new values...)."""
        log.log(level, "%s [%s]: %s", source, tag, message)
        event = make_event(time.time_ns(), self._node, level, source, tag, message, **fields)
        with self._lock:
            if len(self._pending) >= self._backlog:
                self._pending.popleft()
                self.dropped += 1
            self._pending.append(encode(event))
        self.flush()

    def flush(self) -> None:
        """Publish what is waiting, if the hub listens."""
        pub = self._pub
        if pub is None or not pub.matching_status.matching:
            return
        with self._lock:
            pending, self._pending = self._pending, deque()
            dropped, self.dropped = self.dropped, 0
        if dropped:
            note = make_event(
                time.time_ns(),
                self._node,
                logging.WARNING,
                "agent",
                "events_dropped",
                f"{dropped} event(s) dropped while no hub was listening",
                dropped=dropped,
            )
            pending.appendleft(encode(note))
        for payload in pending:
            pub.put(payload)

    def close(self) -> None:
        self.flush()
        if self._pub is not None:
            self._pub.undeclare()
            self._pub = None
