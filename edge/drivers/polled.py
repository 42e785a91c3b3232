"""Shared behaviour of slow polled devices (thermocouple converters on SPI, sensors on I2C).

A subclass opens its bus in `connect` and reads one scan in `poll`; this class paces polls on
the host clock, assembles blocks, marks polls that could not happen on time as skipped, and
turns a device's fault state into events when it changes (not on every poll).
"""

from __future__ import annotations

import logging
import threading
from dataclasses import dataclass
from typing import Any

import numpy as np

from edge.drivers.base import Block, DriverEvent
from edge.drivers.pacing import PollPacer, TimeSource
from edge.wire import SampleStatus


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

    def extra_health(self) -> dict[str, Any]:
        return {}

    # -- Driver protocol -------------------------------------------------------------------

    def open(self) -> None:
        self.closing.clear()
        self.connect()
        if self.opens:
            self.event(logging.INFO, "reconnected", f"{self.where}: reading again")
        self.opens += 1
        self.pacer.start()

    def read(self) -> Block:
        raw = np.zeros((self.scans, self.channels))
        status = np.zeros(raw.shape, dtype=np.uint8)
        i = 0
        while i < self.scans:
            missed = self.pacer.next_poll(self.closing)
            if missed is None:
                raise InterruptedError("driver closed")
            if missed:
                self.event(
                    logging.WARNING,
                    "missed_polls",
                    f"{self.where}: {missed} poll(s) missed their time; marked invalid",
                )
            for _ in range(min(missed, self.scans - i)):
                status[i] = SampleStatus.SKIPPED_SCAN
                i += 1
            if i == self.scans:
                break
            result = self.poll()
            raw[i] = result.values
            status[i] = result.status
            self._note(result.problem, result.detail)
            i += 1
        events, self._events = tuple(self._events), []
        return Block(raw, self.clock.time_ns(), status if status.any() else None, None, events)

    def close(self) -> None:
        self.closing.set()
        self.disconnect()

    def health(self) -> dict[str, Any]:
        return {
            "faulty_polls": self.faulty_polls,
            "missed_polls": self.pacer.missed,
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
