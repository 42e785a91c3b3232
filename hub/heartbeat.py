"""The hub's heartbeat: `HubHeartbeat` on ``fleetdaq/<site>/hub/heartbeat`` about once a second.

Edges watch it (on their monotonic clock) to know the hub is there; an edge that stops
hearing it puts its outputs to their safe values.
"""

from __future__ import annotations

import logging
import threading
import time
from typing import Any

from edge import __version__
from edge.cdr import encode
from edge.keys import SiteKeys
from edge.messages import HubHeartbeat
from edge.threads import NamedThread
from hub.router import Router

log = logging.getLogger("fleetdaq.hub")


class Heartbeat:
    name = "heartbeat"

    def __init__(self, router: Router, keys: SiteKeys, session: Any, period_s: float = 1.0) -> None:
        """`session()` returns the recording session's name (it can change while running)."""
        self.router = router
        self.key = keys.hub("heartbeat")
        self.session = session
        self.period_s = period_s
        self.beats = 0
        self._stop = threading.Event()
        self._thread = NamedThread(target=self._run, name="heartbeat", daemon=True)
        self._pub: Any = None
        self._died: str | None = None

    def start(self) -> None:
        self._pub = self.router.session.declare_publisher(self.key)
        self._thread.start()

    def _run(self) -> None:
        try:
            while not self._stop.wait(self.period_s):
                self.beats += 1
                beat = HubHeartbeat(time.time_ns(), __version__, str(self.session()), self.beats)
                self._pub.put(encode(beat))
        except Exception as err:
            self._died = f"the heartbeat thread died: {err!r}"
            log.critical("%s", self._died, exc_info=True)

    def stop(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(5.0)
        if self._pub is not None:
            self._pub.undeclare()
            self._pub = None

    def failure(self) -> str | None:
        return self._died
