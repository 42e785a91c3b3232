"""Slow command-response reads of a LabJack T8 (AIN volts, DIO states): `labjack_t8_poll`."""

from __future__ import annotations

import logging
import threading
from typing import Annotated, Literal

import numpy as np
from pydantic import AfterValidator, Field

from fleetdaq.contract.drivers import DriverKind, DriverPlugin
from fleetdaq.contract.errors import DriverError
from fleetdaq.contract.schema import Channel, Float, Int, Resolution, StreamBase
from fleetdaq.edge.drivers.base import Block, DriverEvent
from fleetdaq.edge.drivers.labjack_ljm import (
    CORE_TIMER_HZ,
    T8_ADC_BITS,
    CoreTimer,
    LabJackT8Sim,
    Ljm,
    LjmDevice,
    T8Connection,
    T8Outputs,
    load_ljm,
    t8_range,
)
from fleetdaq.edge.drivers.pacing import SYSTEM_TIME, LatePolls, PollPacer, TimeSource

T8_POLL_REGISTER = r"^(AIN[0-7]|FIO[0-7]|EIO[0-7]|CIO[0-3]|DIO([0-9]|1[0-9])|DAC[01])$"


class T8PollChannel(Channel):
    """A register the T8 is polled for: an AIN (volts), a digital line (0/1) or a DAC readback."""

    source: Annotated[str, Field(pattern=T8_POLL_REGISTER)]
    """The T8 register read: AIN0-7, FIO0-7, EIO0-7, CIO0-3, DIO0-19 or DAC0-1."""
    range: Annotated[Float, AfterValidator(t8_range)] = 11.0
    """AIN#_RANGE for an AIN source."""


class LabJackT8PollStream(StreamBase, T8Connection):
    """Slow command-response reads of a T8 (AIN, DIO states), stamped by its CORE_TIMER."""

    driver: Literal["labjack_t8_poll"]
    rate_hz: Annotated[Float, Field(gt=0, le=100)]
    channels: Annotated[list[T8PollChannel], Field(min_length=1, max_length=32)]  # type: ignore[assignment]
    resolution_index: Annotated[Int, Field(ge=0, le=16)] = 0
    """AIN#_RESOLUTION_INDEX for every polled AIN."""
    sim: LabJackT8Sim | None = None

    def resolutions(self) -> tuple[Resolution | None, ...]:
        """AIN: the 24-bit ADC over ±range; a digital line: 0 or 1; a DAC readback (the value
        written, any float): taken as fine as the ADC over the DAC's -0.1..10 V, which float32
        does not hold, so a stream with one stays float64."""

        def one(ch: T8PollChannel) -> Resolution:
            if ch.source.startswith("AIN"):
                return Resolution.bits(T8_ADC_BITS, -ch.range, ch.range)
            if ch.source.startswith("DAC"):
                return Resolution.bits(T8_ADC_BITS, T8Outputs.DAC_MIN_V, T8Outputs.DAC_MAX_V)
            return Resolution(1.0, 0.0, 1.0)

        return tuple(one(ch) for ch in self.channels)


class LabJackT8Poll:
    """Slow command-response reads of a T8 (AIN volts, DIO states): `labjack_t8_poll`.

    Each poll reads every channel and CORE_TIMER in one eReadNames, so the device clock times
    polls as it times stream scans. Polls are paced on the host; slots the host was too late
    for pass unpolled and are counted as late (see `PollPacer`): nothing is made up for them.
    """

    def __init__(
        self,
        cfg: LabJackT8PollStream,
        transport: Ljm | None = None,
        clock: TimeSource = SYSTEM_TIME,
    ) -> None:
        self.cfg = cfg
        self.clock = clock
        self.ljm = transport if transport is not None else load_ljm()
        self.dev = LjmDevice(self.ljm, cfg.connection, cfg.identifier, clock)
        self.scans = cfg.batch_scans
        self.names = [ch.source for ch in cfg.channels] + ["CORE_TIMER"]
        self.pacer = PollPacer(cfg.rate_hz, clock)
        self.timer = CoreTimer()
        self._closing = threading.Event()
        self._last_host_ns: int | None = None
        self._events: list[DriverEvent] = []
        self._lateness = LatePolls()
        self._carried: tuple[list[float], int] | None = None
        """A poll made after a stretch without polls (its values and host time): the next
        block's first scan."""
        self._late_before = (0, 0)
        self.opens = 0
        self.reconnects = 0

    def open(self) -> None:
        self._closing.clear()
        handle = self.dev.open()
        names: list[str] = []
        values: list[float] = []
        for ch in self.cfg.channels:
            if ch.source.startswith("AIN"):
                names += [f"{ch.source}_RANGE", f"{ch.source}_RESOLUTION_INDEX"]
                values += [ch.range, float(self.cfg.resolution_index)]
        try:
            if names:
                self.dev.call(self.ljm.eWriteNames, handle, len(names), names, values)
        except DriverError:
            self.dev.close()
            raise
        if self.opens:
            self.reconnects += 1
            self._events.append(
                DriverEvent(logging.INFO, "reconnected", f"{self.dev.where}: polling again")
            )
        self.opens += 1
        self._carried, self._late_before = None, (0, 0)
        self.pacer.start()

    def read(self) -> Block:
        """The next block of polls; it ends early when the host was too late for the next
        slots, as a polled driver's does (`fleetdaq.edge.drivers.polled.PolledDriver.read`)."""
        rows = np.full((self.scans, len(self.cfg.channels)), np.nan)
        timer: list[int] = []
        poll_host: list[int] = []
        late, late_ns = self._late_before
        self._late_before = (0, 0)
        if self._carried is not None:
            (values, host), self._carried = self._carried, None
            rows[0] = values[:-1]
            timer.append(int(values[-1]))
            poll_host.append(host)
        while len(timer) < self.scans:
            due = self.pacer.next_poll(self._closing)
            if due is None or self.dev.handle is None:
                raise InterruptedError("driver closed")
            passed, overdue = due
            values = self.dev.call(
                self.ljm.eReadNames, self.dev.handle, len(self.names), self.names
            )
            if passed and timer:
                # Made after a stretch without polls: it starts the next block.
                self._carried = (values, self.clock.time_ns())
                self._late_before = (passed, overdue)
                break
            if passed:
                late, late_ns = passed, overdue
            rows[len(timer)] = values[:-1]
            timer.append(int(values[-1]))
            poll_host.append(self.clock.time_ns())
        n = len(timer)
        # Polls are paced by the host: the expected ticks between them come from host time.
        hosts = np.asarray(poll_host, dtype=np.float64)
        previous = self._last_host_ns if self._last_host_ns is not None else poll_host[0]
        expected = np.diff(hosts, prepend=previous) * (CORE_TIMER_HZ / 1e9)
        ticks = self.timer.unwrap(np.asarray(timer, dtype=np.int64), expected)
        device_ns = int(ticks[-1]) * 1_000_000_000 // CORE_TIMER_HZ
        self._last_host_ns = poll_host[-1]
        if (ev := self._lateness.block(self.dev.where, late, late_ns)) is not None:
            self._events.append(ev)
        events, self._events = tuple(self._events), []
        return Block(rows[:n], poll_host[-1], None, device_ns, events, late)

    def close(self) -> None:
        self._closing.set()
        self.dev.close()

    def health(self) -> dict[str, object]:
        return {"late_polls": self.pacer.late, "reconnects": self.reconnects}


PLUGIN = DriverPlugin(
    DriverKind.STREAM,
    LabJackT8PollStream,
    LabJackT8Poll,
    "fleetdaq.edge.drivers.sim_ljm:t8_transport",
)
