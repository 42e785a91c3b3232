"""Sensirion SHT3x (SHT30/31/35) humidity and temperature sensor on I2C (smbus2).

Single-shot measurements without clock stretching (datasheet 4.3, Table 9): write the
command (0x2400 high, 0x240B medium, 0x2416 low repeatability), wait the measurement time
(15 / 6 / 4 ms max), then read 6 bytes: T MSB, T LSB, CRC, RH MSB, RH LSB, CRC. A read before
the measurement is done is NACKed. Each 16-bit word carries a CRC-8 (datasheet 4.12:
polynomial 0x31, init 0xFF, no reflection, no final XOR; CRC(0xBEEF) = 0x92). Conversion
(4.13): T = -45 + 175 * S_T / (2^16 - 1) °C, RH = 100 * S_RH / (2^16 - 1) %.

NACKs and CRC mismatches are retried (`retries` more attempts); after that the poll's
samples are invalid (COMM_ERROR) with an event, and polling goes on.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Annotated, Literal

from pydantic import Field

from fleetdaq.contract.drivers import DriverKind, DriverPlugin
from fleetdaq.contract.errors import DeviceError, DeviceNotFound
from fleetdaq.contract.schema import Channel, Float, Int, Resolution, StreamBase, Strict
from fleetdaq.contract.wire import SampleStatus
from fleetdaq.edge.drivers.i2cbus import I2cBus, I2cFault, Smbus2, is_nack, load_smbus2, open_bus
from fleetdaq.edge.drivers.pacing import SYSTEM_TIME, TimeSource
from fleetdaq.edge.drivers.polled import Poll, PolledDriver


class Sht3xSim(Strict):
    """A simulated SHT3x on a pier: temperature and humidity wander slowly."""

    temperature_c: Float = 14.0
    humidity_pct: Annotated[Float, Field(ge=0, le=100)] = 78.0
    seed: Int | None = None
    faults: list[I2cFault] = []


class Sht3xStream(StreamBase):
    """Sensirion SHT3x on I2C: channel 0 temperature (°C), channel 1 (optional) humidity (%RH)."""

    driver: Literal["sht3x"]
    rate_hz: Annotated[Float, Field(gt=0, le=10)]
    channels: Annotated[list[Channel], Field(min_length=1, max_length=2)]
    bus: Annotated[Int, Field(ge=0, le=255)] = 1
    """/dev/i2c-<bus>."""
    address: Literal[0x44, 0x45] = 0x44
    """0x44 with ADDR to GND, 0x45 with ADDR to VDD."""
    repeatability: Literal["high", "medium", "low"] = "high"
    retries: Annotated[Int, Field(ge=0, le=10)] = 3
    """Extra attempts after a NACK or a CRC mismatch before the sample is marked invalid."""
    sim: Sht3xSim | None = None

    def resolutions(self) -> tuple[Resolution | None, ...]:
        """16-bit words (datasheet 4.13): T = -45 + 175 x / 65535 °C, RH = 100 x / 65535 %."""
        return (Resolution(175 / 65535, -45.0, 130.0), Resolution(100 / 65535, 0.0, 100.0))[
            : len(self.channels)
        ]


COMMANDS = {"high": (0x24, 0x00), "medium": (0x24, 0x0B), "low": (0x24, 0x16)}
MEASUREMENT_S = {"high": 0.0155, "medium": 0.0065, "low": 0.0045}
SOFT_RESET = (0x30, 0xA2)


def crc8(data: bytes | Sequence[int]) -> int:
    """The SHT3x CRC-8 of `data`."""
    crc = 0xFF
    for byte in data:
        crc ^= byte
        for _ in range(8):
            crc = ((crc << 1) ^ 0x31) & 0xFF if crc & 0x80 else (crc << 1) & 0xFF
    return crc


class CrcError(ValueError):
    """A word's CRC does not match."""


@dataclass(frozen=True, slots=True)
class Sht3xReading:
    temperature_c: float
    humidity_pct: float


def decode_sht3x(data: bytes | Sequence[int]) -> Sht3xReading:
    """Decode a 6-byte measurement. Raises CrcError on a CRC mismatch."""
    raw = bytes(data)
    if len(raw) != 6:
        raise ValueError(f"an SHT3x measurement is 6 bytes, got {len(raw)}")
    for name, word, crc in (("temperature", raw[0:2], raw[2]), ("humidity", raw[3:5], raw[5])):
        if crc8(word) != crc:
            raise CrcError(f"{name} CRC 0x{crc:02X}, expected 0x{crc8(word):02X}")
    s_t = int.from_bytes(raw[0:2], "big")
    s_rh = int.from_bytes(raw[3:5], "big")
    return Sht3xReading(-45.0 + 175.0 * s_t / 65535.0, 100.0 * s_rh / 65535.0)


def encode_sht3x(temperature_c: float, humidity_pct: float) -> bytes:
    """The 6 bytes an SHT3x sends for these values (what the simulated sensor answers)."""
    s_t = min(max(round((temperature_c + 45.0) * 65535.0 / 175.0), 0), 65535).to_bytes(2, "big")
    s_rh = min(max(round(humidity_pct * 65535.0 / 100.0), 0), 65535).to_bytes(2, "big")
    return s_t + bytes([crc8(s_t)]) + s_rh + bytes([crc8(s_rh)])


class Sht3x(PolledDriver):
    """The `sht3x` driver: channel 0 temperature (°C), channel 1 (optional) humidity (%RH).

    Args:
        cfg: the stream's config.
        transport: an `smbus2`-like module (the simulated sensor's bus in sims, a fake in
            tests); default: smbus2 (imported now).
        clock: host clocks (a VirtualTime in tests).
    Raises:
        DriverUnavailable: smbus2 is not installed.
    """

    fault_tag = "sensor_fault"

    def __init__(
        self, cfg: Sht3xStream, transport: Smbus2 | None = None, clock: TimeSource = SYSTEM_TIME
    ) -> None:
        super().__init__(cfg.rate_hz, cfg.batch_scans, len(cfg.channels), clock)
        self.cfg = cfg
        self.smbus = transport if transport is not None else load_smbus2("SHT3x")
        self._bus: I2cBus | None = None
        self.retries = 0
        self.crc_errors = 0
        self.nacks = 0

    @property
    def where(self) -> str:
        return f"SHT3x at 0x{self.cfg.address:02X} on /dev/i2c-{self.cfg.bus}"

    def connect(self) -> None:
        bus = open_bus(self.smbus, self.cfg.bus)
        try:
            bus.i2c_rdwr(self.smbus.i2c_msg.write(self.cfg.address, list(SOFT_RESET)))
        except OSError as err:
            bus.close()
            if is_nack(err):
                raise DeviceNotFound(f"{self.where}: no answer (NACK)", err.errno) from err
            raise DeviceError(f"{self.where}: {err}", err.errno) from err
        self._bus = bus
        self._sleep(0.002)  # soft reset: 1.5 ms max (datasheet Table 4)

    def poll(self) -> Poll:
        problem, detail = "", ""
        for attempt in range(self.cfg.retries + 1):
            if attempt:
                self.retries += 1
            try:
                return self._measure()
            except CrcError as err:
                self.crc_errors += 1
                problem, detail = "CRC error", str(err)
            except OSError as err:
                self.nacks += is_nack(err)
                problem, detail = ("NACK" if is_nack(err) else "bus error"), str(err)
        bad = (SampleStatus.COMM_ERROR,) * self.channels
        detail = f"{detail}; {self.cfg.retries + 1} attempt(s)"
        return Poll((0.0,) * self.channels, bad, problem, detail)

    def _measure(self) -> Poll:
        bus = self._bus
        if bus is None:
            raise InterruptedError("driver closed")
        msg = self.smbus.i2c_msg
        bus.i2c_rdwr(msg.write(self.cfg.address, list(COMMANDS[self.cfg.repeatability])))
        self._sleep(MEASUREMENT_S[self.cfg.repeatability])
        read = msg.read(self.cfg.address, 6)
        bus.i2c_rdwr(read)
        r = decode_sht3x(bytes(read))
        values = (r.temperature_c, r.humidity_pct)[: self.channels]
        return Poll(values, (SampleStatus.VALID,) * self.channels)

    def _sleep(self, seconds: float) -> None:
        if not self.clock.sleep_until(
            self.clock.monotonic_ns() + round(seconds * 1e9), self.closing
        ):
            raise InterruptedError("driver closed")

    def disconnect(self) -> None:
        bus, self._bus = self._bus, None
        if bus is not None:
            bus.close()

    def extra_health(self) -> dict[str, object]:
        return {"retries": self.retries, "crc_errors": self.crc_errors, "nacks": self.nacks}


PLUGIN = DriverPlugin(
    DriverKind.STREAM,
    Sht3xStream,
    Sht3x,
    "fleetdaq.edge.drivers.sim_smbus:sht3x_transport",
)
