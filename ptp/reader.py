"""Reading a time source into a `TimeStatus`, again and again.

A reader owns its connection (ptp4l's UDS socket, or chronyc) and a `SyncTracker`: the memory
that a single reading lacks. ptp4l forgets its last sync the moment a port leaves SLAVE
(TIME_STATUS_NP's ingress_time drops to 0), so the tracker remembers, on the monotonic clock,
when the last sync was seen and when this clock was last LOCKED. That is what HOLDOVER is
measured from, and what "last sync" shows once ptp4l has forgotten.

How old the last sync is: ptp4l's ingress_time is a timestamp in the time base of the port's
clock: CLOCK_REALTIME with software timestamping, the NIC's PHC with hardware timestamping.
The age is that clock's "now" minus ingress_time (what ptpcheck does). When the PHC cannot be
read, the age is how long ingress_time has stayed the same across polls (coarse: ±1 poll).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Protocol

from fleetdaq.ptp.checks import (
    Thresholds,
    defaults_for,
    evaluate_chrony,
    evaluate_ptp4l,
    unreachable,
)
from fleetdaq.ptp.chrony import read_chrony
from fleetdaq.ptp.datasets import HARDWARE_TIMESTAMPING, Ptp4lSnapshot
from fleetdaq.ptp.errors import PtpError
from fleetdaq.ptp.host import KernelClock, TimestampingCaps, phc_time_ns, read_kernel_clock
from fleetdaq.ptp.host import timestamping_caps as read_caps
from fleetdaq.ptp.management import DEFAULT_UDS, Ptp4lClient
from fleetdaq.ptp.pmc import snapshot_via_pmc
from fleetdaq.ptp.time_status import SyncState, TimeStatus


class Reader(Protocol):
    source: str
    """"ptp4l" or "chrony"."""

    def read(self) -> TimeStatus:
        """One reading. Never raises for a daemon that is down: that is a FAIL status."""
        ...

    def close(self) -> None: ...


@dataclass(slots=True)
class SyncTracker:
    """Memory across readings, on the monotonic clock (immune to the clock being judged)."""

    last_sync_mono_ns: int | None = None
    last_locked_sync_mono_ns: int | None = None
    last_locked_grandmaster: str = ""
    _ingress: int = 0
    _ingress_seen_mono_ns: int = 0

    def sync_age(self, now_mono: int, age_from_clock: int | None, ingress: int) -> int | None:
        """The age of the last sync: from the clock if it could be read, else from memory."""
        if ingress and ingress != self._ingress:
            self._ingress, self._ingress_seen_mono_ns = ingress, now_mono
        if ingress and age_from_clock is None:
            age_from_clock = now_mono - self._ingress_seen_mono_ns
        if ingress and age_from_clock is not None:
            self.last_sync_mono_ns = now_mono - max(0, age_from_clock)
            return age_from_clock
        if self.last_sync_mono_ns is not None:
            return now_mono - self.last_sync_mono_ns
        return None

    def holdover_age(self, now_mono: int) -> int | None:
        if self.last_locked_sync_mono_ns is None:
            return None
        return now_mono - self.last_locked_sync_mono_ns

    def note(self, status: TimeStatus, now_mono: int) -> TimeStatus:
        """Remember what a LOCKED reading says; give a HOLDOVER reading the grandmaster it
        holds over from (ptp4l names none once the port left SLAVE)."""
        if status.state is SyncState.LOCKED:
            age = status.last_sync_age_ns or 0
            self.last_locked_sync_mono_ns = now_mono - max(0, age)
            self.last_locked_grandmaster = status.grandmaster_id
        elif status.state is SyncState.HOLDOVER and not status.grandmaster_id:
            return replace(status, grandmaster_id=self.last_locked_grandmaster)
        return status


def _kernel() -> KernelClock | None:
    try:
        return read_kernel_clock()
    except PtpError:
        return None


class Ptp4lReader:
    """Reads ptp4l through its UDS socket (``via="uds"``, our client) or through pmc.

    `thresholds` None: the defaults for the timestamping ptp4l actually uses. `interface`
    None: the interface ptp4l reports for its first port."""

    source = "ptp4l"

    def __init__(
        self,
        uds: str = DEFAULT_UDS,
        thresholds: Thresholds | None = None,
        *,
        interface: str | None = None,
        expect_hardware: bool | None = None,
        via: str = "uds",
        domain: int = 0,
        timeout: float = 1.0,
        ignore: frozenset[str] = frozenset(),
        monotonic_ns: Callable[[], int] = time.monotonic_ns,
    ) -> None:
        if via not in ("uds", "pmc"):
            raise ValueError(f"via must be 'uds' or 'pmc', not {via!r}")
        self.uds = uds
        self.thresholds = thresholds
        self.interface = interface
        self.expect_hardware = expect_hardware
        self.via = via
        self.domain = domain
        self.timeout = timeout
        self.ignore = ignore
        self.tracker = SyncTracker()
        self._mono = monotonic_ns
        self._client: Ptp4lClient | None = None
        self._caps: dict[str, TimestampingCaps | None] = {}

    def _snapshot(self) -> Ptp4lSnapshot:
        if self.via == "pmc":
            return snapshot_via_pmc(self.uds, timeout=max(self.timeout, 2.0))
        if self._client is None:
            self._client = Ptp4lClient(self.uds, self.timeout, self.domain)
        return self._client.snapshot()

    def caps(self, interface: str | None) -> TimestampingCaps | None:
        if not interface:
            return None
        if interface not in self._caps:  # capabilities do not change while we run
            try:
                self._caps[interface] = read_caps(interface)
            except PtpError:
                self._caps[interface] = None  # e.g. ptp4l runs in another network namespace
        return self._caps[interface]

    def read(self) -> TimeStatus:
        try:
            snap = self._snapshot()
        except PtpError as err:
            if self._client is not None:
                self._client.close()
                self._client = None
            now_mono = self._mono()
            status = unreachable(
                "ptp4l",
                str(err),
                now_ns=time.time_ns(),
                holdover_age_ns=self.tracker.holdover_age(now_mono),
                thresholds=self.thresholds or defaults_for(bool(self.expect_hardware)),
                ignore=self.ignore,
            )
            return self.tracker.note(status, now_mono)
        hardware = snap.timestamping in HARDWARE_TIMESTAMPING
        caps = self.caps(self.interface or snap.interface)
        ingress = snap.time_status.ingress_time_ns
        age_from_clock: int | None = None
        now_ns = time.time_ns()
        now_mono = self._mono()
        if ingress:
            if not hardware:
                age_from_clock = now_ns - ingress
            elif caps is not None and caps.phc_index >= 0:
                try:
                    age_from_clock = phc_time_ns(caps.phc_index) - ingress
                except OSError:
                    age_from_clock = None
        status = evaluate_ptp4l(
            snap,
            now_ns=now_ns,
            sync_age_ns=self.tracker.sync_age(now_mono, age_from_clock, ingress),
            holdover_age_ns=self.tracker.holdover_age(now_mono),
            thresholds=self.thresholds or defaults_for(hardware),
            kernel=_kernel(),
            caps=caps,
            expect_hardware=self.expect_hardware,
            ignore=self.ignore,
        )
        return self.tracker.note(status, now_mono)

    def close(self) -> None:
        if self._client is not None:
            self._client.close()
            self._client = None


class ChronyReader:
    """Reads chronyd through ``chronyc -c tracking``."""

    source = "chrony"

    def __init__(
        self,
        thresholds: Thresholds | None = None,
        ignore: frozenset[str] = frozenset(),
        monotonic_ns: Callable[[], int] = time.monotonic_ns,
    ) -> None:
        self.thresholds = thresholds or defaults_for(False)
        self.ignore = ignore
        self.tracker = SyncTracker()
        self._mono = monotonic_ns

    def read(self) -> TimeStatus:
        now_mono = self._mono()
        try:
            tracking = read_chrony()
        except PtpError as err:
            status = unreachable(
                "chrony",
                str(err),
                now_ns=time.time_ns(),
                holdover_age_ns=self.tracker.holdover_age(now_mono),
                thresholds=self.thresholds,
                ignore=self.ignore,
            )
            return self.tracker.note(status, now_mono)
        status = evaluate_chrony(
            tracking,
            now_ns=time.time_ns(),
            holdover_age_ns=self.tracker.holdover_age(now_mono),
            thresholds=self.thresholds,
            kernel=_kernel(),
            ignore=self.ignore,
        )
        return self.tracker.note(status, now_mono)

    def close(self) -> None:
        pass
