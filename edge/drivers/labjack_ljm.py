"""The LabJack T8 over LJM (labjack-ljm), shared by its drivers: the device handle and LJM error
wrapping, the CORE_TIMER unwrapping, the T8's DAC and DIO outputs, and the config the T8
drivers share (connection, analog ranges, the simulated T8).

The drivers: `labjack_t8` (stream mode) and `labjack_t8_poll` (slow polled I/O). The vendor
module is imported when a driver is created without a simulated transport, never at import of
these modules; without LJM's native library that fails with one line saying what to install.
"""

from __future__ import annotations

import contextlib
import importlib
import io
import re
import threading
from collections.abc import Callable, Sequence
from typing import Annotated, Concatenate, Literal, ParamSpec, Protocol, TypeVar, cast

import numpy as np
import numpy.typing as npt
from pydantic import BeforeValidator, Field

from fleetdaq.contract.errors import (
    DeviceDisconnected,
    DeviceError,
    DeviceNotFound,
    DriverError,
    DriverUnavailable,
)
from fleetdaq.contract.schema import Float, Int, SimFault, Strict, as_identifier
from fleetdaq.edge.drivers.pacing import SYSTEM_TIME, TimeSource

T8_ADC_BITS = 24
"""One 24-bit sigma-delta ADC per analog input: its codes span the channel's ±range."""
T8_RANGES = (11.0, 9.6, 4.8, 2.4, 1.2, 0.6, 0.3, 0.15, 0.075, 0.036, 0.018)
"""The T8's AIN#_RANGE values (± volts), T-Series datasheet 14.3.2 / A-3-3-3."""
T8_MAX_SAMPLE_RATE = 400_000
"""T8 stream: samples per second over the whole scan list (datasheet 14.3.2, A-1)."""


class LjmErrorCodes(Protocol):
    """``labjack.ljm.errorcodes``: the codes the drivers test for (all are read by name)."""

    INVALID_HANDLE: int
    DEVICE_NOT_OPEN: int
    STREAM_NOT_RUNNING: int


class LjmConstants(Protocol):
    """``labjack.ljm.constants``: the ones the drivers use."""

    DUMMY_VALUE: int


class Ljm(Protocol):
    """The ``labjack.ljm`` module as the T8 drivers call it, or a stand-in with the same
    signatures (`fleetdaq.edge.drivers.sim_ljm.SimLJM`, a test's fake): the transport a T8
    driver's constructor takes. Every call raises `LJMError` (with `errorCode`) on failure."""

    @property
    def LJMError(self) -> type[Exception]: ...

    @property
    def errorcodes(self) -> LjmErrorCodes: ...

    @property
    def constants(self) -> LjmConstants: ...

    def openS(self, deviceType: str, connectionType: str, identifier: str, /) -> int: ...

    def close(self, handle: int, /) -> None: ...

    def eWriteName(self, handle: int, name: str, value: float, /) -> None: ...

    def eWriteNames(
        self, handle: int, numFrames: int, aNames: Sequence[str], aValues: Sequence[float], /
    ) -> None: ...

    def eReadName(self, handle: int, name: str, /) -> float: ...

    def eReadNames(self, handle: int, numFrames: int, aNames: Sequence[str], /) -> list[float]: ...

    def namesToAddresses(
        self, numFrames: int, aNames: Sequence[str], /
    ) -> tuple[list[int], list[int]]: ...

    def eStreamStart(
        self,
        handle: int,
        scansPerRead: int,
        numAddresses: int,
        aScanList: Sequence[int],
        scanRate: float,
        /,
    ) -> float: ...

    def eStreamStop(self, handle: int, /) -> None: ...

    def eStreamRead(self, handle: int, /) -> tuple[list[float], int, int]: ...


_P = ParamSpec("_P")
_T = TypeVar("_T")


def t8_range(value: float) -> float:
    if value not in T8_RANGES:
        raise ValueError(
            f"not a T8 range: {value:g} (one of {', '.join(f'{r:g}' for r in T8_RANGES)})"
        )
    return value


class T8Fault(SimFault):
    kind: Literal["skipped_scans", "unplug", "stream_error"]
    scans: Annotated[Int, Field(ge=1, le=1_000_000)] = 10
    """skipped_scans: how many consecutive scans the device skips each time."""


class LabJackT8Sim(Strict):
    """A simulated T8 (edge/drivers/sim_ljm.py): wave-like signals, a drifting CORE_TIMER."""

    drift_ppm: Float = 40.0
    """The T8's crystal against the host clock (positive: the device runs fast)."""
    wave_period_s: Annotated[Float, Field(gt=0)] = 8.0
    noise_v: Annotated[Float, Field(ge=0)] = 0.002
    read_latency_ms: Annotated[Float, Field(ge=0, le=1000)] = 2.0
    """Each eStreamRead returns up to this much after its last scan (uniformly random)."""
    core_timer_start: Annotated[Int, Field(ge=0, le=0xFFFFFFFF)] | None = None
    """CORE_TIMER at power-up; default random (it wraps every ~43 s at 100 MHz anyway)."""
    seed: Int | None = None
    faults: list[T8Fault] = []


class T8Connection(Strict):
    connection: Literal["ANY", "USB", "ETHERNET", "TCP"] = "ANY"
    """How LJM reaches the T8 (openS connectionType)."""
    identifier: Annotated[str, BeforeValidator(as_identifier), Field(min_length=1)] = "ANY"
    """Serial number, IP address or device name (openS identifier); ANY = the first found."""


CORE_TIMER_HZ = 100_000_000
"""The T8's CORE_TIMER counts at 100 MHz (10 ns; MODAQ 2's T8 nodes scale it the same way).
The T7's runs at 40 MHz: this driver is for the T8."""
_TWO32 = 1 << 32
_INSTALL = (
    "install LJM (the LabJack driver with libLabJackM) from https://labjack.com/ljm, "
    "then `pip install fleetdaq[labjack]`"
)
_NOT_FOUND = {"DEVICE_NOT_FOUND", "NO_DEVICES_FOUND", "CANNOT_OPEN_DEVICE", "CANNOT_CONNECT"}
_GONE = {
    "DEVICE_DISCONNECTED",
    "RECONNECT_FAILED",
    "CONNECTION_HAS_YIELDED_RECONNECT_FAILED",
    "NO_RESPONSE_BYTES_RECEIVED",
    "INCORRECT_NUM_RESPONSE_BYTES_RECEIVED",
    "SOCKET_LEVEL_ERROR",
    "USB_FAILURE",
    "DEVICE_NOT_OPEN",
    "INVALID_HANDLE",
}


def load_ljm() -> Ljm:
    """Import labjack-ljm's module, or raise DriverUnavailable saying what to install.

    The Python wrapper installs without the native library; it then prints an error at import
    and fails at the first call, so the missing library is detected here instead.
    """
    try:
        with contextlib.redirect_stdout(io.StringIO()):
            ljm = importlib.import_module("labjack.ljm")
    except ImportError as err:
        raise DriverUnavailable(f"the LabJack T8 needs labjack-ljm: {_INSTALL}") from err
    if getattr(getattr(ljm, "ljm", None), "_staticLib", object()) is None:
        raise DriverUnavailable(f"the LabJack T8 needs LJM's native library: {_INSTALL}")
    return cast(Ljm, ljm)  # labjack-ljm ships no type information


class LjmDevice:
    """A T8 handle and LJM error wrapping, shared by the stream, poll and output classes."""

    def __init__(self, ljm: Ljm, connection: str, identifier: str, clock: TimeSource) -> None:
        self.ljm = ljm
        self.connection = connection
        self.identifier = identifier
        self.clock = clock
        self.handle: int | None = None
        self.error_type: type[Exception] = ljm.LJMError
        self._code_names = {
            v: k
            for k, v in vars(ljm.errorcodes).items()
            if isinstance(v, int) and not k.endswith(("_BEGIN", "_END"))
        }

    @property
    def where(self) -> str:
        return f"T8 {self.identifier} ({self.connection})"

    def wrap(self, err: Exception, call: str) -> DriverError:
        """A typed DriverError for an LJMError, keeping the LJM code."""
        code = getattr(err, "errorCode", None)
        name = self._code_names.get(code, "") if isinstance(code, int) else ""
        text = getattr(err, "errorString", "") or str(err)
        message = f"{self.where}: {call}: LJM error {code}"
        message += f" {name}" if name else ""
        if text and text != name:
            message += f": {text}"
        if name in _NOT_FOUND:
            return DeviceNotFound(message, code)
        if name in _GONE:
            return DeviceDisconnected(message, code)
        return DeviceError(message, code)

    def call(self, fn: Callable[_P, _T], *args: _P.args, **kwargs: _P.kwargs) -> _T:
        """`fn(*args)`, an LJM function: an `LJMError` is raised as a typed DriverError."""
        try:
            return fn(*args, **kwargs)
        except self.error_type as err:
            raise self.wrap(err, fn.__name__) from err

    def open(self) -> int:
        handle = self.call(self.ljm.openS, "T8", self.connection, self.identifier)
        self.handle = handle
        return handle

    def close(self) -> None:
        handle, self.handle = self.handle, None
        if handle is None:
            return
        with contextlib.suppress(self.error_type):
            self.ljm.close(handle)


class CoreTimer:
    """Unwraps the T8's 32-bit CORE_TIMER into a 64-bit tick count, exactly, in numpy.

    Between two timer values the expected number of ticks is known (from scan indices within a
    stream, from host time across a restart), so the number of 2^32 wraps between them is the
    integer that reconciles expected and raw differences: exact while the expectation is good to
    better than ±2^31 ticks (21 s)."""

    def __init__(self) -> None:
        self.last_ticks: int | None = None
        """Unwrapped ticks of the newest timer value."""
        self.wraps = 0

    def reset(self) -> None:
        self.last_ticks = None

    def unwrap(
        self, ticks32: npt.NDArray[np.int64], expected_deltas: npt.NDArray[np.float64]
    ) -> npt.NDArray[np.int64]:
        """Unwrap `ticks32` (raw timer values, oldest first).

        `expected_deltas[i]` is the expected tick count from the value before `ticks32[i]` (the
        previous call's last value for i = 0; ignored on the first call) to `ticks32[i]`.
        """
        if ticks32.size == 0:
            return ticks32
        if self.last_ticks is None:
            base = int(ticks32[0])
            raw = np.diff(ticks32)
            expected = expected_deltas[1:]
        else:
            base = self.last_ticks
            raw = np.diff(ticks32, prepend=self.last_ticks % _TWO32)
            expected = expected_deltas
        wraps = np.rint((expected - raw) / _TWO32).astype(np.int64)
        self.wraps += int(np.count_nonzero(wraps))
        steps = raw + wraps * _TWO32
        out = np.empty(ticks32.size, dtype=np.int64)
        if self.last_ticks is None:
            out[0] = base
            np.cumsum(steps, out=out[1:])
            out[1:] += base
        else:
            np.cumsum(steps, out=out)
            out += base
        self.last_ticks = int(out[-1])
        return out


_DIO = re.compile(r"^(FIO[0-7]|EIO[0-7]|CIO[0-3]|DIO([0-9]|1[0-9]))$")


def dio_number(line: str) -> int:
    """DIO# of a T8 digital line: FIO0-7 = 0-7, EIO0-7 = 8-15, CIO0-3 = 16-19, DIO# = #
    (T-Series datasheet 13.0, "Digital I/O"); the bit of that line in DIO bitmask registers."""
    m = _DIO.match(line)
    if not m:
        raise ValueError(f"not a T8 digital line: {line!r}")
    base = {"FIO": 0, "EIO": 8, "CIO": 16, "DIO": 0}[line[:3]]
    return base + int(line[3:])


class T8Outputs:
    """The T8's DAC and DIO outputs: set a value, get the device's readback.

    What the output drivers drive; every write is followed by a read of the same register so a
    command can report what the device actually holds (a DAC clamps to its -0.1..10 V span).
    One per device in an agent (`fleetdaq.edge.drivers.shared`), one LJM call at a time through
    `lock`.

    LJM hands out the handle of a device that is already open in the process (LJM User's Guide
    2.1, "Subsequent calls may return the same handle"), so on a T8 that also streams this goes
    over the stream driver's connection. Closing a handle closes it for both: when the other
    side closed it (a stream reconnecting, the agent stopping), the next call here reopens it
    once (INVALID_HANDLE, DEVICE_NOT_OPEN) instead of failing.
    """

    DAC_MIN_V = -0.1
    DAC_MAX_V = 10.0

    def __init__(
        self,
        transport: Ljm | None = None,
        connection: str = "ANY",
        identifier: str = "ANY",
        clock: TimeSource = SYSTEM_TIME,
    ) -> None:
        self.ljm = transport if transport is not None else load_ljm()
        self.dev = LjmDevice(self.ljm, connection, identifier, clock)
        self.lock = threading.RLock()
        codes = self.ljm.errorcodes
        self._stale = {codes.INVALID_HANDLE, codes.DEVICE_NOT_OPEN}

    def __enter__(self) -> T8Outputs:
        self.open()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def where(self) -> str:
        return self.dev.where

    def open(self) -> None:
        with self.lock:
            if self.dev.handle is None:
                self.dev.open()

    def close(self) -> None:
        with self.lock:
            self.dev.close()

    def call(
        self, fn: Callable[Concatenate[int, _P], _T], *args: _P.args, **kwargs: _P.kwargs
    ) -> _T:
        """`fn(handle, *args)` (`fn` an LJM function taking the handle first), reopening once
        if the handle went stale."""
        with self.lock:
            handle = self._handle()
            try:
                return self.dev.call(fn, handle, *args, **kwargs)
            except DeviceError as err:
                if err.code not in self._stale:
                    raise
                self.dev.handle = None
                return self.dev.call(fn, self._handle(), *args, **kwargs)

    def _handle(self) -> int:
        self.open()
        assert self.dev.handle is not None  # `open` sets it or raises
        return self.dev.handle

    def set_dac(self, dac: int, volts: float) -> float:
        """Set DAC0 or DAC1; returns the readback (V). Raises ValueError outside -0.1..10 V."""
        if dac not in (0, 1):
            raise ValueError(f"the T8 has DAC0 and DAC1, not DAC{dac}")
        if not self.DAC_MIN_V <= volts <= self.DAC_MAX_V:
            raise ValueError(
                f"DAC{dac}: {volts:g} V is outside {self.DAC_MIN_V}..{self.DAC_MAX_V} V"
            )
        return self.write_read(f"DAC{dac}", float(volts))

    def set_dio(self, line: str, state: bool) -> bool:
        """Drive a digital line (FIO#, EIO#, CIO#, DIO#) high or low; returns the readback."""
        self._check_line(line)
        return self.write_read(line, 1.0 if state else 0.0) >= 0.5

    def read_dio(self, line: str) -> bool:
        self._check_line(line)
        return self.read(line) >= 0.5

    def write_read(self, name: str, value: float) -> float:
        with self.lock:
            self.call(self.ljm.eWriteName, name, value)
            return self.read(name)

    def read(self, name: str) -> float:
        return float(self.call(self.ljm.eReadName, name))

    @staticmethod
    def _check_line(line: str) -> None:
        if not _DIO.match(line):
            raise ValueError(f"not a T8 digital line: {line!r}")
