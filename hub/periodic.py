"""The worker of a hub service that does one thing every `period_s` in a thread of its own.

A tick that raises ends the thread, and from then on the service's `failure()` says so (the
hub's supervision of its services reports it loudly; never a healthy-looking process with a
dead worker).
"""

from __future__ import annotations

import logging
import threading

from fleetdaq.runtime.threads import NamedThread

log = logging.getLogger("fleetdaq.hub")


class Periodic:
    """Subclasses define `tick()` and call `start_ticking()` from their `start()`."""

    def __init__(self, thread_name: str, period_s: float) -> None:
        self.period_s = period_s
        self._stop = threading.Event()
        self._thread = NamedThread(target=self._run, name=thread_name, daemon=True)
        self._died: str | None = None
        self._at_once = False

    def tick(self) -> None:
        raise NotImplementedError

    def start_ticking(self, at_once: bool = False) -> None:
        """The first tick comes `period_s` from now (`at_once`: now, in the thread)."""
        self._at_once = at_once
        self._thread.start()

    def _run(self) -> None:
        try:
            if self._at_once:
                self.tick()
            while not self._stop.wait(self.period_s):
                self.tick()
        except Exception as err:
            self._died = f"the {self._thread.name} thread died: {err!r}"
            log.critical("%s", self._died, exc_info=True)

    def stop(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(5.0)

    def failure(self) -> str | None:
        return self._died
