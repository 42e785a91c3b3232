"""MAX31855 cold-junction-compensated thermocouple-to-digital converter on SPI (spidev).

The chip is read-only: each read clocks out one 32-bit frame (datasheet, "Serial Interface"):

    D31-D18  thermocouple temperature, 14-bit two's complement, 0.25 °C
    D17      reserved (0)
    D16      fault: 1 when any of SCV, SCG, OC is set
    D15-D4   internal (cold-junction) temperature, 12-bit two's complement, 0.0625 °C
    D3       reserved (0)
    D2 SCV   thermocouple shorted to VCC
    D1 SCG   thermocouple shorted to GND
    D0 OC    thermocouple open (no connection)

SPI mode 0, SCK up to 5 MHz; a conversion takes up to 100 ms, so reads go at most at 10 Hz.
A fault makes the thermocouple sample invalid (with an event); the cold junction stays valid.
A frame that breaks the datasheet's rules (reserved bits set, fault bits without D16, MISO
floating high) is a bus error: both samples invalid.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Annotated, Literal

from pydantic import Field

from fleetdaq.contract.drivers import DriverKind, DriverPlugin
from fleetdaq.contract.schema import (
    Channel,
    Float,
    Int,
    Name,
    Resolution,
    SimFault,
    StreamBase,
    Strict,
)
from fleetdaq.contract.wire import SampleStatus
from fleetdaq.edge.drivers.pacing import SYSTEM_TIME, TimeSource
from fleetdaq.edge.drivers.polled import Poll, PolledDriver
from fleetdaq.edge.drivers.spibus import SpiDev, SpiDevice, SpiFactory, load_spidev, open_spi

log = logging.getLogger("fleetdaq.drivers.max31855")


class TcFault(SimFault):
    kind: Literal["open_circuit", "short_gnd", "short_vcc", "no_response"]


class WeldThermalModel(Strict):
    """A simulated thermocouple on a weld cell: heats during each layer, cools between layers."""

    ambient_c: Float = 25.0
    peak_c: Float = 450.0
    layer_s: Annotated[Float, Field(gt=0)] = 20.0
    cool_s: Annotated[Float, Field(gt=0)] = 15.0
    noise_c: Annotated[Float, Field(ge=0)] = 0.3
    seed: Int | None = None
    cell: Name | None = None
    """The simulated weld cell whose robot heats it (a `weld_robot_sim` stream of this node):
    it heats while the robot welds and cools otherwise, instead of the fixed layer_s/cool_s
    cycle."""


class ThermocoupleSim(WeldThermalModel):
    faults: list[TcFault] = []


class Max31855Stream(StreamBase, SpiDevice):
    """MAX31855 on SPI: channel 0 the thermocouple, channel 1 (optional) the cold junction."""

    driver: Literal["max31855"]
    rate_hz: Annotated[Float, Field(gt=0, le=10)]
    """At most 10 Hz: a conversion takes up to 100 ms (datasheet, tCONV)."""
    channels: Annotated[list[Channel], Field(min_length=1, max_length=2)]
    sim: ThermocoupleSim | None = None

    def resolutions(self) -> tuple[Resolution | None, ...]:
        """Thermocouple: 14-bit two's complement, 0.25 °C; cold junction: 12-bit, 0.0625 °C."""
        return (Resolution.bits(14, -2048.0, 2048.0), Resolution.bits(12, -128.0, 128.0))[
            : len(self.channels)
        ]


SPI_MODE = 0
_FAULT = 1 << 16
_RESERVED = (1 << 17) | (1 << 3)


@dataclass(frozen=True, slots=True)
class Max31855Reading:
    """One decoded frame."""

    thermocouple_c: float
    cold_junction_c: float
    fault: bool
    open_circuit: bool
    short_gnd: bool
    short_vcc: bool

    @property
    def status(self) -> int:
        """SampleStatus of the thermocouple sample."""
        if self.open_circuit:
            return SampleStatus.OPEN_CIRCUIT
        if self.short_gnd:
            return SampleStatus.SHORT_GND
        if self.short_vcc:
            return SampleStatus.SHORT_VCC
        return SampleStatus.DEVICE_FAULT if self.fault else SampleStatus.VALID

    @property
    def problem(self) -> str | None:
        faults = [
            name
            for flag, name in (
                (self.open_circuit, "thermocouple open (OC)"),
                (self.short_gnd, "thermocouple shorted to GND (SCG)"),
                (self.short_vcc, "thermocouple shorted to VCC (SCV)"),
            )
            if flag
        ]
        if faults:
            return ", ".join(faults)
        return "fault bit set" if self.fault else None


def _signed(value: int, bits: int) -> int:
    return value - (1 << bits) if value & (1 << (bits - 1)) else value


def decode_max31855(frame: bytes | Sequence[int]) -> Max31855Reading:
    """Decode a 4-byte frame (MSB first). Raises ValueError for a frame the chip cannot send."""
    data = bytes(frame)
    if len(data) != 4:
        raise ValueError(f"a MAX31855 frame is 4 bytes, got {len(data)}")
    word = int.from_bytes(data, "big")
    if word & _RESERVED:
        raise ValueError(f"reserved bits set in frame 0x{word:08X} (no chip, or MISO floating)")
    flags = word & 0b111
    fault = bool(word & _FAULT)
    if flags and not fault:
        raise ValueError(f"fault bits without the fault flag in frame 0x{word:08X}")
    return Max31855Reading(
        thermocouple_c=_signed(word >> 18, 14) * 0.25,
        cold_junction_c=_signed((word >> 4) & 0xFFF, 12) * 0.0625,
        fault=fault,
        open_circuit=bool(flags & 0b001),
        short_gnd=bool(flags & 0b010),
        short_vcc=bool(flags & 0b100),
    )


def encode_max31855(
    thermocouple_c: float,
    cold_junction_c: float,
    open_circuit: bool = False,
    short_gnd: bool = False,
    short_vcc: bool = False,
) -> bytes:
    """The frame a MAX31855 sends for these readings (what the simulated chip clocks out)."""
    tc = round(thermocouple_c / 0.25) & 0x3FFF
    cj = round(cold_junction_c / 0.0625) & 0xFFF
    flags = int(open_circuit) | int(short_gnd) << 1 | int(short_vcc) << 2
    word = tc << 18 | (_FAULT if flags else 0) | cj << 4 | flags
    return word.to_bytes(4, "big")


class Max31855(PolledDriver):
    """The `max31855` driver: channel 0 the thermocouple, channel 1 (optional) the cold junction.

    Args:
        cfg: the stream's config.
        transport: makes the SpiDev to use (the simulated chip in sims, a fake in tests);
            default: `spidev.SpiDev` (imported now).
        clock: host clocks (a VirtualTime in tests).
    Raises:
        DriverUnavailable: spidev is not installed.
    """

    fault_tag = "thermocouple_fault"

    def __init__(
        self,
        cfg: Max31855Stream,
        transport: SpiFactory | None = None,
        clock: TimeSource = SYSTEM_TIME,
    ) -> None:
        super().__init__(cfg.rate_hz, cfg.batch_scans, len(cfg.channels), clock)
        self.cfg = cfg
        self._factory = transport if transport is not None else load_spidev("MAX31855")
        self._spi: SpiDev | None = None

    @property
    def where(self) -> str:
        return f"MAX31855 on /dev/spidev{self.cfg.bus}.{self.cfg.device}"

    def connect(self) -> None:
        self._spi = open_spi(
            self._factory, self.cfg.bus, self.cfg.device, SPI_MODE, self.cfg.max_speed_hz
        )

    def poll(self) -> Poll:
        if self._spi is None:
            raise InterruptedError("driver closed")
        bad = (SampleStatus.COMM_ERROR,) * self.channels
        try:
            frame = self._spi.xfer2([0, 0, 0, 0])
        except OSError as err:
            return Poll((0.0,) * self.channels, bad, "SPI transfer failed", str(err))
        try:
            r = decode_max31855(frame)
        except ValueError as err:
            return Poll((0.0,) * self.channels, bad, "bad frame", str(err))
        values = (r.thermocouple_c, r.cold_junction_c)[: self.channels]
        status = (r.status, SampleStatus.VALID)[: self.channels]
        return Poll(values, status, r.problem)

    def disconnect(self) -> None:
        spi, self._spi = self._spi, None
        if spi is not None:
            spi.close()


PLUGIN = DriverPlugin(
    DriverKind.STREAM,
    Max31855Stream,
    Max31855,
    "fleetdaq.edge.drivers.sim_spi:max31855_transport",
)
