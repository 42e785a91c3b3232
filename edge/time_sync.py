"""Time-sync monitoring: is the host clock (CLOCK_REALTIME) disciplined to the grandmaster?

Not to be confused with `fleetdaq.edge.device_time` (fitting a device's own clock to the host clock)
or `fleetdaq.edge.drivers.pacing.TimeSource` (where a driver reads the time, virtual in tests).

`make_time_sync_monitor` builds the monitor a node's config asks for. The agent reads `quality`
for every batch (cheap: a field read) and puts `message()` into node health; the monitor polls
its source (ptp4l over its management socket, or chronyc) on its own thread and calls
`emit(level, tag, message, **fields)` when the clock state or the grandmaster changes, or when
the checks' verdict does. A grandmaster change carries ``old`` and ``new`` as fields.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from typing import Protocol

from fleetdaq.contract.config.node import ClockConfig, NodeConfig
from fleetdaq.contract.messages import TimeSyncStatus
from fleetdaq.ptp.checks import Thresholds, defaults_for
from fleetdaq.ptp.quality import UNSYNCED, ClockQuality
from fleetdaq.ptp.reader import ChronyReader, Ptp4lReader, Reader
from fleetdaq.ptp.time_status import (
    GRANDMASTER_CHANGED,
    STATE_TAGS,
    Level,
    SyncState,
    TimeStatus,
    format_ns,
    grandmaster_change_message,
)
from fleetdaq.runtime.threads import NamedThread

log = logging.getLogger("fleetdaq.clock")

Emit = Callable[..., None]
"""emit(level, tag, message, **fields): raise an event from the time-sync monitor."""


class TimeSyncMonitor(Protocol):
    @property
    def quality(self) -> ClockQuality: ...

    def message(self) -> TimeSyncStatus:
        """The latest status, as node health carries it."""
        ...

    def start(self) -> None: ...

    def close(self) -> None:
        """Idempotent."""
        ...


class NoTimeSyncMonitor:
    """Nothing checks the clock: every batch says unsynced."""

    quality: ClockQuality = UNSYNCED

    def message(self) -> TimeSyncStatus:
        return TimeSyncStatus.unknown()

    def start(self) -> None:
        pass

    def close(self) -> None:
        pass


def thresholds(cfg: ClockConfig) -> Thresholds:
    """The config's thresholds, unset offset limits defaulted by timestamping (ns)."""
    base = defaults_for(cfg.timestamping == "hardware")
    warn = cfg.offset_warn_ns if cfg.offset_warn_ns is not None else base.offset_warn_ns
    fail = cfg.offset_fail_ns if cfg.offset_fail_ns is not None else base.offset_fail_ns
    s = 1_000_000_000
    return Thresholds(
        offset_warn_ns=warn,
        offset_fail_ns=max(warn, fail),
        last_sync_warn_ns=round(cfg.last_sync_warn_s * s),
        last_sync_fail_ns=round(cfg.last_sync_fail_s * s),
        path_delay_warn_ns=base.path_delay_warn_ns,
        path_delay_fail_ns=base.path_delay_fail_ns,
        holdover_ns=round(cfg.holdover_s * s),
    )


_STATE_LEVEL = {
    SyncState.LOCKED: logging.INFO,
    SyncState.HOLDOVER: logging.WARNING,
    SyncState.FREERUN: logging.ERROR,
}


class PollingTimeSyncMonitor:
    """Polls a `fleetdaq.ptp.reader` every `poll_s` on its own thread; `quality` and `message()` are
    the latest reading (start: UNSYNCED until the first reading)."""

    def __init__(self, reader: Reader, emit: Emit, poll_s: float = 0.5) -> None:
        self.reader = reader
        self.emit = emit
        self.poll_s = poll_s
        self.quality: ClockQuality = UNSYNCED
        self._status: TimeStatus | None = None
        self._last_gm = ""
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._lock = threading.Lock()

    def message(self) -> TimeSyncStatus:
        with self._lock:
            status = self._status
        if status is None:
            return TimeSyncStatus.unknown(self.reader.source)
        return TimeSyncStatus.of(status)

    @property
    def last(self) -> TimeStatus | None:
        return self._status

    def start(self) -> None:
        if self._thread is not None:
            return
        self.poll()  # the first batches already carry a real reading
        self._thread = NamedThread(target=self._run, name="clock-monitor", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.wait(self.poll_s):
            try:
                self.poll()
            except Exception:  # a bug in one reading must not end the monitoring
                log.exception("reading the clock status failed")

    def poll(self) -> TimeStatus:
        """Read once, publish the result, raise events for what changed."""
        status = self.reader.read()
        with self._lock:
            previous, self._status = self._status, status
            self.quality = status.quality
        self._events(previous, status)
        return status

    def _events(self, old: TimeStatus | None, new: TimeStatus) -> None:
        # Compared with the last grandmaster seen, so A -> (no master) -> B is a change too.
        # Raised before the state event, so whoever follows sees the new grandmaster first.
        if new.grandmaster_id:
            if self._last_gm and new.grandmaster_id != self._last_gm:
                self.emit(
                    logging.WARNING,
                    GRANDMASTER_CHANGED,
                    grandmaster_change_message(self._last_gm, new.grandmaster_id, new),
                    old=self._last_gm,
                    new=new.grandmaster_id,
                )
            self._last_gm = new.grandmaster_id
        if old is None or old.state is not new.state:
            problems = "; ".join(c.message for c in new.checks if c.level is not Level.OK)
            detail = {
                SyncState.LOCKED: f"locked to grandmaster {new.grandmaster_id or '-'}, "
                f"offset {format_ns(new.offset_ns)}",
                SyncState.HOLDOVER: "lost lock, holding over: timestamps drift from the "
                "grandmaster",
                SyncState.FREERUN: "not synchronised: timestamps come from a free-running clock",
            }[new.state]
            before = f"{old.state.value} -> " if old is not None else ""
            message = f"{before}{new.state.value}: {detail}"
            if problems and new.state is not SyncState.LOCKED:
                message += f" ({problems})"
            self.emit(
                _STATE_LEVEL[new.state],
                STATE_TAGS[new.state],
                message,
                state=new.state.value,
                grandmaster=new.grandmaster_id,
            )
        elif old.level is not new.level:
            problems = "; ".join(c.message for c in new.checks if c.level is not Level.OK)
            level = {Level.OK: logging.INFO, Level.WARN: logging.WARNING}.get(
                new.level, logging.ERROR
            )
            self.emit(
                level,
                "clock_checks",
                f"time checks {old.level.name} -> {new.level.name}"
                + (f": {problems}" if problems else ""),
            )

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(5.0)
            self._thread = None
        self.reader.close()


def make_time_sync_monitor(node: NodeConfig, emit: Emit) -> TimeSyncMonitor:
    cfg = node.clock
    if cfg.source == "none":
        return NoTimeSyncMonitor()
    reader: Reader
    if cfg.source == "ptp4l":
        reader = Ptp4lReader(
            cfg.uds,
            thresholds(cfg),
            interface=cfg.interface,
            expect_hardware=cfg.timestamping == "hardware",
            domain=cfg.domain,
            timeout=min(1.0, cfg.poll_s * 2),
            ignore=frozenset(cfg.ignore_checks),
        )
    else:
        reader = ChronyReader(thresholds(cfg), frozenset(cfg.ignore_checks))
    return PollingTimeSyncMonitor(reader, emit, cfg.poll_s)
