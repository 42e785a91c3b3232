"""Pacing: real-time sims' device clocks (with drift), polled devices' schedules, and the
injectable clocks that let drivers and simulated transports run in virtual time."""

from __future__ import annotations

import logging
import threading
import time
from typing import Protocol

import numpy as np
import numpy.typing as npt

from fleetdaq.edge.drivers.base import Block, DriverEvent


class DevicePacer:
    """Hands out scan indices at the rate a real device would produce them.

    The sim's device clock runs `drift_ppm` fast (positive) or slow against the host, so the
    timing fit has something real to find.
    """

    def __init__(self, rate_hz: float, drift_ppm: float = 0.0) -> None:
        self.rate_hz = rate_hz * (1.0 + drift_ppm * 1e-6)
        self._start_mono = 0
        self.next_index = 0
        self._stop = threading.Event()

    def start(self) -> None:
        self._start_mono = time.monotonic_ns()
        self.next_index = 0
        self._stop.clear()

    def wait_for(self, scans: int) -> int | None:
        """Sleep until `scans` more scans exist; return the index of the first, None if stopped.

        Scan k is sampled at device time k / rate, so the block is complete once its last scan
        (first + scans - 1) has been sampled.
        """
        first = self.next_index
        due_ns = self._start_mono + (first + scans - 1) * 1e9 / self.rate_hz
        delay = (due_ns - time.monotonic_ns()) / 1e9
        if self._stop.is_set() or (delay > 0 and self._stop.wait(delay)):
            return None  # stopped: a closed device gives no scans, due or not
        self.next_index = first + scans
        return first

    def seconds_of(self, first: int, scans: int) -> tuple[float, float]:
        """Device time (s since start) of scan `first` and the scan period (s)."""
        return first / self.rate_hz, 1.0 / self.rate_hz

    def stop(self) -> None:
        self._stop.set()


class PacedSim:
    """Shared behaviour of the sims: real-time pacing and the Driver protocol around
    `generate(first) -> (scans, channels)`, which each sim implements."""

    def __init__(self, rate_hz: float, scans: int, drift_ppm: float) -> None:
        self.scans = scans
        self.pacer = DevicePacer(rate_hz, drift_ppm)

    def generate(self, first: int) -> npt.NDArray[np.float64]:
        raise NotImplementedError

    def open(self) -> None:
        self.pacer.start()

    def read(self) -> Block:
        first = self.pacer.wait_for(self.scans)
        if first is None:
            raise InterruptedError("driver closed")
        return Block(self.generate(first), time.time_ns())

    def close(self) -> None:
        self.pacer.stop()


# --- Clocks for drivers and simulated transports ---------------------------------------------


class TimeSource(Protocol):
    """Host time for a driver and its (simulated) transport.

    Real drivers use `SYSTEM_TIME`; unit tests and the timing bench hand the driver and its
    simulated transport the same `VirtualTime`, so hours of device time run in seconds.
    """

    def time_ns(self) -> int:
        """CLOCK_REALTIME, ns (what samples are stamped with)."""
        ...

    def monotonic_ns(self) -> int:
        """A clock that never steps, ns (what reads are paced with)."""
        ...

    def sleep_until(self, monotonic_ns: int, cancel: threading.Event) -> bool:
        """Wait until `monotonic_ns`; False (at once) if `cancel` is or becomes set."""
        ...


class SystemTime:
    """The host's clocks; waits are interruptible through `cancel`."""

    def time_ns(self) -> int:
        return time.time_ns()

    def monotonic_ns(self) -> int:
        return time.monotonic_ns()

    def sleep_until(self, monotonic_ns: int, cancel: threading.Event) -> bool:
        delay = (monotonic_ns - time.monotonic_ns()) / 1e9
        if delay > 0:
            return not cancel.wait(delay)
        return not cancel.is_set()


SYSTEM_TIME = SystemTime()


class VirtualTime:
    """Simulated time: `sleep_until` jumps there at once. Both clocks advance together."""

    def __init__(self, start_ns: int = 1_795_000_000_000_000_000) -> None:
        self._realtime0 = start_ns
        self._now = 0
        self._lock = threading.Lock()

    def time_ns(self) -> int:
        return self._realtime0 + self._now

    def monotonic_ns(self) -> int:
        return self._now

    def sleep_until(self, monotonic_ns: int, cancel: threading.Event) -> bool:
        if cancel.is_set():
            return False
        with self._lock:
            self._now = max(self._now, monotonic_ns)
        return True

    def advance(self, ns: int) -> None:
        with self._lock:
            self._now += ns


class PollPacer:
    """When each poll of a polled device is due, at a fixed rate.

    Polls are due at ``start + k / rate`` on the monotonic clock. A poll the host could not
    make on time (a busy host, a stopped or paused process, a slow bus) is late: the slots
    that passed meanwhile are not polled, and nothing is made up for them. A reading taken
    now is not the value at a time already gone, so it is never stamped with one: the next
    poll waits for the next slot (less than a period away) and is stamped with it, as every
    poll is. `next_poll` says how many slots passed; the driver ends its block before them
    and the stream's scan index (its time) moves on by that many (`Block.late_polls`): a
    stretch without scans, never an invalid sample and never a sensor fault. A poll late by
    less than a period (scheduling jitter) is made at once, in its own slot.
    """

    def __init__(self, rate_hz: float, clock: TimeSource) -> None:
        self.period_ns = 1e9 / rate_hz
        self.clock = clock
        self._start = 0
        self._k = 0
        self.late = 0
        """Polls the host was too late for (their slots passed unpolled), since the start."""

    def start(self) -> None:
        self._start = self.clock.monotonic_ns()
        self._k = 0

    def next_poll(self, cancel: threading.Event) -> tuple[int, int] | None:
        """Wait for the next poll; return (slots passed unpolled before it, how late the
        first of them was in ns), (0, 0) when on time; None if cancelled. Lateness is looked
        at after the wait too: a host stopped while it waited wakes past its slot."""
        passed, overdue = 0, 0
        while True:
            due = self._start + round(self._k * self.period_ns)
            if not self.clock.sleep_until(due, cancel):
                return None
            lateness = self.clock.monotonic_ns() - due
            if lateness < self.period_ns:
                break
            skip = -int(-lateness // self.period_ns)  # up to the first slot not yet gone
            overdue = overdue or lateness
            passed += skip
            self._k += skip
        self.late += passed
        self._k += 1
        return passed, overdue


class LatePolls:
    """A polled device's lateness as events: one when polls start coming late, one when they
    are on time again (not one per block), and the count in health."""

    def __init__(self) -> None:
        self._late = False

    def block(self, where: str, late: int, worst_ns: int) -> DriverEvent | None:
        """After a block with `late` polls passed unpolled before it, the first of them
        `worst_ns` overdue when the host came back: the event, if any."""
        if late and not self._late:
            self._late = True
            return DriverEvent(
                logging.WARNING,
                "polls_late",
                f"{where}: {late} poll(s) not made on time (the host was busy or stopped "
                f"{worst_ns / 1e9:.3f} s past the first): no readings for that stretch and "
                "none made up; polling goes on from the next slot; not a sensor fault",
                (("late_polls", str(late)), ("late_ns", str(worst_ns))),
            )
        if not late and self._late:
            self._late = False
            return DriverEvent(logging.INFO, "polls_on_time", f"{where}: polls on time again")
        return None
