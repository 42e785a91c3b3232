"""LabJack T8 through LJM (labjack-ljm): stream mode, slow polled I/O, DAC and DIO outputs.

Stream (`LabJackT8`): AIN0-7 (any subset) sampled simultaneously at up to 40 kS/s each, plus
CORE_TIMER and STREAM_DATA_CAPTURE_16 in the scan list, so every scan carries the device clock
(T-Series datasheet 3.2: a 32-bit register streams its low 16 bits, STREAM_DATA_CAPTURE_16 the
high 16 bits captured with them). Per read, the interleaved list LJM returns goes into numpy
once; samples, skipped scans and the timer are decoded as whole columns.

- Device time: the 32-bit timer is unwrapped exactly: between consecutive scans the expected
  tick count is known (scans x ticks per scan), so the number of 2^32 wraps in between is the
  integer that reconciles it with the raw difference; the first scan is as good as any other.
  (MODAQ 2 adds 2^32 - 1 per wrap and stamps its first sample from an unset value.)
- Skipped scans: LJM fills every address of a scan the device skipped with its dummy value
  (-9999.0). They are marked SKIPPED_SCAN (NaN on the wire), counted, and raised as an event.
- Backlogs: deviceScanBacklog and ljmScanBacklog of the last read are in node health; a reader
  falling behind (or catching up) is an event.
- Errors: LJM errors become typed DriverErrors that keep the LJM code; the agent closes, backs
  off and reopens, in-process; the driver says "reconnected" when that works.

The vendor module is imported when a driver is created without a `sim:` block, never at import
of this module; without LJM's native library that fails with one line saying what to install.
"""

from __future__ import annotations

import contextlib
import importlib
import io
import logging
import re
import threading
from collections.abc import Sequence
from typing import Any

import numpy as np
import numpy.typing as npt

from edge.config import LabJackT8PollStream, LabJackT8Sim, LabJackT8Stream
from edge.drivers import Block, DriverEvent
from edge.drivers.pacing import SYSTEM_CLOCK, Clock, PollPacer
from edge.errors import (
    DeviceDisconnected,
    DeviceError,
    DeviceNotFound,
    DriverError,
    DriverUnavailable,
)
from edge.wire import SampleStatus

log = logging.getLogger("fleetdaq.drivers.labjack_t8")

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


def load_ljm() -> Any:
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
    return ljm


def _transport(sim: LabJackT8Sim | None, clock: Clock) -> Any:
    if sim is None:
        return load_ljm()
    from edge.drivers.sim_ljm import SimLJM

    return SimLJM(sim, clock)


class _LjmDevice:
    """A T8 handle and LJM error wrapping, shared by the stream, poll and output classes."""

    def __init__(self, ljm: Any, connection: str, identifier: str, clock: Clock) -> None:
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

    def call(self, call: str, *args: Any) -> Any:
        try:
            return getattr(self.ljm, call)(*args)
        except self.error_type as err:
            raise self.wrap(err, call) from err

    def open(self) -> int:
        self.handle = self.call("openS", "T8", self.connection, self.identifier)
        return self.handle

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
    integer that reconciles expected and raw differences: exact while the expectation is good
    to better than ±2^31 ticks (21 s).
    """

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


def decode_scans(
    data: Sequence[float] | npt.NDArray[np.float64], ain_count: int, dummy: float = -9999.0
) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.bool_], npt.NDArray[np.int64]]:
    """Split LJM stream data (AINs then CORE_TIMER, STREAM_DATA_CAPTURE_16 per scan).

    Returns the (scans, ain_count) volts, a per-scan "skipped" mask (LJM's dummy value) and the
    raw 32-bit CORE_TIMER of each scan (meaningless where skipped).
    """
    arr = np.asarray(data, dtype=np.float64).reshape(-1, ain_count + 2)
    skipped = (arr == dummy).any(axis=1)
    ticks32 = arr[:, ain_count].astype(np.int64) | (arr[:, ain_count + 1].astype(np.int64) << 16)
    return np.ascontiguousarray(arr[:, :ain_count]), skipped, ticks32


class LabJackT8:
    """A T8 in stream mode: the `labjack_t8` driver.

    Args:
        cfg: the stream's config.
        ljm: the `ljm` module to use (a fake in tests); default: the simulated T8 when the
            config has `sim:`, otherwise labjack-ljm (imported now).
        clock: host clocks (a VirtualClock in tests and benches).
    Raises:
        DriverUnavailable: labjack-ljm or LJM's native library is not installed.
    """

    def __init__(
        self, cfg: LabJackT8Stream, ljm: Any | None = None, clock: Clock = SYSTEM_CLOCK
    ) -> None:
        self.cfg = cfg
        self.clock = clock
        self.ljm = ljm if ljm is not None else _transport(cfg.sim, clock)
        self.dev = _LjmDevice(self.ljm, cfg.connection, cfg.identifier, clock)
        self.scans = cfg.batch_scans
        self.ains = cfg.ains
        self._dummy = float(self.ljm.constants.DUMMY_VALUE)
        self.timer = CoreTimer()
        self.scan_rate_hz = cfg.rate_hz
        self.ticks_per_scan = CORE_TIMER_HZ / cfg.rate_hz
        self._closing = threading.Event()
        self._events: list[DriverEvent] = []
        self._index = 0  # scans read in this stream
        self._last_valid = -1  # index of the newest scan with a timer value
        self._last_host_ns: int | None = None
        self._behind = False
        self._timer_ok = True
        self.opens = 0
        self.reconnects = 0
        self.skipped_scans = 0
        self.device_scan_backlog = 0
        self.ljm_scan_backlog = 0
        self.max_ljm_scan_backlog = 0

    # -- Driver protocol -------------------------------------------------------------------

    def open(self) -> None:
        self._closing.clear()
        dev = self.dev
        dev.open()
        try:
            self._stop_stream()  # a stream left running by a previous process
            names = [
                "STREAM_TRIGGER_INDEX",
                "STREAM_CLOCK_SOURCE",
                "STREAM_RESOLUTION_INDEX",
                "STREAM_SETTLING_US",
                "STREAM_BUFFER_SIZE_BYTES",
            ]
            values = [
                0.0,
                0.0,
                float(self.cfg.resolution_index),
                float(self.cfg.settling_us),
                float(self.cfg.buffer_bytes),
            ]
            for ain, ch in zip(self.ains, self.cfg.channels, strict=True):
                names.append(f"AIN{ain}_RANGE")
                values.append(ch.range)
            dev.call("eWriteNames", dev.handle, len(names), names, values)
            scan_list = [f"AIN{a}" for a in self.ains] + ["CORE_TIMER", "STREAM_DATA_CAPTURE_16"]
            addresses = dev.call("namesToAddresses", len(scan_list), scan_list)[0]
            actual = dev.call(
                "eStreamStart", dev.handle, self.scans, len(addresses), addresses, self.cfg.rate_hz
            )
        except DriverError:
            dev.close()
            raise
        self.scan_rate_hz = float(actual)
        self.ticks_per_scan = CORE_TIMER_HZ / self.scan_rate_hz
        self._index = 0
        self._last_valid = -1
        if abs(actual / self.cfg.rate_hz - 1.0) > 1e-6:
            self._event(
                logging.INFO,
                "scan_rate",
                f"{dev.where}: scanning at {actual:.6g} Hz (asked {self.cfg.rate_hz:g} Hz)",
            )
        if self.opens:
            self.reconnects += 1
            self._event(logging.INFO, "reconnected", f"{dev.where}: streaming again")
        self.opens += 1

    def read(self) -> Block:
        if self._closing.is_set() or self.dev.handle is None:
            raise InterruptedError("driver closed")
        try:
            data, device_backlog, ljm_backlog = self.ljm.eStreamRead(self.dev.handle)
        except self.dev.error_type as err:
            if self._closing.is_set():
                raise InterruptedError("driver closed") from err
            raise self.dev.wrap(err, "eStreamRead") from err
        host_ns = self.clock.time_ns()
        return self._block(data, int(device_backlog), int(ljm_backlog), host_ns)

    def close(self) -> None:
        self._closing.set()
        if self.dev.handle is not None:
            with contextlib.suppress(DriverError):
                self._stop_stream()
        self.dev.close()

    def health(self) -> dict[str, Any]:
        return {
            "device_scan_backlog": self.device_scan_backlog,
            "ljm_scan_backlog": self.ljm_scan_backlog,
            "max_ljm_scan_backlog": self.max_ljm_scan_backlog,
            "skipped_scans": self.skipped_scans,
            "reconnects": self.reconnects,
            "scan_rate_hz": self.scan_rate_hz,
            "core_timer_wraps": self.timer.wraps,
            "device_clock": self._timer_ok,
        }

    # -- decoding --------------------------------------------------------------------------

    def _block(self, data: Any, device_backlog: int, ljm_backlog: int, host_ns: int) -> Block:
        raw, skipped, ticks32 = decode_scans(data, len(self.ains), self._dummy)
        scans = raw.shape[0]
        status: npt.NDArray[np.uint8] | None = None
        n_skipped = int(np.count_nonzero(skipped))
        if n_skipped:
            status = np.zeros(raw.shape, dtype=np.uint8)
            status[skipped] = SampleStatus.SKIPPED_SCAN
            self.skipped_scans += n_skipped
            self._event(
                logging.WARNING,
                "skipped_scans",
                f"{self.dev.where}: {n_skipped} scan(s) skipped by the device (LJM dummy value)"
                f"; marked invalid ({self.skipped_scans} in total)",
            )
        device_ns = self._device_time(ticks32, ~skipped, scans, host_ns)
        self._backlogs(device_backlog, ljm_backlog)
        self._index += scans
        self._last_host_ns = host_ns
        events, self._events = tuple(self._events), []
        return Block(raw, host_ns, status, device_ns, events)

    def _device_time(
        self,
        ticks32: npt.NDArray[np.int64],
        valid: npt.NDArray[np.bool_],
        scans: int,
        host_ns: int,
    ) -> int | None:
        """Device time (ns) of the block's last scan, from the unwrapped CORE_TIMER."""
        rows = np.flatnonzero(valid)
        if rows.size == 0:  # every scan skipped: extrapolate from the last timer value
            last = self.timer.last_ticks
            if last is None or not self._timer_ok:
                return None
            if self._last_valid < 0:  # none yet in this stream: go by host time
                assert self._last_host_ns is not None
                return self._ns(last + round((host_ns - self._last_host_ns) * CORE_TIMER_HZ / 1e9))
            after = self._index + scans - 1 - self._last_valid
            return self._ns(last + round(after * self.ticks_per_scan))
        index = self._index + rows  # scan index within this stream
        previous = self._last_valid if self._index else -1
        expected = np.diff(index, prepend=previous).astype(np.float64)
        expected *= self.ticks_per_scan
        if self._index == 0 and self._last_host_ns is not None:
            # A new stream: the timer ran on (or restarted) since the previous read.
            expected[0] = (host_ns - self._last_host_ns) * CORE_TIMER_HZ / 1e9
        ticks = self.timer.unwrap(ticks32[rows], expected)
        self._last_valid = int(index[-1])
        if rows.size >= 2 and self._timer_ok:
            measured = (ticks[-1] - ticks[0]) / (rows[-1] - rows[0])
            if abs(measured / self.ticks_per_scan - 1.0) > 0.01:
                self._timer_ok = False
                self._event(
                    logging.ERROR,
                    "device_clock",
                    f"{self.dev.where}: CORE_TIMER runs at {measured:.1f} ticks per scan, "
                    f"expected {self.ticks_per_scan:.1f}: timing falls back to the scan index",
                )
        if not self._timer_ok:
            return None
        last = int(ticks[-1]) + round((scans - 1 - int(rows[-1])) * self.ticks_per_scan)
        return self._ns(last)

    @staticmethod
    def _ns(ticks: int) -> int:
        return ticks * 1_000_000_000 // CORE_TIMER_HZ

    def _backlogs(self, device_backlog: int, ljm_backlog: int) -> None:
        self.device_scan_backlog = device_backlog
        self.ljm_scan_backlog = ljm_backlog
        self.max_ljm_scan_backlog = max(self.max_ljm_scan_backlog, ljm_backlog)
        behind_s = ljm_backlog / self.scan_rate_hz
        if not self._behind and ljm_backlog > 2 * self.scans:
            self._behind = True
            self._event(
                logging.WARNING,
                "reader_behind",
                f"{self.dev.where}: LJM scan backlog {ljm_backlog} scans ({behind_s:.2f} s): "
                "the agent reads slower than the T8 streams",
            )
        elif self._behind and ljm_backlog <= self.scans:
            self._behind = False
            self._event(logging.INFO, "reader_caught_up", f"{self.dev.where}: backlog cleared")
        capacity = self.cfg.buffer_bytes // (2 * (len(self.ains) + 2))
        if device_backlog > capacity // 2:
            self._event(
                logging.WARNING,
                "device_backlog",
                f"{self.dev.where}: device scan backlog {device_backlog} of {capacity} scans: "
                "the link to the T8 is too slow",
            )

    def _stop_stream(self) -> None:
        try:
            self.ljm.eStreamStop(self.dev.handle)
        except self.dev.error_type as err:
            if getattr(err, "errorCode", None) != self.ljm.errorcodes.STREAM_NOT_RUNNING:
                raise self.dev.wrap(err, "eStreamStop") from err

    def _event(self, level: int, tag: str, message: str) -> None:
        self._events.append(DriverEvent(level, tag, message))


_DIO = re.compile(r"^(FIO[0-7]|EIO[0-7]|CIO[0-3]|DIO([0-9]|1[0-9]))$")


class LabJackT8Poll:
    """Slow command-response reads of a T8 (AIN volts, DIO states): `labjack_t8_poll`.

    Each poll reads every channel and CORE_TIMER in one eReadNames, so the device clock times
    polls as it times stream scans. Polls are paced on the host; a poll that could not happen
    on time becomes an invalid sample instead of a burst.
    """

    def __init__(
        self, cfg: LabJackT8PollStream, ljm: Any | None = None, clock: Clock = SYSTEM_CLOCK
    ) -> None:
        self.cfg = cfg
        self.clock = clock
        self.ljm = ljm if ljm is not None else _transport(cfg.sim, clock)
        self.dev = _LjmDevice(self.ljm, cfg.connection, cfg.identifier, clock)
        self.scans = cfg.batch_scans
        self.names = [ch.source for ch in cfg.channels] + ["CORE_TIMER"]
        self.pacer = PollPacer(cfg.rate_hz, clock)
        self.timer = CoreTimer()
        self._closing = threading.Event()
        self._last_host_ns: int | None = None
        self._events: list[DriverEvent] = []
        self.opens = 0
        self.reconnects = 0

    def open(self) -> None:
        self._closing.clear()
        self.dev.open()
        names: list[str] = []
        values: list[float] = []
        for ch in self.cfg.channels:
            if ch.source.startswith("AIN"):
                names += [f"{ch.source}_RANGE", f"{ch.source}_RESOLUTION_INDEX"]
                values += [ch.range, float(self.cfg.resolution_index)]
        try:
            if names:
                self.dev.call("eWriteNames", self.dev.handle, len(names), names, values)
        except DriverError:
            self.dev.close()
            raise
        if self.opens:
            self.reconnects += 1
            self._events.append(
                DriverEvent(logging.INFO, "reconnected", f"{self.dev.where}: polling again")
            )
        self.opens += 1
        self.pacer.start()

    def read(self) -> Block:
        rows = np.full((self.scans, len(self.cfg.channels)), np.nan)
        status = np.zeros(rows.shape, dtype=np.uint8)
        timer: list[int] = []
        polled: list[int] = []
        poll_host: list[int] = []
        i = 0
        while i < self.scans:
            missed = self.pacer.next_poll(self._closing)
            if missed is None or self.dev.handle is None:
                raise InterruptedError("driver closed")
            for _ in range(min(missed, self.scans - i)):
                status[i] = SampleStatus.SKIPPED_SCAN
                i += 1
            if i == self.scans:
                break
            values = self.dev.call("eReadNames", self.dev.handle, len(self.names), self.names)
            poll_host.append(self.clock.time_ns())
            rows[i] = values[:-1]
            timer.append(int(values[-1]))
            polled.append(i)
            i += 1
        host_ns = self.clock.time_ns()
        device_ns = None
        if timer:
            # Polls are paced by the host: the expected ticks between them come from host time.
            hosts = np.asarray(poll_host, dtype=np.float64)
            previous = self._last_host_ns if self._last_host_ns is not None else poll_host[0]
            expected = np.diff(hosts, prepend=previous) * (CORE_TIMER_HZ / 1e9)
            ticks = self.timer.unwrap(np.asarray(timer, dtype=np.int64), expected)
            period_ticks = self.pacer.period_ns * CORE_TIMER_HZ / 1e9
            last = int(ticks[-1]) + round((self.scans - 1 - polled[-1]) * period_ticks)
            device_ns = last * 1_000_000_000 // CORE_TIMER_HZ
            self._last_host_ns = poll_host[-1]
        events, self._events = tuple(self._events), []
        return Block(rows, host_ns, status if status.any() else None, device_ns, events)

    def close(self) -> None:
        self._closing.set()
        self.dev.close()

    def health(self) -> dict[str, Any]:
        return {"missed_polls": self.pacer.missed, "reconnects": self.reconnects}


class T8Outputs:
    """The T8's DAC and DIO outputs: set a value, get the device's readback.

    What the control work drives; every write is followed by a read of the same register so a
    command can report what the device actually holds (a DAC clamps to its -0.1..10 V span).
    """

    DAC_MIN_V = -0.1
    DAC_MAX_V = 10.0

    def __init__(
        self,
        ljm: Any | None = None,
        connection: str = "ANY",
        identifier: str = "ANY",
        sim: LabJackT8Sim | None = None,
        clock: Clock = SYSTEM_CLOCK,
    ) -> None:
        self.ljm = ljm if ljm is not None else _transport(sim, clock)
        self.dev = _LjmDevice(self.ljm, connection, identifier, clock)

    def __enter__(self) -> T8Outputs:
        self.open()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def open(self) -> None:
        if self.dev.handle is None:
            self.dev.open()

    def close(self) -> None:
        self.dev.close()

    def set_dac(self, dac: int, volts: float) -> float:
        """Set DAC0 or DAC1; returns the readback (V). Raises ValueError outside -0.1..10 V."""
        if dac not in (0, 1):
            raise ValueError(f"the T8 has DAC0 and DAC1, not DAC{dac}")
        if not self.DAC_MIN_V <= volts <= self.DAC_MAX_V:
            raise ValueError(
                f"DAC{dac}: {volts:g} V is outside {self.DAC_MIN_V}..{self.DAC_MAX_V} V"
            )
        return self._write_read(f"DAC{dac}", float(volts))

    def set_dio(self, line: str, state: bool) -> bool:
        """Drive a digital line (FIO#, EIO#, CIO#, DIO#) high or low; returns the readback."""
        self._check_line(line)
        return self._write_read(line, 1.0 if state else 0.0) >= 0.5

    def read_dio(self, line: str) -> bool:
        self._check_line(line)
        self.open()
        return float(self.dev.call("eReadName", self.dev.handle, line)) >= 0.5

    def _write_read(self, name: str, value: float) -> float:
        self.open()
        self.dev.call("eWriteName", self.dev.handle, name, value)
        return float(self.dev.call("eReadName", self.dev.handle, name))

    @staticmethod
    def _check_line(line: str) -> None:
        if not _DIO.match(line):
            raise ValueError(f"not a T8 digital line: {line!r}")
