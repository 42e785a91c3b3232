"""MAX31856 precision thermocouple-to-digital converter with linearization, on SPI (spidev).

Registers (datasheet, "Register Memory Map"); read at 0xh, write at 8xh, auto-incrementing:

    00 CR0   CMODE(7) 1SHOT(6) OCFAULT(5:4) CJ(3) FAULT(2) FAULTCLR(1) 50/60Hz(0)
    01 CR1   AVGSEL(6:4) = 1/2/4/8/16 samples, TC TYPE(3:0) B=0 E=1 J=2 K=3 N=4 R=5 S=6 T=7
    02 MASK  fault mask
    0A-0B    CJTH:CJTL cold junction, 14-bit two's complement left-justified, 0.015625 °C
    0C-0E    LTCBH:LTCBM:LTCBL linearized thermocouple, 19-bit left-justified, 0.0078125 °C
    0F SR    CJ range(7) TC range(6) CJHIGH(5) CJLOW(4) TCHIGH(3) TCLOW(2) OVUV(1) OPEN(0)

SPI mode 1 (data out on SCK rising, read on falling; mode 3 also works), up to 5 MHz. The
driver writes CR0, CR1 and MASK at open and reads them back: a chip that does not echo its
configuration is not there. Each poll reads 0A..0F in one transfer (in one-shot mode it first
starts a conversion and waits for it). The fault status register makes samples invalid: OPEN
= open circuit, OVUV = device fault, range and threshold faults = out of range.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Annotated, Literal

from pydantic import Field, model_validator

from fleetdaq.contract.drivers import DriverKind, DriverPlugin
from fleetdaq.contract.errors import DeviceNotFound
from fleetdaq.contract.schema import Channel, Float, Resolution, SimFault, StreamBase
from fleetdaq.contract.wire import SampleStatus
from fleetdaq.edge.drivers.max31855 import WeldThermalModel
from fleetdaq.edge.drivers.pacing import SYSTEM_TIME, TimeSource
from fleetdaq.edge.drivers.polled import Poll, PolledDriver
from fleetdaq.edge.drivers.spibus import SpiDev, SpiDevice, SpiFactory, load_spidev, open_spi


class Tc56Fault(SimFault):
    kind: Literal["open_circuit", "tc_range", "cj_range", "overvoltage", "no_response"]


class Max31856Sim(WeldThermalModel):
    faults: list[Tc56Fault] = []


MAX31856_TYPES = ("B", "E", "J", "K", "N", "R", "S", "T")


class Max31856Stream(StreamBase, SpiDevice):
    """MAX31856 on SPI: thermocouple type, averaging, filter and conversion mode configured."""

    driver: Literal["max31856"]
    rate_hz: Annotated[Float, Field(gt=0, le=12)]
    channels: Annotated[list[Channel], Field(min_length=1, max_length=2)]
    thermocouple: Literal["B", "E", "J", "K", "N", "R", "S", "T"] = "K"
    averaging: Literal[1, 2, 4, 8, 16] = 1
    mains_hz: Literal[50, 60] = 50
    """The notch of the input filter: the local mains frequency."""
    conversion: Literal["continuous", "one_shot"] = "continuous"
    sim: Max31856Sim | None = None

    def resolutions(self) -> tuple[Resolution | None, ...]:
        """Thermocouple: 19-bit two's complement, 2^-7 °C; cold junction: 14-bit, 2^-6 °C."""
        return (Resolution.bits(19, -2048.0, 2048.0), Resolution.bits(14, -128.0, 128.0))[
            : len(self.channels)
        ]

    @property
    def conversion_s(self) -> float:
        """Longest conversion time (datasheet, Electrical Characteristics: tCONV)."""
        first = {("continuous", 60): 0.090, ("continuous", 50): 0.100}.get(
            (self.conversion, self.mains_hz), 0.155 if self.mains_hz == 60 else 0.185
        )
        return first + (self.averaging - 1) * (0.03333 if self.mains_hz == 60 else 0.040)

    @model_validator(mode="after")
    def _rate_within_conversion_time(self) -> Max31856Stream:
        limit = 1.0 / self.conversion_s
        if self.rate_hz > limit:
            raise ValueError(
                f"rate_hz {self.rate_hz:g} is faster than a {self.conversion} conversion with "
                f"averaging {self.averaging} at {self.mains_hz} Hz allows ({limit:.2f} Hz)"
            )
        return self


SPI_MODE = 1
WRITE = 0x80
CR0, CR1, MASK, CJTH, SR = 0x00, 0x01, 0x02, 0x0A, 0x0F
CR0_CMODE, CR0_1SHOT, CR0_OCFAULT_01, CR0_50HZ = 0x80, 0x40, 0x10, 0x01
AVGSEL = {1: 0, 2: 1, 4: 2, 8: 3, 16: 4}
# Fault status register bits.
SR_CJRANGE, SR_TCRANGE, SR_CJHIGH, SR_CJLOW = 0x80, 0x40, 0x20, 0x10
SR_TCHIGH, SR_TCLOW, SR_OVUV, SR_OPEN = 0x08, 0x04, 0x02, 0x01
_SR_NAMES = (
    (SR_CJRANGE, "cold junction out of range"),
    (SR_TCRANGE, "thermocouple out of range"),
    (SR_CJHIGH, "cold junction above its high threshold"),
    (SR_CJLOW, "cold junction below its low threshold"),
    (SR_TCHIGH, "thermocouple above its high threshold"),
    (SR_TCLOW, "thermocouple below its low threshold"),
    (SR_OVUV, "over/under voltage on the inputs (OVUV)"),
    (SR_OPEN, "thermocouple open (OPEN)"),
)


@dataclass(frozen=True, slots=True)
class Max31856Reading:
    """Registers 0A..0F decoded."""

    thermocouple_c: float
    cold_junction_c: float
    fault_status: int

    @property
    def thermocouple_status(self) -> int:
        sr = self.fault_status
        if sr & SR_OPEN:
            return SampleStatus.OPEN_CIRCUIT
        if sr & SR_OVUV:
            return SampleStatus.DEVICE_FAULT
        if sr & (SR_TCRANGE | SR_TCHIGH | SR_TCLOW | SR_CJRANGE):
            return SampleStatus.OUT_OF_RANGE  # a CJ out of range spoils the compensation too
        return SampleStatus.VALID

    @property
    def cold_junction_status(self) -> int:
        sr = self.fault_status
        if sr & SR_OVUV:
            return SampleStatus.DEVICE_FAULT
        if sr & (SR_CJRANGE | SR_CJHIGH | SR_CJLOW):
            return SampleStatus.OUT_OF_RANGE
        return SampleStatus.VALID

    @property
    def problem(self) -> str | None:
        names = [name for bit, name in _SR_NAMES if self.fault_status & bit]
        return ", ".join(names) if names else None


def decode_max31856(registers: bytes | Sequence[int]) -> Max31856Reading:
    """Decode the six registers CJTH, CJTL, LTCBH, LTCBM, LTCBL, SR (0x0A..0x0F)."""
    data = bytes(registers)
    if len(data) != 6:
        raise ValueError(f"expected the 6 registers 0x0A..0x0F, got {len(data)} bytes")
    cj = int.from_bytes(data[0:2], "big", signed=True) >> 2  # 14 bits, 2^-6 °C
    tc = int.from_bytes(data[2:5], "big", signed=True) >> 5  # 19 bits, 2^-7 °C
    return Max31856Reading(tc * 0.0078125, cj * 0.015625, data[5])


def encode_max31856(thermocouple_c: float, cold_junction_c: float, fault_status: int = 0) -> bytes:
    """Registers 0x0A..0x0F as the chip holds them for these readings."""
    cj = (round(cold_junction_c / 0.015625) & 0x3FFF) << 2
    tc = (round(thermocouple_c / 0.0078125) & 0x7FFFF) << 5
    return cj.to_bytes(2, "big") + tc.to_bytes(3, "big") + bytes([fault_status & 0xFF])


def config_registers(cfg: Max31856Stream) -> tuple[int, int, int]:
    """CR0, CR1, MASK for a stream's config."""
    cr0 = CR0_OCFAULT_01 | (CR0_50HZ if cfg.mains_hz == 50 else 0)
    if cfg.conversion == "continuous":
        cr0 |= CR0_CMODE
    cr1 = AVGSEL[cfg.averaging] << 4 | MAX31856_TYPES.index(cfg.thermocouple)
    return cr0, cr1, 0x00  # MASK 0: every fault asserts the FAULT pin


class Max31856(PolledDriver):
    """The `max31856` driver: channel 0 the thermocouple, channel 1 (optional) the cold junction.

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
        cfg: Max31856Stream,
        transport: SpiFactory | None = None,
        clock: TimeSource = SYSTEM_TIME,
    ) -> None:
        super().__init__(cfg.rate_hz, cfg.batch_scans, len(cfg.channels), clock)
        self.cfg = cfg
        self._factory = transport if transport is not None else load_spidev("MAX31856")
        self._spi: SpiDev | None = None
        self.registers = config_registers(cfg)

    @property
    def where(self) -> str:
        return f"MAX31856 on /dev/spidev{self.cfg.bus}.{self.cfg.device}"

    def connect(self) -> None:
        spi = open_spi(
            self._factory, self.cfg.bus, self.cfg.device, SPI_MODE, self.cfg.max_speed_hz
        )
        cr0, cr1, mask = self.registers
        try:
            spi.xfer2([WRITE | CR0, cr0, cr1, mask])
            echo = spi.xfer2([CR0, 0, 0, 0])[1:]
        except OSError as err:
            spi.close()
            raise DeviceNotFound(f"{self.where}: SPI transfer failed: {err}", err.errno) from err
        if [echo[0] & ~CR0_1SHOT & 0xFF, echo[1], echo[2]] != [cr0, cr1, mask]:
            spi.close()
            raise DeviceNotFound(
                f"{self.where}: no MAX31856 answering (wrote CR0/CR1/MASK "
                f"{cr0:02X} {cr1:02X} {mask:02X}, read back {' '.join(f'{b:02X}' for b in echo)})"
            )
        self._spi = spi

    def poll(self) -> Poll:
        spi = self._spi
        if spi is None:
            raise InterruptedError("driver closed")
        bad = (SampleStatus.COMM_ERROR,) * self.channels
        try:
            if self.cfg.conversion == "one_shot":
                spi.xfer2([WRITE | CR0, self.registers[0] | CR0_1SHOT])
                done = self.clock.monotonic_ns() + round(self.cfg.conversion_s * 1e9)
                if not self.clock.sleep_until(done, self.closing):
                    raise InterruptedError("driver closed")
            data = spi.xfer2([CJTH, 0, 0, 0, 0, 0, 0])[1:]
        except OSError as err:
            return Poll((0.0,) * self.channels, bad, "SPI transfer failed", str(err))
        if all(b == 0xFF for b in data):
            return Poll((0.0,) * self.channels, bad, "no response (MISO reads all ones)")
        r = decode_max31856(data)
        values = (r.thermocouple_c, r.cold_junction_c)[: self.channels]
        status = (r.thermocouple_status, r.cold_junction_status)[: self.channels]
        return Poll(values, status, r.problem)

    def disconnect(self) -> None:
        spi, self._spi = self._spi, None
        if spi is not None:
            spi.close()


PLUGIN = DriverPlugin(
    DriverKind.STREAM,
    Max31856Stream,
    Max31856,
    "fleetdaq.edge.drivers.sim_spi:max31856_transport",
)
