"""A barometer on a serial port (RS-232 or USB-serial, ASCII): the `serial_barometer` driver.

The instrument is polled: the host sends ``SEND\\r\\n`` and the barometer answers one line,
``P= 1013.25 hPa\\r\\n`` (the pressure with 0.01 hPa resolution, as Vaisala-style barometers
print it). Its sensor measures 500..1100 hPa; a reading outside that range is flagged
OUT_OF_RANGE. No answer within the port's timeout, or a line that does not parse, makes the
sample COMM_ERROR (with an event), and polling goes on. A port that goes away in use (a
USB-serial adapter unplugged: the kernel answers EIO) is DeviceDisconnected, so the agent
closes and reopens it; a port that is not there on open is DeviceNotFound.

pyserial is imported only when a driver is created without a simulated port.
"""

from __future__ import annotations

import errno
import importlib
import re
from typing import Annotated, Literal, Protocol

from pydantic import Field

from fleetdaq.contract.errors import (
    DeviceDisconnected,
    DeviceError,
    DeviceNotFound,
    DriverUnavailable,
)
from fleetdaq.contract.schema import Channel, Float, Int, Resolution, SimFault, StreamBase, Strict
from fleetdaq.contract.wire import SampleStatus
from fleetdaq.edge.drivers.pacing import SYSTEM_TIME, TimeSource
from fleetdaq.edge.drivers.polled import Poll, PolledDriver

SEND = b"SEND\r\n"
RANGE_HPA = (500.0, 1100.0)
"""What the sensor measures (hPa)."""


class BarometerFault(SimFault):
    """A fault of the simulated barometer."""

    kind: Literal["no_response", "garbled", "unplug"]


class BarometerSim(Strict):
    """A simulated barometer: pressure wandering around `pressure_hpa`."""

    pressure_hpa: Annotated[Float, Field(ge=RANGE_HPA[0], le=RANGE_HPA[1])] = 1013.25
    swing_hpa: Annotated[Float, Field(ge=0, le=50)] = 2.0
    noise_hpa: Annotated[Float, Field(ge=0, le=5)] = 0.02
    seed: Int | None = None
    faults: list[BarometerFault] = Field(default_factory=list)


class SerialBarometerStream(StreamBase):
    """A barometer on a serial port, polled: one channel, the pressure in hPa."""

    driver: Literal["serial_barometer"]
    rate_hz: Annotated[Float, Field(gt=0, le=10)]
    """At most 10 Hz: a poll and its answer take ~20 ms at 9600 Bd."""
    channels: Annotated[list[Channel], Field(min_length=1, max_length=1)]
    port: Annotated[str, Field(min_length=1)] = "/dev/ttyUSB0"
    baudrate: Literal[1200, 2400, 4800, 9600, 19200, 38400, 57600, 115200] = 9600
    timeout_s: Annotated[Float, Field(gt=0, le=5)] = 0.5
    """How long to wait for an answer before the sample is COMM_ERROR."""
    sim: BarometerSim | None = None

    def resolutions(self) -> tuple[Resolution | None, ...]:
        """0.01 hPa over the sensor's range."""
        return (Resolution(0.01, *RANGE_HPA),)


class SerialPort(Protocol):
    """What the driver uses of a `serial.Serial`."""

    def write(self, data: bytes, /) -> int | None: ...

    def readline(self) -> bytes: ...

    def close(self) -> None: ...


class PortOpener(Protocol):
    def __call__(self, port: str, baudrate: int, timeout: float) -> SerialPort: ...


_LINE = re.compile(rb"^P=\s*(-?\d{1,4}\.\d{2})\s+hPa\r?\n$")


def decode_line(line: bytes) -> float:
    """The pressure (hPa) in one answer line. Raises ValueError for a line it cannot be."""
    m = _LINE.match(line)
    if m is None:
        raise ValueError(f"not a pressure line: {line!r}")
    return float(m.group(1))


def encode_line(pressure_hpa: float) -> bytes:
    """The line the barometer sends for this pressure (what the simulator answers)."""
    return f"P= {pressure_hpa:7.2f} hPa\r\n".encode()


def load_pyserial() -> PortOpener:
    """pyserial's port opener, imported now; DriverUnavailable (one line) when missing."""
    try:
        serial = importlib.import_module("serial")
    except ImportError as err:
        raise DriverUnavailable(
            "the serial barometer needs pyserial: `pip install fleetdaq-driver-example[serial]`"
        ) from err

    def opener(port: str, baudrate: int, timeout: float) -> SerialPort:
        opened: SerialPort = serial.Serial(port, baudrate=baudrate, timeout=timeout)
        return opened

    return opener


class SerialBarometer(PolledDriver):
    """The `serial_barometer` driver.

    Args:
        cfg: the stream's config.
        transport: opens the port (the simulated barometer in sims); default: pyserial's.
        clock: host clocks (a VirtualTime in tests).
    Raises:
        DriverUnavailable: pyserial is not installed.
    """

    fault_tag = "barometer_fault"

    def __init__(
        self,
        cfg: SerialBarometerStream,
        transport: PortOpener | None = None,
        clock: TimeSource = SYSTEM_TIME,
    ) -> None:
        super().__init__(cfg.rate_hz, cfg.batch_scans, 1, clock)
        self.cfg = cfg
        self._open_port = transport if transport is not None else load_pyserial()
        self._port: SerialPort | None = None

    @property
    def where(self) -> str:
        return f"barometer on {self.cfg.port}"

    def connect(self) -> None:
        try:
            self._port = self._open_port(self.cfg.port, self.cfg.baudrate, self.cfg.timeout_s)
        except OSError as err:  # pyserial's SerialException is an OSError keeping the errno
            if err.errno == errno.ENOENT:
                raise DeviceNotFound(f"{self.where}: no such port", err.errno) from err
            raise DeviceError(f"{self.where}: cannot open: {err}", err.errno) from err

    def poll(self) -> Poll:
        port = self._port
        if port is None:
            raise InterruptedError("driver closed")
        try:
            port.write(SEND)
            line = port.readline()
        except OSError as err:
            raise DeviceDisconnected(f"{self.where}: port gone: {err}", err.errno) from err
        bad = (SampleStatus.COMM_ERROR,)
        if not line:
            return Poll((0.0,), bad, "no answer", f"within {self.cfg.timeout_s:g} s")
        try:
            hpa = decode_line(line)
        except ValueError as err:
            return Poll((0.0,), bad, "bad answer", str(err))
        if not RANGE_HPA[0] <= hpa <= RANGE_HPA[1]:
            return Poll((hpa,), (SampleStatus.OUT_OF_RANGE,), "outside the sensor's range")
        return Poll((hpa,), (SampleStatus.VALID,))

    def disconnect(self) -> None:
        port, self._port = self._port, None
        if port is not None:
            port.close()
