"""Drivers: one device, one module, behind the small `Driver` protocol.

The registry maps a config's `driver` name to ``"module:Class"`` and imports it only when a
config uses it, so a missing vendor library fails that driver alone, with a typed error.
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Protocol, runtime_checkable

import numpy as np
import numpy.typing as npt

from edge.errors import DriverError, DriverUnavailable

if TYPE_CHECKING:
    from edge.config import StreamConfig


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


REGISTRY: dict[str, str] = {
    "wave_sim": "edge.drivers.wave_sim:WaveSim",
    "thermocouple_sim": "edge.drivers.thermocouple_sim:ThermocoupleSim",
    "environment_sim": "edge.drivers.environment_sim:EnvironmentSim",
    "labjack_t8": "edge.drivers.labjack_t8:LabJackT8",
    "labjack_t8_poll": "edge.drivers.labjack_t8:LabJackT8Poll",
    "max31855": "edge.drivers.max31855:Max31855",
    "max31856": "edge.drivers.max31856:Max31856",
    "sht3x": "edge.drivers.sht3x:Sht3x",
}
"""Driver name -> "module:Class". A real driver with a `sim:` block runs on the simulated
transport shipped beside it (sim_ljm, sim_spi, sim_smbus); without one, the class imports its
vendor library (labjack-ljm, spidev, smbus2) when it is constructed, never before."""


def create_driver(cfg: StreamConfig) -> Driver:
    """Import the driver named by `cfg.driver` (only now) and construct it from `cfg`."""
    target = REGISTRY.get(cfg.driver)
    if target is None:
        raise DriverError(f"no driver named {cfg.driver!r}")
    module_name, _, class_name = target.partition(":")
    try:
        module = importlib.import_module(module_name)
    except ImportError as err:
        raise DriverUnavailable(f"driver {cfg.driver!r} needs {err.name!r}: {err}") from err
    cls = getattr(module, class_name)
    driver: Driver = cls(cfg)
    return driver
