"""Shared behaviour of slow polled devices (thermocouple converters on SPI, sensors on I2C).

A subclass opens its bus in `connect` and reads one scan in `poll`; this class paces polls on
the host clock, assembles blocks, counts polls the host could not make on time as late (their
slots pass without scans: nothing is made up, nothing marked invalid, and a busy host is not a
broken sensor), and turns a device's fault state and its lateness into events when they change
(not on every poll).
"""

from __future__ import annotations

import logging
import threading
from dataclasses import dataclass

import numpy as np

from fleetdaq.edge.drivers.base import Block, DriverEvent
from fleetdaq.edge.drivers.pacing import LatePolls, PollPacer, TimeSource


@dataclass(frozen=True, slots=True)
class Poll:
    """One poll's result: a value and a SampleStatus code per channel, and what is wrong."""

    values: tuple[float, ...]
    status: tuple[int, ...]
    problem: str | None = None
    """A device fault or bus problem in words (None: all well); an event when it changes."""
    detail: str = ""
    """More about the problem for the event (not compared: it may change every poll)."""


class PolledDriver:
    """The Driver protocol around `connect` / `poll` / `disconnect`."""

    fault_tag = "device_fault"

    def __init__(self, rate_hz: float, scans: int, channels: int, clock: TimeSource) -> None:
        self.scans = scans
        self.channels = channels
        self.clock = clock
        self.pacer = PollPacer(rate_hz, clock)
        self.closing = threading.Event()
        self.faulty_polls = 0
        self.opens = 0
        self._problem: str | None = None
        self._events: list[DriverEvent] = []
        self._lateness = LatePolls()
        self._carried: tuple[Poll, int] | None = None
        """A poll made after a stretch without polls, with its host time: the next block's
        first scan."""
        self._late_before = (0, 0)
        """(slots passed unpolled, how late) before the carried poll."""

    # -- subclasses ------------------------------------------------------------------------

    @property
    def where(self) -> str:
        raise NotImplementedError

    def connect(self) -> None:
        raise NotImplementedError

    def poll(self) -> Poll:
        raise NotImplementedError

    def disconnect(self) -> None:
        raise NotImplementedError

    def extra_health(self) -> dict[str, object]:
        return {}

    # -- Driver protocol -------------------------------------------------------------------

    def open(self) -> None:
        self.closing.clear()
        self.connect()
        if self.opens:
            self.event(logging.INFO, "reconnected", f"{self.where}: reading again")
        self.opens += 1
        self._carried, self._late_before = None, (0, 0)
        self.pacer.start()

    def read(self) -> Block:
        """The next block of polls. A block ends early, with its last poll made on time,
        when the host was too late for the next slots (see `PollPacer`): the poll made after
        them starts the next block, whose `late_polls` says how many slots passed unpolled."""
        raw = np.zeros((self.scans, self.channels))
        status = np.zeros(raw.shape, dtype=np.uint8)
        late, late_ns = self._late_before
        self._late_before = (0, 0)
        host_ns = 0
        i = 0
        if self._carried is not None:
            (result, host_ns), self._carried = self._carried, None
            raw[0], status[0] = result.values, result.status
            i = 1
        while i < self.scans:
            due = self.pacer.next_poll(self.closing)
            if due is None:
                raise InterruptedError("driver closed")
            passed, overdue = due
            result = self.poll()
            self._note(result.problem, result.detail)
            if passed and i:
                # Made after a stretch without polls: it starts the next block.
                self._carried = (result, self.clock.time_ns())
                self._late_before = (passed, overdue)
                break
            if passed:
                late, late_ns = passed, overdue
            raw[i], status[i] = result.values, result.status
            host_ns = self.clock.time_ns()
            i += 1
        if (ev := self._lateness.block(self.where, late, late_ns)) is not None:
            self._events.append(ev)
        events, self._events = tuple(self._events), []
        status = status[:i]
        return Block(raw[:i], host_ns, status if status.any() else None, None, events, late)

    def close(self) -> None:
        self.closing.set()
        self.disconnect()

    def health(self) -> dict[str, object]:
        return {
            "faulty_polls": self.faulty_polls,
            "late_polls": self.pacer.late,
            "fault": self._problem or "",
            **self.extra_health(),
        }

    # -- events ----------------------------------------------------------------------------

    def event(self, level: int, tag: str, message: str) -> None:
        self._events.append(DriverEvent(level, tag, message))

    def _note(self, problem: str | None, detail: str = "") -> None:
        if problem is not None:
            self.faulty_polls += 1
        if problem == self._problem:
            return
        if problem is None:
            message = f"{self.where}: {self._problem} cleared"
            self.event(logging.INFO, f"{self.fault_tag}_cleared", message)
        else:
            more = f" ({detail})" if detail else ""
            message = f"{self.where}: {problem}{more}; samples marked invalid"
            self.event(logging.WARNING, self.fault_tag, message)
        self._problem = problem
