"""The dead-man: is the hub there? Its heartbeat (`HubHeartbeat`, ~1 Hz on
``fleetdaq/<site>/hub/heartbeat``) is watched on the monotonic clock, so a step of the wall
clock can neither trip nor hide it.

States: ``waiting`` (started, no heartbeat yet), ``present``, ``lost`` (none for
`safe_after_s`). The edge is in its safe state while waiting or lost. `on_lost` is called once
when the heartbeat has been missing for `safe_after_s`, `on_back` at the first heartbeat after
waiting or lost; both are called under the watch's lock, in order, and must return at once
(they post work to the output service).

A payload that is not a HubHeartbeat is refused and counted (`junk`); it neither proves the hub
alive nor changes anything. (A well-formed heartbeat forged by a peer on the site network is
indistinguishable from the hub's without the security layer.)
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from enum import StrEnum

from fleetdaq.contract.cdr import decode
from fleetdaq.contract.errors import WireError
from fleetdaq.contract.messages import HubHeartbeat
from fleetdaq.runtime.threads import NamedThread


class HubState(StrEnum):
    """Whether the hub's heartbeat is heard (see the module's docstring)."""

    WAITING = "waiting"
    PRESENT = "present"
    LOST = "lost"


class HubWatch:
    """Watches the hub's heartbeat; a thread of its own checks for its absence."""

    def __init__(
        self,
        safe_after_s: float,
        on_lost: Callable[[float], None],
        on_back: Callable[[HubHeartbeat], None],
        monotonic: Callable[[], float] = time.monotonic,
        check_every_s: float = 0.05,
    ) -> None:
        self.safe_after_s = safe_after_s
        self._on_lost = on_lost
        self._on_back = on_back
        self._monotonic = monotonic
        self._every = check_every_s
        self._lock = threading.Lock()
        self.state = HubState.WAITING
        self.last_beat_s: float | None = None
        self.beats = 0
        self.junk = 0
        self.last: HubHeartbeat | None = None
        self._stop = threading.Event()
        self._thread = NamedThread(target=self._run, name="hub-watch", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def close(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(5.0)

    def heard(self, payload: bytes) -> bool:
        """A payload arrived on the heartbeat key; True when it was a heartbeat."""
        try:
            beat = decode(payload, HubHeartbeat)
        except WireError:
            with self._lock:
                self.junk += 1
            return False
        with self._lock:  # callbacks under the lock: a lost and a back never swap places
            self.beats += 1
            self.last = beat
            self.last_beat_s = self._monotonic()
            if self.state is not HubState.PRESENT:
                self.state = HubState.PRESENT
                self._on_back(beat)
        return True

    def check(self) -> None:
        """Go to `lost` (calling on_lost) if the last heartbeat is `safe_after_s` old."""
        with self._lock:
            if self.state is not HubState.PRESENT or self.last_beat_s is None:
                return
            missing = self._monotonic() - self.last_beat_s
            if missing < self.safe_after_s:
                return
            self.state = HubState.LOST
            self._on_lost(missing)

    @property
    def hub_present(self) -> bool:
        return self.state is HubState.PRESENT

    def _run(self) -> None:
        while not self._stop.wait(self._every):
            self.check()
