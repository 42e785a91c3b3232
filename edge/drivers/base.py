"""What every driver is: the small `Driver` protocol and the `Block` of scans it returns."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Protocol, runtime_checkable

import numpy as np
import numpy.typing as npt


@dataclass(frozen=True, slots=True)
class DriverEvent:
    """Something a driver noticed (skipped scans, a fault, a reconnect): the agent raises it."""

    level: int
    """Python logging level."""
    tag: str
    message: str


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

    def health(self) -> dict[str, Any]: ...
