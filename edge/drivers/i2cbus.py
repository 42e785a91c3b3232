"""I2C through smbus2: the lazy import, the calls drivers use, and bounded retries.

Drivers get an `smbus2`-like module (the real one, or `sim_smbus` in sims and tests) and use
`module.SMBus(bus)`, `module.i2c_msg.read/write` with `SMBus.i2c_rdwr`, and `SMBus.write_byte`.
On Linux a NACK surfaces as OSError (EREMOTEIO, or EIO on some adapters).
"""

from __future__ import annotations

import errno
import importlib
from typing import Any, Literal

from fleetdaq.contract.errors import DeviceError, DeviceNotFound, DriverUnavailable
from fleetdaq.contract.schema import SimFault

NACK_ERRNOS = {errno.EREMOTEIO, errno.EIO, errno.ENXIO}


def load_smbus2(what: str) -> Any:
    """The smbus2 module, imported now; DriverUnavailable (one line) when it is missing."""
    try:
        return importlib.import_module("smbus2")
    except ImportError as err:
        raise DriverUnavailable(
            f"the {what} needs smbus2: `pip install fleetdaq[pi]` (and enable I2C: "
            "Raspberry Pi dtparam=i2c_arm=on)"
        ) from err


def open_bus(smbus: Any, bus: int) -> Any:
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
