"""LabJack T8 stream mode through LJM (labjack-ljm): the `labjack_t8` driver.

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
import logging
import threading
from collections.abc import Sequence
from typing import Annotated, Literal

import numpy as np
import numpy.typing as npt
from pydantic import AfterValidator, Field, model_validator

from fleetdaq.contract.drivers import DriverKind, DriverPlugin
from fleetdaq.contract.errors import DriverError
from fleetdaq.contract.schema import Channel, Float, Int, Resolution, StreamBase
from fleetdaq.contract.wire import SampleStatus
from fleetdaq.edge.drivers.base import Block, DriverEvent
from fleetdaq.edge.drivers.labjack_ljm import (
    CORE_TIMER_HZ,
    T8_ADC_BITS,
    T8_MAX_SAMPLE_RATE,
    CoreTimer,
    LabJackT8Sim,
    Ljm,
    LjmDevice,
    T8Connection,
    load_ljm,
    t8_range,
)
from fleetdaq.edge.drivers.pacing import SYSTEM_TIME, TimeSource

log = logging.getLogger("fleetdaq.drivers.labjack_t8")


class T8Channel(Channel):
    """A T8 analog input in a stream."""

    ain: Annotated[Int, Field(ge=0, le=7)] | None = None
    """AIN number; default: the channel's position in the list."""
    range: Annotated[Float, AfterValidator(t8_range)] = 11.0
    """AIN#_RANGE in ± volts."""


class LabJackT8Stream(StreamBase, T8Connection):
    """LabJack T8 stream mode: AIN0-7 sampled simultaneously, timed by the T8's CORE_TIMER."""

    driver: Literal["labjack_t8"]
    rate_hz: Annotated[Float, Field(gt=0, le=40_000)]
    channels: Annotated[list[T8Channel], Field(min_length=1, max_length=8)]  # type: ignore[assignment]
    resolution_index: Annotated[Int, Field(ge=0, le=16)] = 0
    """STREAM_RESOLUTION_INDEX (0 = the device default); higher is quieter and slower."""
    settling_us: Annotated[Float, Field(ge=0, le=50_000)] = 0.0
    """STREAM_SETTLING_US (0 = automatic)."""
    buffer_bytes: Annotated[Int, Field(ge=1024, le=32768)] = 32768
    """STREAM_BUFFER_SIZE_BYTES: the device-side stream buffer, at its maximum by default."""
    sim: LabJackT8Sim | None = None

    @model_validator(mode="after")
    def _inputs_and_rate(self) -> LabJackT8Stream:
        ains = [ch.ain if ch.ain is not None else i for i, ch in enumerate(self.channels)]
        if len(set(ains)) != len(ains):
            raise ValueError(f"two channels read the same AIN ({ains})")
        if self.buffer_bytes & (self.buffer_bytes - 1):
            raise ValueError(f"buffer_bytes must be a power of two (got {self.buffer_bytes})")
        addresses = len(self.channels) + 2  # + CORE_TIMER and STREAM_DATA_CAPTURE_16
        if addresses * self.rate_hz > T8_MAX_SAMPLE_RATE:
            raise ValueError(
                f"{addresses} addresses x {self.rate_hz:g} Hz exceeds the T8's "
                f"{T8_MAX_SAMPLE_RATE} samples/s"
            )
        return self

    def resolutions(self) -> tuple[Resolution | None, ...]:
        """The T8's ADC: 24 bits per channel over its ±range (T-Series datasheet, T8 AIN)."""
        return tuple(Resolution.bits(T8_ADC_BITS, -ch.range, ch.range) for ch in self.channels)

    @property
    def ains(self) -> list[int]:
        return [ch.ain if ch.ain is not None else i for i, ch in enumerate(self.channels)]


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
        transport: the `ljm` module to use (the simulated T8 in sims, a fake in tests);
            default: labjack-ljm (imported now).
        clock: host clocks (a VirtualTime in tests and benches).
    Raises:
        DriverUnavailable: labjack-ljm or LJM's native library is not installed.
    """

    def __init__(
        self, cfg: LabJackT8Stream, transport: Ljm | None = None, clock: TimeSource = SYSTEM_TIME
    ) -> None:
        self.cfg = cfg
        self.clock = clock
        self.ljm = transport if transport is not None else load_ljm()
        self.dev = LjmDevice(self.ljm, cfg.connection, cfg.identifier, clock)
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
        handle = dev.open()
        try:
            self._stop_stream(handle)  # a stream left running by a previous process
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
            dev.call(self.ljm.eWriteNames, handle, len(names), names, values)
            scan_list = [f"AIN{a}" for a in self.ains] + ["CORE_TIMER", "STREAM_DATA_CAPTURE_16"]
            addresses = dev.call(self.ljm.namesToAddresses, len(scan_list), scan_list)[0]
            actual = dev.call(
                self.ljm.eStreamStart,
                handle,
                self.scans,
                len(addresses),
                addresses,
                self.cfg.rate_hz,
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
                self._stop_stream(self.dev.handle)
        self.dev.close()

    def health(self) -> dict[str, object]:
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

    def _block(
        self, data: Sequence[float], device_backlog: int, ljm_backlog: int, host_ns: int
    ) -> Block:
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

    def _stop_stream(self, handle: int) -> None:
        try:
            self.ljm.eStreamStop(handle)
        except self.dev.error_type as err:
            if getattr(err, "errorCode", None) != self.ljm.errorcodes.STREAM_NOT_RUNNING:
                raise self.dev.wrap(err, "eStreamStop") from err

    def _event(self, level: int, tag: str, message: str) -> None:
        self._events.append(DriverEvent(level, tag, message))


PLUGIN = DriverPlugin(
    DriverKind.STREAM,
    LabJackT8Stream,
    LabJackT8,
    "fleetdaq.edge.drivers.sim_ljm:t8_transport",
)
