"""SPI through spidev: the lazy import, the SpiDev calls drivers use, and opening a device."""

from __future__ import annotations

import errno
import importlib
from collections.abc import Callable
from typing import Annotated, Protocol

from pydantic import Field

from fleetdaq.contract.errors import DeviceError, DeviceNotFound, DriverUnavailable
from fleetdaq.contract.schema import Int, Strict


class SpiDev(Protocol):
    """The part of `spidev.SpiDev` the drivers use (a fake in tests and sims)."""

    mode: int
    max_speed_hz: int

    def open(self, bus: int, device: int) -> None: ...

    def xfer2(self, data: list[int]) -> list[int]: ...

    def close(self) -> None: ...


SpiFactory = Callable[[], SpiDev]


def load_spidev(what: str) -> SpiFactory:
    """`spidev.SpiDev`, imported now; DriverUnavailable (one line) when it is not installed."""
    try:
        module = importlib.import_module("spidev")
    except ImportError as err:
        raise DriverUnavailable(
            f"the {what} needs spidev: `pip install fleetdaq[pi]` on a Linux machine with SPI "
            "enabled (Raspberry Pi: dtparam=spi=on in /boot/firmware/config.txt)"
        ) from err
    factory: SpiFactory = module.SpiDev
    return factory


def open_spi(factory: SpiFactory, bus: int, device: int, mode: int, speed_hz: int) -> SpiDev:
    """Open /dev/spidev<bus>.<device> in `mode` at `speed_hz`; typed errors keep the errno."""
    path = f"/dev/spidev{bus}.{device}"
    spi = factory()
    try:
        spi.open(bus, device)
    except FileNotFoundError as err:
        raise DeviceNotFound(
            f"{path} not found: enable SPI (Raspberry Pi: dtparam=spi=on) and check bus/device",
            err.errno,
        ) from err
    except PermissionError as err:
        raise DeviceError(
            f"{path}: permission denied (add the user to the spi group)", err.errno
        ) from err
    except OSError as err:
        raise DeviceError(f"{path}: cannot open: {err}", err.errno or errno.EIO) from err
    spi.max_speed_hz = speed_hz
    spi.mode = mode
    return spi


class SpiDevice(Strict):
    """Where a chip sits on SPI (the part of a stream's config every SPI driver shares)."""

    bus: Annotated[Int, Field(ge=0, le=15)] = 0
    """/dev/spidev<bus>.<device>."""
    device: Annotated[Int, Field(ge=0, le=15)] = 0
    """Chip select (CE0 = 0, CE1 = 1)."""
    max_speed_hz: Annotated[Int, Field(ge=10_000, le=5_000_000)] = 1_000_000
    """SCK; the MAX3185x allow up to 5 MHz."""
