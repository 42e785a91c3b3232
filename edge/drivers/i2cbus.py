"""I2C through smbus2: the lazy import, the calls drivers use, and bounded retries.

Drivers get an `smbus2`-like module (the real one, or `sim_smbus` in sims and tests) and use
`module.SMBus(bus)`, `module.i2c_msg.read/write` with `SMBus.i2c_rdwr`, and `SMBus.write_byte`.
On Linux a NACK surfaces as OSError (EREMOTEIO, or EIO on some adapters).
"""

from __future__ import annotations

import errno
import importlib
from typing import Literal, Protocol, cast

from fleetdaq.contract.errors import DeviceError, DeviceNotFound, DriverUnavailable
from fleetdaq.contract.schema import SimFault

NACK_ERRNOS = {errno.EREMOTEIO, errno.EIO, errno.ENXIO}


class I2cMessage(Protocol):
    """One message of a combined transfer (`smbus2.i2c_msg`); `bytes(msg)` is what was read."""

    @property
    def addr(self) -> int: ...

    @property
    def flags(self) -> int: ...

    @property
    def len(self) -> int: ...

    def __bytes__(self) -> bytes: ...


class I2cMessages(Protocol):
    """What makes the messages (`smbus2.i2c_msg`'s static methods)."""

    def read(self, address: int, length: int) -> I2cMessage: ...

    def write(self, address: int, buf: bytes | list[int]) -> I2cMessage: ...


class I2cBus(Protocol):
    """An open bus (`smbus2.SMBus`): the calls drivers make."""

    def i2c_rdwr(self, *i2c_msgs: I2cMessage) -> None: ...

    def write_byte(self, i2c_addr: int, value: int, force: bool | None = None) -> None: ...

    def read_byte(self, i2c_addr: int, force: bool | None = None) -> int: ...

    def close(self) -> None: ...


class Smbus2(Protocol):
    """The `smbus2` module as drivers use it, or a stand-in (`sim_smbus.SimSmbus2`, a test's
    fake): the transport an I2C driver's constructor takes."""

    @property
    def i2c_msg(self) -> I2cMessages: ...

    def SMBus(self, bus: int | None = None, force: bool = False) -> I2cBus: ...


def load_smbus2(what: str) -> Smbus2:
    """The smbus2 module, imported now; DriverUnavailable (one line) when it is missing."""
    try:
        # smbus2's own stubs do not fit its module (`i2c_msg.__iter__` -> int): the protocol
        # says what fleetdaq calls.
        return cast(Smbus2, importlib.import_module("smbus2"))
    except ImportError as err:
        raise DriverUnavailable(
            f"the {what} needs smbus2: `pip install fleetdaq[pi]` (and enable I2C: "
            "Raspberry Pi dtparam=i2c_arm=on)"
        ) from err


def open_bus(smbus: Smbus2, bus: int) -> I2cBus:
    """`smbus.SMBus(bus)` with typed errors keeping the errno."""
    path = f"/dev/i2c-{bus}"
    try:
        return smbus.SMBus(bus)
    except FileNotFoundError as err:
        raise DeviceNotFound(
            f"{path} not found: enable I2C (Raspberry Pi: dtparam=i2c_arm=on)", err.errno
        ) from err
    except PermissionError as err:
        raise DeviceError(
            f"{path}: permission denied (add the user to the i2c group)", err.errno
        ) from err
    except OSError as err:
        raise DeviceError(f"{path}: cannot open: {err}", err.errno) from err


def is_nack(err: OSError) -> bool:
    return err.errno in NACK_ERRNOS


class I2cFault(SimFault):
    kind: Literal["nack", "crc_error"]
