"""What every driver is: the small `Driver` protocol and the `Block` of scans it returns; what
every output driver is (`OutputDriver`) and a device's hardware watchdog."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np
import numpy.typing as npt


@dataclass(frozen=True, slots=True)
class DriverEvent:
    """Something a driver noticed (skipped scans, a fault, a reconnect): the agent raises it."""

    level: int
    """Python logging level."""
    tag: str
    message: str
    fields: tuple[tuple[str, str], ...] = ()
    """Structured values code may react to (the event's key/value fields)."""


@dataclass(frozen=True, slots=True)
class Block:
    """Consecutive scans as read from a device, before scale/offset."""

    raw: npt.NDArray[np.float64]
    """(scans, channels)."""
    host_ns: int
    """CLOCK_REALTIME right after the read returned (every scan in the block is older)."""
    status: npt.NDArray[np.uint8] | None = None
    """(scans, channels) SampleStatus codes, None when all valid."""
    device_ns: int | None = None
    """Device-clock time of the block's last scan (ns, unwrapped), when the device has a
    clock (e.g. the T8's CORE_TIMER); None otherwise."""
    events: tuple[DriverEvent, ...] = ()
    late_polls: int = 0
    """Poll slots, right before this block's first scan, that the host was too late to poll
    (busy or stopped): no reading exists for them and none is made up. The stream's scan
    index (its time) moves on by this many before this block, so its first scan keeps the
    time it was polled at; counted in the stream's health as late polls."""


class Driver(Protocol):
    """What the acquisition loop needs from a device."""

    def open(self) -> None: ...

    def read(self) -> Block:
        """Block until the next `scans_per_batch` scans are available and return them."""
        ...

    def close(self) -> None:
        """Idempotent."""
        ...


@runtime_checkable
class DriverHealth(Protocol):
    """Optional: a driver with this reports device health (backlogs, fault counts, ...)."""

    def health(self) -> dict[str, object]: ...


class OutputDriver(Protocol):
    """What the output service needs from an output: write a value, read it back.

    Values are the output's engineering values (volts, 0/1). Errors are DriverErrors (a
    DeviceError keeps the vendor's code and text); the output service turns them into a
    `device_error` refusal and reopens the device on the next command or readback poll.
    """

    @property
    def where(self) -> str:
        """The device and line, in words (for events and messages)."""
        ...

    def open(self) -> None: ...

    def write(self, value: float) -> None: ...

    def read(self) -> float:
        """What the device holds now (raises when it cannot say)."""
        ...

    def close(self) -> None:
        """Idempotent."""
        ...


class HardwareWatchdog(Protocol):
    """A device that sets its outputs safe by itself when nobody talks to it."""

    @property
    def where(self) -> str: ...

    def arm(self, timeout_s: float) -> str:
        """Configure the watchdog with the safe values of every output on the device and enable
        it; returns what was set, in words. Raises DriverError."""
        ...

    def feed(self) -> None:
        """Talk to the device (its timer restarts on any communication). Raises DriverError."""
        ...


@runtime_checkable
class WithWatchdog(Protocol):
    """Optional: an output driver on a device with a hardware watchdog."""

    def hardware_watchdog(self) -> HardwareWatchdog: ...
