"""PCF8574 / PCF8574A I2C port expander pins as digital outputs: the `pcf8574` output driver.

Datasheet: NXP PCF8574/PCF8574A, Rev. 5 (27 May 2013).

- Addresses (7.1, Tables 4 and 5): PCF8574 0x20-0x27, PCF8574A 0x38-0x3F (A2 A1 A0 pins).
- Quasi-bidirectional I/Os (8.1): there is no direction register, one 8-bit port. At power-on
  every pin is HIGH (weak 100 uA pull-up); a pin written LOW is pulled down strongly.
- Writing (8.2): each data byte sets all eight pins P7..P0 at once; the latest byte wins. Pins
  used as inputs must be written 1.
- Reading (8.3): one data byte with the *pin levels*, not the latch: a pin written HIGH but held
  low outside reads 0. So readback here is the real state of the pin (a relay board input that
  shorts it shows), not an echo of what was written.

The eight pins of one chip are eight outputs sharing one port register: all of them go
through one `Pcf8574Port` (fleetdaq.edge.drivers.shared), which keeps the byte last written and
changes one bit at a time. Pins no output drives stay HIGH (inputs, as at power-on). The first
write sets every configured pin to its initial level in one byte, so no relay blips at start.

Relay boards: many boards switch a relay on when the pin is LOW (active-low inputs, often
through an optocoupler); set `invert: true` and the output's 1 means "relay on" = pin LOW.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import Annotated, Literal, TypeVar

from pydantic import AfterValidator, Field

from fleetdaq.contract.drivers import DriverKind, DriverPlugin
from fleetdaq.contract.errors import DeviceError
from fleetdaq.contract.schema import Int, OutputBase, Strict
from fleetdaq.edge.drivers.i2cbus import I2cBus, I2cFault, Smbus2, is_nack, load_smbus2, open_bus
from fleetdaq.edge.drivers.pacing import SYSTEM_TIME, TimeSource
from fleetdaq.edge.drivers.shared import SharedDevices

POWER_ON_PORT = 0xFF
"""Every pin HIGH at power-on (datasheet 8.1)."""


def _pcf8574_address(value: int) -> int:
    if not (0x20 <= value <= 0x27 or 0x38 <= value <= 0x3F):
        raise ValueError(
            f"0x{value:02X} is not a PCF8574 address (PCF8574 0x20-0x27, PCF8574A 0x38-0x3F)"
        )
    return value


class Pcf8574Sim(Strict):
    """A simulated PCF8574 (edge/drivers/sim_smbus.py)."""

    stuck_low: Annotated[Int, Field(ge=0, le=0xFF)] = 0
    """Bitmask of pins held LOW outside the chip (a short, a loaded line): they read 0."""
    faults: list[I2cFault] = []


class Pcf8574Output(OutputBase):
    """One pin of a PCF8574 (or PCF8574A) I2C port expander, driving a relay or a logic input."""

    driver: Literal["pcf8574"]
    kind: Literal["digital"] = "digital"
    bus: Annotated[Int, Field(ge=0, le=255)] = 1
    """/dev/i2c-<bus>."""
    address: Annotated[Int, AfterValidator(_pcf8574_address)]
    """PCF8574 0x20-0x27, PCF8574A 0x38-0x3F."""
    pin: Annotated[Int, Field(ge=0, le=7)]
    """P0-P7."""
    invert: bool = False
    """Active-low wiring: the output's 1 drives the pin LOW (most relay boards)."""
    retries: Annotated[Int, Field(ge=0, le=10)] = 2
    """Extra attempts after a NACK before the command fails with device_error."""
    sim: Pcf8574Sim | None = None

    @property
    def resource(self) -> str:
        return f"pin P{self.pin} of the PCF8574 at 0x{self.address:02X} on I2C bus {self.bus}"


def port_with(port: int, pin: int, level: bool) -> int:
    """The port byte with `pin` set to `level` (1 = HIGH)."""
    return (port | 1 << pin) if level else (port & ~(1 << pin) & 0xFF)


def pin_level(port: int, pin: int) -> bool:
    """The level of `pin` in a byte read from the port (8.3: pin levels)."""
    return bool(port >> pin & 1)


def level_for(value: float, invert: bool) -> bool:
    """The pin level (True = HIGH) for an output value 0/1."""
    return (value >= 0.5) != invert


def value_of(level: bool, invert: bool) -> float:
    return 1.0 if level != invert else 0.0


_T = TypeVar("_T")


class Pcf8574Port:
    """One PCF8574: its bus, the byte last written (the port latch), one transaction at a time.

    Raises DeviceError (keeping the errno) when the chip does not acknowledge after `retries`.
    """

    def __init__(self, smbus: Smbus2, bus: int, address: int, retries: int) -> None:
        self.smbus = smbus
        self.bus_number = bus
        self.address = address
        self.retries = retries
        self.lock = threading.Lock()
        self.initial = POWER_ON_PORT
        """The byte the first write starts from: every driven pin at its initial level."""
        self.port: int | None = None
        """The byte last written; None before the first write."""
        self._bus: I2cBus | None = None
        self.nacks = 0

    @property
    def where(self) -> str:
        return f"PCF8574 0x{self.address:02X} on /dev/i2c-{self.bus_number}"

    def register(self, pin: int, level: bool) -> None:
        self.initial = port_with(self.initial, pin, level)

    def open(self) -> None:
        with self.lock:
            if self._bus is None:
                self._bus = open_bus(self.smbus, self.bus_number)

    def close(self) -> None:
        with self.lock:
            bus, self._bus = self._bus, None
            if bus is not None:
                bus.close()

    def write_pin(self, pin: int, level: bool) -> None:
        with self.lock:
            base = self.initial if self.port is None else self.port
            byte = port_with(base, pin, level)
            self._io(lambda bus: bus.write_byte(self.address, byte), "write")
            self.port = byte

    def read_port(self) -> int:
        with self.lock:
            return int(self._io(lambda bus: bus.read_byte(self.address), "read"))

    def _io(self, op: Callable[[I2cBus], _T], what: str) -> _T:
        if self._bus is None:
            self._bus = open_bus(self.smbus, self.bus_number)
        for attempt in range(self.retries + 1):
            try:
                return op(self._bus)
            except OSError as err:
                if is_nack(err):
                    self.nacks += 1
                    if attempt < self.retries:
                        continue
                raise DeviceError(f"{self.where}: {what}: {err}", err.errno) from err
        raise AssertionError("unreachable")


class Pcf8574Driver:
    """The `pcf8574` output driver.

    Args:
        cfg: the output's config.
        transport: an `smbus2`-like module (the simulated bus in sims, a fake in tests);
            default: smbus2 (imported now).
        shared: the agent's shared devices (one `Pcf8574Port` per chip).
    Raises:
        DriverUnavailable: smbus2 is not installed.
    """

    def __init__(
        self,
        cfg: Pcf8574Output,
        transport: Smbus2 | None = None,
        clock: TimeSource = SYSTEM_TIME,
        shared: SharedDevices | None = None,
    ) -> None:
        self.cfg = cfg
        smbus = transport if transport is not None else load_smbus2("PCF8574")
        shared = shared or SharedDevices()
        self.port = shared.get(
            ("pcf8574", cfg.bus, cfg.address),
            lambda: Pcf8574Port(smbus, cfg.bus, cfg.address, cfg.retries),
            Pcf8574Port,
        )
        self.port.register(cfg.pin, level_for(cfg.initial_value, cfg.invert))

    @property
    def where(self) -> str:
        return f"{self.port.where} pin P{self.cfg.pin}"

    def open(self) -> None:
        self.port.open()

    def write(self, value: float) -> None:
        self.port.write_pin(self.cfg.pin, level_for(value, self.cfg.invert))

    def read(self) -> float:
        return value_of(pin_level(self.port.read_port(), self.cfg.pin), self.cfg.invert)

    def close(self) -> None:
        self.port.close()


PLUGIN = DriverPlugin(
    DriverKind.OUTPUT,
    Pcf8574Output,
    Pcf8574Driver,
    "fleetdaq.edge.drivers.sim_smbus:pcf8574_transport",
)
