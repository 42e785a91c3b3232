"""MCP4725 12-bit I2C DAC as an analog output: the `mcp4725` output driver.

Datasheet: Microchip MCP4725, DS22039D (2009).

- Address (6.0): device code 1100, A2 A1 set at the factory, A0 by its pin: 0x60-0x67.
- Output (Equation 4-1): VOUT = VREF * code / 4096, VREF being the supply VDD; 12-bit code.
- Fast write (6.1.1, Figure 6-1): two bytes, ``0 0 PD1 PD0 D11 D10 D9 D8`` and ``D7..D0``;
  updates the DAC register only (the EEPROM is untouched, so every command can use it).
- Write DAC register (6.1.2) and write DAC register and EEPROM (6.1.3), Figure 6-2: three
  bytes, ``C2 C1 C0 X X PD1 PD0 X`` (C = 010 / 011), ``D11..D4``, ``D3 D2 D1 D0 X X X X``.
  During an EEPROM write RDY/BSY reads 0 and any new write is ignored.
- Read (6.2, Figure 6-3): five bytes: status ``RDY/BSY POR X X X PD1 PD0 X``, the DAC
  register ``D11..D4``, ``D3..D0 X X X X``, then the EEPROM ``X PD1 PD0 X D11..D8``, ``D7..D0``.
- Power-down bits PD1 PD0 (5.2): 00 normal; 01, 10, 11 output off through 1 k, 100 k, 500 k.
  At power-on the DAC register is loaded from the EEPROM.

Readback is the DAC register read from the chip (the code actually held, as volts). With
`power_on_safe` (default) the EEPROM holds the safe value, so the chip powers up at it even
when the edge is gone; it is written only when it differs (EEPROM endurance).
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from dataclasses import dataclass
from typing import Annotated, Literal, TypeVar

from pydantic import AfterValidator, Field, model_validator

from fleetdaq.contract.drivers import DriverKind, DriverPlugin
from fleetdaq.contract.errors import DeviceError
from fleetdaq.contract.schema import Float, Int, OutputBase, Strict
from fleetdaq.edge.drivers.i2cbus import I2cBus, I2cFault, Smbus2, is_nack, load_smbus2, open_bus
from fleetdaq.edge.drivers.pacing import SYSTEM_TIME, TimeSource
from fleetdaq.edge.drivers.shared import SharedDevices

FULL_SCALE = 4096
MAX_CODE = 4095
WRITE_DAC = 0b010
WRITE_DAC_EEPROM = 0b011
EEPROM_WRITE_S = 0.05
"""EEPROM write time, at most 50 ms (datasheet Table 1-1, TWRITE)."""


def _mcp4725_address(value: int) -> int:
    if not 0x60 <= value <= 0x67:
        raise ValueError(f"0x{value:02X} is not an MCP4725 address (0x60-0x67)")
    return value


class Mcp4725Sim(Strict):
    """A simulated MCP4725 (edge/drivers/sim_smbus.py)."""

    eeprom_code: Annotated[Int, Field(ge=0, le=MAX_CODE)] = 0
    """What the chip's EEPROM holds when the simulation starts (loaded at power-on)."""
    faults: list[I2cFault] = []


class Mcp4725Output(OutputBase):
    """An MCP4725 12-bit DAC on I2C: 0..vref volts."""

    driver: Literal["mcp4725"]
    kind: Literal["analog"] = "analog"
    unit: str = "V"
    bus: Annotated[Int, Field(ge=0, le=255)] = 1
    address: Annotated[Int, AfterValidator(_mcp4725_address)] = 0x60
    vref: Annotated[Float, Field(gt=0, le=5.5)] = 3.3
    """The chip's supply VDD (its reference), volts: 3.3 on a Pi's 3V3 rail."""
    power_on_safe: bool = True
    """Keep the safe value in the chip's EEPROM, so it powers up safe."""
    retries: Annotated[Int, Field(ge=0, le=10)] = 2
    sim: Mcp4725Sim | None = None

    @property
    def device_span(self) -> tuple[float, float]:
        return (0.0, self.vref)

    @model_validator(mode="after")
    def _unit_is_volts(self) -> Mcp4725Output:
        if self.unit != "V":
            raise ValueError(f"unit: an MCP4725 output is in volts (V), got {self.unit!r}")
        return self

    @property
    def resource(self) -> str:
        return f"the MCP4725 at 0x{self.address:02X} on I2C bus {self.bus}"


@dataclass(frozen=True, slots=True)
class Mcp4725Status:
    """The five bytes of a read (6.2)."""

    ready: bool
    """RDY/BSY: False while an EEPROM write is in progress."""
    por: bool
    power_down: int
    code: int
    eeprom_power_down: int
    eeprom_code: int


def volts_to_code(volts: float, vref: float) -> int:
    return min(MAX_CODE, max(0, round(volts / vref * FULL_SCALE)))


def code_to_volts(code: int, vref: float) -> float:
    return code * vref / FULL_SCALE


def fast_write(code: int, power_down: int = 0) -> bytes:
    """The two bytes of a fast-mode write (6.1.1)."""
    if not 0 <= code <= MAX_CODE or not 0 <= power_down <= 3:
        raise ValueError(f"code {code} / power-down {power_down} out of range")
    return bytes([power_down << 4 | code >> 8, code & 0xFF])


def write_dac(code: int, eeprom: bool = False, power_down: int = 0) -> bytes:
    """The three bytes of "write DAC register" (6.1.2), or "... and EEPROM" (6.1.3)."""
    if not 0 <= code <= MAX_CODE or not 0 <= power_down <= 3:
        raise ValueError(f"code {code} / power-down {power_down} out of range")
    command = WRITE_DAC_EEPROM if eeprom else WRITE_DAC
    return bytes([command << 5 | power_down << 1, code >> 4, (code & 0x0F) << 4])


def decode_mcp4725(data: bytes) -> Mcp4725Status:
    """Decode the five bytes of a read (6.2). Raises ValueError for anything else."""
    if len(data) != 5:
        raise ValueError(f"an MCP4725 read is 5 bytes, got {len(data)}")
    status, hi, lo, e_hi, e_lo = data
    return Mcp4725Status(
        ready=bool(status & 0x80),
        por=bool(status & 0x40),
        power_down=status >> 1 & 0x3,
        code=hi << 4 | lo >> 4,
        eeprom_power_down=e_hi >> 5 & 0x3,
        eeprom_code=(e_hi & 0x0F) << 8 | e_lo,
    )


_T = TypeVar("_T")


class Mcp4725Driver:
    """The `mcp4725` output driver.

    Args:
        cfg: the output's config.
        transport: an `smbus2`-like module (the simulated bus in sims, a fake in tests);
            default: smbus2 (imported now).
        clock: where it waits for an EEPROM write (a VirtualTime in tests).
    Raises:
        DriverUnavailable: smbus2 is not installed.
    """

    def __init__(
        self,
        cfg: Mcp4725Output,
        transport: Smbus2 | None = None,
        clock: TimeSource = SYSTEM_TIME,
        shared: SharedDevices | None = None,
    ) -> None:
        self.cfg = cfg
        self.clock = clock
        self.smbus = transport if transport is not None else load_smbus2("MCP4725")
        self._bus: I2cBus | None = None
        self.lock = threading.Lock()
        self.eeprom_writes = 0
        self._never = threading.Event()

    @property
    def where(self) -> str:
        return f"MCP4725 0x{self.cfg.address:02X} on /dev/i2c-{self.cfg.bus}"

    def open(self) -> None:
        with self.lock:
            if self._bus is None:
                self._bus = open_bus(self.smbus, self.cfg.bus)
        if self.cfg.power_on_safe:
            self._keep_safe_in_eeprom()

    def write(self, value: float) -> None:
        code = volts_to_code(value, self.cfg.vref)
        self._io(
            lambda bus: bus.i2c_rdwr(self.smbus.i2c_msg.write(self.cfg.address, fast_write(code))),
            "write",
        )

    def read(self) -> float:
        return code_to_volts(self.status().code, self.cfg.vref)

    def status(self) -> Mcp4725Status:
        def op(bus: I2cBus) -> bytes:
            msg = self.smbus.i2c_msg.read(self.cfg.address, 5)
            bus.i2c_rdwr(msg)
            return bytes(msg)

        data = self._io(op, "read")
        try:
            return decode_mcp4725(data)
        except ValueError as err:
            raise DeviceError(f"{self.where}: {err}") from err

    def close(self) -> None:
        with self.lock:
            bus, self._bus = self._bus, None
            if bus is not None:
                bus.close()

    def _keep_safe_in_eeprom(self) -> None:
        safe = volts_to_code(self.cfg.safe, self.cfg.vref)
        now = self.status()
        if now.eeprom_code == safe and now.eeprom_power_down == 0:
            return
        data = write_dac(safe, eeprom=True)
        self._io(
            lambda bus: bus.i2c_rdwr(self.smbus.i2c_msg.write(self.cfg.address, data)),
            "write EEPROM",
        )
        self.eeprom_writes += 1
        deadline = self.clock.monotonic_ns() + int(4 * EEPROM_WRITE_S * 1e9)
        while not self.status().ready:  # writes are ignored until the EEPROM write is done
            if self.clock.monotonic_ns() > deadline:
                raise DeviceError(f"{self.where}: EEPROM write did not complete")
            self.clock.sleep_until(self.clock.monotonic_ns() + 5_000_000, self._never)

    def _io(self, op: Callable[[I2cBus], _T], what: str) -> _T:
        with self.lock:
            if self._bus is None:
                self._bus = open_bus(self.smbus, self.cfg.bus)
            for attempt in range(self.cfg.retries + 1):
                try:
                    return op(self._bus)
                except OSError as err:
                    if is_nack(err) and attempt < self.cfg.retries:
                        continue
                    raise DeviceError(f"{self.where}: {what}: {err}", err.errno) from err
        raise AssertionError("unreachable")


PLUGIN = DriverPlugin(
    DriverKind.OUTPUT,
    Mcp4725Output,
    Mcp4725Driver,
    "fleetdaq.edge.drivers.sim_smbus:mcp4725_transport",
)
