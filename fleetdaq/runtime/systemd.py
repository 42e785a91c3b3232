"""systemd's service protocol for the hub and the edge (`Type=notify`, `WatchdogSec=`).

- ``READY=1`` once the process does its job (the hub records, the edge acquires), a
  ``STATUS=`` line now and then (what `systemctl status` shows), ``STOPPING=1`` at a stop;
- ``WATCHDOG=1`` pings, sent only while **every registered work loop** has shown life
  recently (`Beat`): the recorder's writer, each acquisition loop, ... A loop that stalls
  stops the pings, and systemd restarts the process after `WatchdogSec`; the pinger thread
  being alive proves nothing by itself.

Without ``$NOTIFY_SOCKET`` (not under systemd) nothing is sent, but a stalled loop is still
logged. The protocol is one datagram on a Unix socket (sd_notify(3)); it is written here rather
than taken from a package: the pure-Python ones are unmaintained and lack the watchdog's
``$WATCHDOG_USEC``/``$WATCHDOG_PID`` handling, and python-systemd needs libsystemd headers to
build on every edge.
"""

from __future__ import annotations

import logging
import os
import socket
import threading
import time
from collections.abc import Callable

from fleetdaq.runtime.threads import NamedThread

log = logging.getLogger("fleetdaq.systemd")

DEFAULT_STALL_S = 15.0
"""Without a systemd watchdog, a loop quiet this long is reported as stalled."""


class Beat:
    """A work loop's sign of life: `beat()` each turn (an attribute store), `quiet(s)` before a
    wait it means to make (a back-off), so a deliberate wait is not a stall."""

    __slots__ = ("_until", "last", "name")

    def __init__(self, name: str) -> None:
        self.name = name
        self.last = time.monotonic()
        self._until = 0.0

    def beat(self) -> None:
        self.last = time.monotonic()

    def quiet(self, seconds: float) -> None:
        now = time.monotonic()
        self.last = now
        self._until = now + seconds

    def stalled_for(self, now: float) -> float:
        """Seconds since it last showed life beyond what it announced (0: fine)."""
        return max(0.0, now - max(self.last, self._until))


class Systemd:
    """The process's line to systemd (a no-op outside a ``Type=notify`` unit)."""

    def __init__(self, env: dict[str, str] | None = None) -> None:
        env = dict(os.environ) if env is None else env
        self.address = env.get("NOTIFY_SOCKET", "")
        usec = env.get("WATCHDOG_USEC", "")
        pid = env.get("WATCHDOG_PID", "")
        mine = not pid or pid == str(os.getpid())
        self.watchdog_s = int(usec) / 1e6 if usec.isdigit() and mine else 0.0
        self.beats: list[Beat] = []
        self.status_of: Callable[[], str] | None = None
        self.sent: list[str] = []
        """The last messages sent (kept short), for tests and `fleetdaq` diagnostics."""
        self.stalled: str | None = None
        self.ticks = 0
        """Watchdog periods gone by (each one a ping, or none when a loop stalled)."""
        self._sock: socket.socket | None = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    @property
    def active(self) -> bool:
        return bool(self.address)

    def send(self, *fields: str) -> None:
        if not self.address:
            return
        addr = self.address
        if addr.startswith("@"):  # an abstract socket
            addr = "\0" + addr[1:]
        try:
            if self._sock is None:
                self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC)
            self._sock.sendto("\n".join(fields).encode(), addr)
        except OSError as err:  # systemd gone or the socket refused: say so once, go on
            log.warning("cannot notify systemd at %s: %s", self.address, err)
            self.address = ""
            return
        self.sent = [*self.sent[-9:], *fields]

    def beat(self, name: str) -> Beat:
        """A new work loop to watch."""
        b = Beat(name)
        self.beats.append(b)
        return b

    def ready(self, status: str) -> None:
        self.send("READY=1", f"STATUS={status}")
        if self._thread is None:
            self._thread = NamedThread(target=self._run, name="systemd", daemon=True)
            self._thread.start()

    def stopping(self, status: str = "stopping") -> None:
        self._stop.set()
        if self._thread is not None:  # no ping or status of its may follow STOPPING
            self._thread.join(5.0)
        self.send("STOPPING=1", f"STATUS={status}")

    def check(self, now: float | None = None) -> str | None:
        """The first stalled loop and for how long, or None when every loop is alive."""
        now = time.monotonic() if now is None else now
        limit = self.watchdog_s / 2 if self.watchdog_s else DEFAULT_STALL_S
        for b in self.beats:
            quiet = b.stalled_for(now)
            if quiet > limit:
                return f"{b.name} has not moved for {quiet:.0f} s"
        return None

    def _run(self) -> None:
        period = self.watchdog_s / 3 if self.watchdog_s else 5.0
        last_status = 0.0
        while not self._stop.wait(period):
            self.ticks += 1
            stalled = self.check()
            if stalled is not None:
                if stalled != self.stalled:  # withhold the ping: systemd restarts us
                    log.critical("work loop stalled: %s; no watchdog ping (restart due)", stalled)
                    self.send(f"STATUS=stalled: {stalled}")
                self.stalled = stalled
                continue
            self.stalled = None
            fields = ["WATCHDOG=1"] if self.watchdog_s else []
            now = time.monotonic()
            if self.status_of is not None and now - last_status >= 10.0:
                last_status = now
                try:
                    fields.append(f"STATUS={self.status_of()}")
                except Exception:  # a status line must never cost the watchdog
                    log.exception("composing the systemd status line failed")
            if fields:
                self.send(*fields)
