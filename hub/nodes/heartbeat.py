"""The hub's heartbeat: `HubHeartbeat` on ``fleetdaq/<site>/hub/heartbeat`` about once a second.

Edges watch it (on their monotonic clock) to know the hub is there; an edge that stops
hearing it puts its outputs to their safe values.
"""

from __future__ import annotations

import time
from collections.abc import Callable

import zenoh

from fleetdaq import __version__
from fleetdaq.contract.cdr import encode
from fleetdaq.contract.keys import SiteKeys
from fleetdaq.contract.messages import HubHeartbeat
from fleetdaq.hub.periodic import Periodic
from fleetdaq.hub.routing.router import Router, undeclare


class Heartbeat(Periodic):
    name = "heartbeat"

    def __init__(
        self, router: Router, keys: SiteKeys, session: Callable[[], object], period_s: float = 1.0
    ) -> None:
        """`session()` returns the recording session's name (it can change while running)."""
        super().__init__("heartbeat", period_s)
        self.router = router
        self.key = keys.hub("heartbeat")
        self.session = session
        self.beats = 0
        self._pub: zenoh.Publisher | None = None

    def start(self) -> None:
        self._pub = self.router.session.declare_publisher(self.key)
        self.start_ticking()

    def tick(self) -> None:
        self.beats += 1
        beat = HubHeartbeat(time.time_ns(), __version__, str(self.session()), self.beats)
        if self._pub is not None:
            self._pub.put(encode(beat))

    def stop(self) -> None:
        super().stop()
        if self._pub is not None:
            undeclare(self._pub)
            self._pub = None
