"""A simulated LabJack T8 behind a fake `ljm` module: the transport of `labjack_t8` in sims.

`SimLJM` has the functions the driver uses from labjack-ljm's ``labjack.ljm`` with the same
names, parameters, return values and error type (`LJMError` with `errorCode`, `errorAddress`,
`errorString`), plus ``errorcodes`` and ``constants`` namespaces with the vendor's values. Behind
it one simulated T8 runs in (real or virtual) time:

- a 32-bit CORE_TIMER at 100 MHz from a crystal `drift_ppm` off the host clock, starting at a
  random value, so it wraps every ~43 s;
- stream mode: scans clocked by the same crystal; in a scan list CORE_TIMER returns its low
  16 bits and STREAM_DATA_CAPTURE_16 the high 16 bits captured with them (T-Series datasheet
  3.2, "16-bit or 32-bit data"); AIN channels play `WaveModel` signals clipped to their range;
- `eStreamRead` blocks until its `scansPerRead` scans exist, then returns up to
  `read_latency_ms` later; a reader that is slower than the stream finds the scans already
  there and sees `ljmScanBacklog` grow, until LJM's buffer is full (LJME_LJM_BUFFER_FULL);
- faults from config: skipped scans (every address of the scan is LJM's dummy value -9999),
  stream errors, and unplugging (the device power-cycles: its timer restarts on replug);
- DAC0/DAC1 (clamped to -0.1..10 V) and DIO outputs that read back, and the hardware watchdog
  (`sim_t8_watchdog`), fed by every command-response call (not by stream data);
- like LJM, opening a T8 that is already open in the process returns its handle (LJM User's
  Guide 2.1), and `t8_transport` gives every driver of an agent naming the same identifier the
  same simulated T8, so a stream and outputs share one device.

`scan_time_ns` gives the host time at which a scan was really sampled: the truth the timing
bench measures the clock fit against.
"""

from __future__ import annotations

import math
import re
import threading
from collections.abc import Sequence
from typing import TYPE_CHECKING, ClassVar

import numpy as np

from fleetdaq.edge.drivers.labjack_ljm import T8_MAX_SAMPLE_RATE, T8_RANGES, LabJackT8Sim
from fleetdaq.edge.drivers.pacing import SYSTEM_TIME, TimeSource
from fleetdaq.edge.drivers.shared import SharedDevices
from fleetdaq.edge.drivers.sim_t8_watchdog import SimWatchdog
from fleetdaq.edge.drivers.simfaults import FaultSchedule
from fleetdaq.edge.drivers.wave_sim import WaveModel

if TYPE_CHECKING:
    from fleetdaq.edge.drivers.labjack_t8 import LabJackT8Stream
    from fleetdaq.edge.drivers.labjack_t8_out import LabJackT8DacOutput, LabJackT8DioOutput
    from fleetdaq.edge.drivers.labjack_t8_poll import LabJackT8PollStream

CORE_TIMER_HZ = 100_000_000
"""The T8's CORE_TIMER rate (the T7's runs at 40 MHz)."""
_TWO32 = 1 << 32
_LJM_BUFFER_S = 20.0
"""How much stream data LJM buffers for a slow reader before LJME_LJM_BUFFER_FULL."""


class errorcodes:
    """LJM error codes used here (labjack.ljm.errorcodes, same values)."""

    NOERROR = 0
    INVALID_HANDLE = 1223
    DEVICE_NOT_OPEN = 1224
    DEVICE_DISCONNECTED = 1226
    DEVICE_NOT_FOUND = 1227
    CANNOT_CONNECT = 1231
    RECONNECT_FAILED = 1239
    INVALID_PARAMETER = 1255
    INVALID_NAME = 1294
    LJM_BUFFER_FULL = 1301
    COULD_NOT_START_STREAM = 1302
    STREAM_NOT_RUNNING = 1303
    SYNCHRONIZATION_TIMEOUT = 1306
    NO_DEVICES_FOUND = 1314


class constants:
    """LJM constants used here (labjack.ljm.constants, same values)."""

    DUMMY_VALUE = -9999
    UINT16 = 0
    UINT32 = 1
    INT32 = 2
    FLOAT32 = 3
    dtANY = 0
    dtT8 = 8
    ctANY = 0
    ctUSB = 1
    ctTCP = 2
    ctETHERNET = 3


_ERROR_NAMES = {v: k for k, v in vars(errorcodes).items() if isinstance(v, int)}


class LJMError(Exception):
    """Mirrors labjack.ljm.LJMError: `errorCode`, `errorAddress`, `errorString`."""

    def __init__(
        self,
        errorCode: int | None = None,
        errorAddress: int | None = None,
        errorString: str | None = None,
    ) -> None:
        super().__init__(errorCode, errorAddress, errorString)
        self._errorCode = errorCode
        self._errorAddress = errorAddress
        if errorString is None:
            errorString = _ERROR_NAMES.get(errorCode or 0, "") if errorCode is not None else ""
        self._errorString = str(errorString)

    @property
    def errorCode(self) -> int | None:
        return self._errorCode

    @property
    def errorAddress(self) -> int | None:
        return self._errorAddress

    @property
    def errorString(self) -> str:
        return self._errorString

    def __str__(self) -> str:
        addr = f"Address {self._errorAddress}, " if self._errorAddress is not None else ""
        code = f"LJM library error code {self._errorCode} " if self._errorCode is not None else ""
        return addr + code + self._errorString


# Modbus addresses (ljm_constants.json): AIN# = 2 * #, DAC# = 1000 + 2 * #, DIO# = 2000 + #.
CORE_TIMER_ADDRESS = 61520
CAPTURE_16_ADDRESS = 4899
_DIO_NAMES = {
    **{f"FIO{i}": i for i in range(8)},
    **{f"EIO{i}": 8 + i for i in range(8)},
    **{f"CIO{i}": 16 + i for i in range(4)},
    **{f"DIO{i}": i for i in range(20)},
}
_STREAM_SETTINGS = {
    "STREAM_TRIGGER_INDEX": 0.0,
    "STREAM_CLOCK_SOURCE": 0.0,
    "STREAM_RESOLUTION_INDEX": 0.0,
    "STREAM_SETTLING_US": 0.0,
    "STREAM_BUFFER_SIZE_BYTES": 32768.0,
}
_AIN = re.compile(r"^AIN([0-7])$")
_AIN_SETTING = re.compile(r"^AIN([0-7])_(RANGE|RESOLUTION_INDEX|SETTLING_US)$")
_DAC = re.compile(r"^DAC([01])$")


class SimT8:
    """One simulated T8: registers, CORE_TIMER, stream engine, plug state."""

    def __init__(self, cfg: LabJackT8Sim, clock: TimeSource) -> None:
        self.cfg = cfg
        self.clock = clock
        self.rng = np.random.default_rng(cfg.seed)
        self.faults = FaultSchedule(cfg.faults, self.rng)
        self.ticks_per_s = CORE_TIMER_HZ * (1.0 + cfg.drift_ppm * 1e-6)
        self.wave = WaveModel(8, cfg.wave_period_s, cfg.noise_v, self.rng)
        self.serial = 480010000 + int(self.rng.integers(0, 9999))
        self.lock = threading.Lock()
        self.epoch_mono: int | None = None  # when the schedule of faults started (first open)
        self.power_ons = 0
        self._was_unplugged = False
        self._checked_s = 0.0
        self.watchdog = SimWatchdog()  # its settings are in flash: they outlive power cycles
        self._power_on()

    # -- time ------------------------------------------------------------------------------

    def _power_on(self) -> None:
        self.power_ons += 1
        start = self.cfg.core_timer_start
        if start is None or self.power_ons > 1:
            start = int(self.rng.integers(0, _TWO32))
        self.tick0 = float(start)
        self.on_mono = self.clock.monotonic_ns()
        self.on_real = self.clock.time_ns()
        self.registers: dict[str, float] = dict(_STREAM_SETTINGS)
        for i in range(8):
            self.registers[f"AIN{i}_RANGE"] = 11.0
            self.registers[f"AIN{i}_RESOLUTION_INDEX"] = 0.0
            self.registers[f"AIN{i}_SETTLING_US"] = 0.0
        self.registers["DAC0"] = self.registers["DAC1"] = 0.0
        self.dio_out: dict[int, int] = {}
        self.stream: _Stream | None = None
        self.watchdog.power_on(self.on_mono)

    def ticks_at_mono(self, mono_ns: float) -> float:
        return self.tick0 + (mono_ns - self.on_mono) * self.ticks_per_s / 1e9

    def mono_at_ticks(self, ticks: float) -> float:
        return self.on_mono + (ticks - self.tick0) * 1e9 / self.ticks_per_s

    def fault_time_s(self, mono_ns: float) -> float:
        if self.epoch_mono is None:
            return -1.0
        return (mono_ns - self.epoch_mono) / 1e9

    def unplugged(self, mono_ns: float | None = None) -> bool:
        mono = self.clock.monotonic_ns() if mono_ns is None else mono_ns
        return self.faults.in_window("unplug", self.fault_time_s(mono))

    def seen_unplug(self) -> None:
        self._was_unplugged = True

    def check_plugged(self, code: int) -> None:
        """Raise LJMError(code) while unplugged; power-cycle on the first call after replug."""
        now = self.clock.monotonic_ns()
        if self.unplugged(now):
            if self.stream is not None:
                self.stream.running = False
            self._was_unplugged = True
            raise LJMError(code)
        t_s = self.fault_time_s(now)
        if self._was_unplugged or self.faults.starts("unplug", self._checked_s, t_s):
            self._was_unplugged = False
            self._power_on()
        self._checked_s = t_s

    def command_response(self) -> None:
        """A command-response packet arrived: the watchdog acts if its time ran out, then its
        timer restarts."""
        now = self.clock.monotonic_ns()
        self.check_watchdog(now)
        self.watchdog.feed(now)

    def check_watchdog(self, now: int | None = None) -> None:
        """Perform the watchdog's actions if it timed out (without feeding it)."""
        action = self.watchdog.due(self.clock.monotonic_ns() if now is None else now)
        if action is None:
            return
        for dac, volts in action.dacs.items():
            self.registers[f"DAC{dac}"] = min(max(volts, -0.1), 10.0)
        self.dio_out.update(action.dios)

    # -- registers --------------------------------------------------------------------------

    def write(self, name: str, value: float) -> None:
        if SimWatchdog.owns(name):
            refused = self.watchdog.write(name, value)
            if refused is not None:
                raise LJMError(errorcodes.INVALID_PARAMETER, errorString=refused)
        elif m := _AIN_SETTING.match(name):
            if m.group(2) == "RANGE" and value not in T8_RANGES:
                raise LJMError(errorcodes.INVALID_PARAMETER, errorString=f"{name}={value:g}")
            self.registers[name] = float(value)
        elif name in _STREAM_SETTINGS or name.startswith("AIN_ALL_"):
            self.registers[name] = float(value)
        elif m := _DAC.match(name):
            self.registers[name] = min(max(float(value), -0.1), 10.0)  # T8 DAC: -0.1 to 10 V
        elif name in _DIO_NAMES:
            self.dio_out[_DIO_NAMES[name]] = 1 if value else 0
        else:
            raise LJMError(errorcodes.INVALID_NAME, errorString=f"INVALID_NAME: {name}")

    def read(self, name: str) -> float:
        now = self.clock.monotonic_ns()
        if name in self.registers:
            return self.registers[name]
        if SimWatchdog.owns(name):
            return self.watchdog.read(name)
        if m := _AIN.match(name):
            t = np.array([(now - self.on_mono) / 1e9])
            rng = self.registers[f"AIN{m.group(1)}_RANGE"]
            return float(np.clip(self.wave.sample(t)[0, int(m.group(1))], -rng, rng))
        if name in _DIO_NAMES:
            line = _DIO_NAMES[name]
            # An output reads back its state; an input with nothing wired reads high (pull-up).
            return float(self.dio_out.get(line, 1))
        if name == "CORE_TIMER":
            return float(int(self.ticks_at_mono(now)) % _TWO32)
        if name == "SERIAL_NUMBER":
            return float(self.serial)
        if name == "PRODUCT_ID":
            return 8.0
        raise LJMError(errorcodes.INVALID_NAME, errorString=f"INVALID_NAME: {name}")


class _Stream:
    @property
    def running(self) -> bool:
        return not self.stopped.is_set()

    @running.setter
    def running(self, value: bool) -> None:
        if value:
            self.stopped.clear()
        else:
            self.stopped.set()

    def __init__(self, addresses: list[int], scans_per_read: int, rate: float, ticks: float):
        self.addresses = addresses
        self.spr = scans_per_read
        self.rate = rate
        self.ticks_per_scan = CORE_TIMER_HZ / rate  # device ticks: same crystal as the scans
        self.start_ticks = ticks
        self.consumed = 0
        self.stopped = threading.Event()
        self.skipped: list[tuple[int, int]] = []  # [first, last) scan ranges the device skipped
        self.next_fault_s = 0.0


class SimLJM:
    """A fake ``labjack.ljm`` with one simulated T8 behind it (any identifier finds it)."""

    LJMError: ClassVar[type[LJMError]] = LJMError
    errorcodes: ClassVar[type[errorcodes]] = errorcodes
    constants: ClassVar[type[constants]] = constants

    def __init__(self, cfg: LabJackT8Sim, clock: TimeSource = SYSTEM_TIME) -> None:
        self.device = SimT8(cfg, clock)
        self.clock = clock
        self._handles: set[int] = set()
        self._next_handle = 1
        self.opens = 0

    # -- connection ------------------------------------------------------------------------

    def openS(
        self,
        deviceType: str = "ANY",
        connectionType: str = "ANY",
        identifier: str = "ANY",
    ) -> int:
        dev = self.device
        if deviceType.upper().removeprefix("LJM_DT") not in {"ANY", "T8", ""}:
            raise LJMError(errorcodes.DEVICE_NOT_FOUND)
        with dev.lock:
            if dev.epoch_mono is None:
                dev.epoch_mono = self.clock.monotonic_ns()
            dev.check_plugged(errorcodes.DEVICE_NOT_FOUND)
            if self._handles:  # already open in this process: LJM returns that handle
                return min(self._handles)
            dev.command_response()  # opening reads the device's identity
            handle = self._next_handle
            self._next_handle += 1
            self._handles.add(handle)
            self.opens += 1
            return handle

    def close(self, handle: int) -> None:
        self._check(handle)
        self._handles.discard(handle)

    def errorToString(self, errorCode: int) -> str:
        return _ERROR_NAMES.get(errorCode, "")

    def _check(self, handle: int) -> None:
        if handle not in self._handles:
            raise LJMError(errorcodes.INVALID_HANDLE)

    # -- command-response ------------------------------------------------------------------

    def eWriteName(self, handle: int, name: str, value: float) -> None:
        self.eWriteNames(handle, 1, [name], [value])

    def eWriteNames(
        self,
        handle: int,
        numFrames: int,
        aNames: Sequence[str],
        aValues: Sequence[float],
    ) -> None:
        self._check(handle)
        with self.device.lock:
            self.device.check_plugged(errorcodes.DEVICE_DISCONNECTED)
            self.device.command_response()
            for name, value in zip(aNames[:numFrames], aValues[:numFrames], strict=True):
                self.device.write(name, value)

    def eReadName(self, handle: int, name: str) -> float:
        return self.eReadNames(handle, 1, [name])[0]

    def eReadNames(self, handle: int, numFrames: int, aNames: Sequence[str]) -> list[float]:
        self._check(handle)
        with self.device.lock:
            self.device.check_plugged(errorcodes.DEVICE_DISCONNECTED)
            self.device.command_response()
            return [self.device.read(name) for name in aNames[:numFrames]]

    def namesToAddresses(
        self,
        numFrames: int,
        aNames: Sequence[str],
        aAddresses: Sequence[int] | None = None,
        aDataTypes: Sequence[int] | None = None,
    ) -> tuple[list[int], list[int]]:
        addresses: list[int] = []
        types: list[int] = []
        for name in aNames[:numFrames]:
            if m := _AIN.match(name):
                addresses.append(2 * int(m.group(1)))
                types.append(constants.FLOAT32)
            elif name == "CORE_TIMER":
                addresses.append(CORE_TIMER_ADDRESS)
                types.append(constants.UINT32)
            elif name == "STREAM_DATA_CAPTURE_16":
                addresses.append(CAPTURE_16_ADDRESS)
                types.append(constants.UINT16)
            elif m := _DAC.match(name):
                addresses.append(1000 + 2 * int(m.group(1)))
                types.append(constants.FLOAT32)
            elif name in _DIO_NAMES:
                addresses.append(2000 + _DIO_NAMES[name])
                types.append(constants.UINT16)
            else:
                raise LJMError(errorcodes.INVALID_NAME, errorString=f"INVALID_NAME: {name}")
        return addresses, types

    # -- stream ----------------------------------------------------------------------------

    def eStreamStart(
        self,
        handle: int,
        scansPerRead: int,
        numAddresses: int,
        aScanList: Sequence[int],
        scanRate: float,
    ) -> float:
        self._check(handle)
        dev = self.device
        with dev.lock:
            dev.check_plugged(errorcodes.DEVICE_DISCONNECTED)
            addresses = list(aScanList[:numAddresses])
            if dev.stream is not None and dev.stream.running:
                raise LJMError(errorcodes.COULD_NOT_START_STREAM, errorString="stream is active")
            for a in addresses:
                if not (a < 16 and a % 2 == 0) and a not in {
                    CORE_TIMER_ADDRESS,
                    CAPTURE_16_ADDRESS,
                }:
                    raise LJMError(errorcodes.INVALID_PARAMETER, errorAddress=a)
            if scanRate <= 0 or scanRate * len(addresses) > T8_MAX_SAMPLE_RATE:
                raise LJMError(errorcodes.COULD_NOT_START_STREAM, errorString="scan rate too high")
            # The scan clock divides the core clock: the actual rate is the nearest reachable one.
            actual = CORE_TIMER_HZ / round(CORE_TIMER_HZ / scanRate)
            now = self.clock.monotonic_ns()
            # The first scan follows the start command by a little (a few ticks of setup).
            first_ticks = dev.ticks_at_mono(now) + 1000.0
            dev.stream = _Stream(addresses, scansPerRead, actual, first_ticks)
            dev.stream.next_fault_s = dev.fault_time_s(now)
            return actual

    def eStreamStop(self, handle: int) -> None:
        self._check(handle)
        dev = self.device
        with dev.lock:
            stream = dev.stream
            if stream is None or not stream.running:
                raise LJMError(errorcodes.STREAM_NOT_RUNNING)
            stream.running = False

    def eStreamRead(self, handle: int) -> tuple[list[float], int, int]:
        self._check(handle)
        dev = self.device
        stream = dev.stream
        if stream is None or not stream.running:
            raise LJMError(errorcodes.STREAM_NOT_RUNNING)
        first, spr = stream.consumed, stream.spr
        last_mono = dev.mono_at_ticks(
            stream.start_ticks + (first + spr - 1) * stream.ticks_per_scan
        )
        latency = float(dev.rng.uniform(0.0, dev.cfg.read_latency_ms * 1e6))
        due = last_mono + latency
        self._wait_for(stream, due)
        now = self.clock.monotonic_ns()
        t_s = dev.fault_time_s(now)
        with dev.lock:
            if not stream.running:
                raise LJMError(errorcodes.STREAM_NOT_RUNNING)
            if dev.unplugged(now):
                stream.running = False
                dev.seen_unplug()
                raise LJMError(errorcodes.DEVICE_DISCONNECTED)
            errors = dev.faults.starts("stream_error", stream.next_fault_s, t_s)
            if errors or dev.faults.hits("stream_error", t_s):
                stream.running = False
                stream.next_fault_s = t_s
                raise LJMError(errorcodes.SYNCHRONIZATION_TIMEOUT)
            produced = (
                int((dev.ticks_at_mono(now) - stream.start_ticks) // stream.ticks_per_scan) + 1
            )
            ljm_backlog = max(0, produced - (first + spr))
            if ljm_backlog > _LJM_BUFFER_S * stream.rate:
                stream.running = False
                raise LJMError(errorcodes.LJM_BUFFER_FULL)
            self._schedule_skips(stream, t_s)
            data = self._scans(stream, first, spr)
            stream.consumed = first + spr
        device_backlog = int(dev.rng.integers(0, 3))
        return data.ravel().tolist(), device_backlog, ljm_backlog

    def _wait_for(self, stream: _Stream, due_mono: float) -> None:
        """Sleep until `due_mono`, waking early if the stream stops or the device goes away."""
        dev = self.device
        target = math.ceil(due_mono)
        if dev.epoch_mono is not None:
            now_s = dev.fault_time_s(self.clock.monotonic_ns())
            unplug = dev.faults.starts("unplug", now_s, dev.fault_time_s(target))
            if unplug:
                target = min(target, dev.epoch_mono + math.ceil(unplug[0][1] * 1e9))
        self.clock.sleep_until(target, stream.stopped)

    def _schedule_skips(self, stream: _Stream, t_s: float) -> None:
        """Turn skipped-scans faults that started since the last read into scan ranges."""
        dev = self.device
        if dev.epoch_mono is None:
            return
        for fault, start_s in dev.faults.starts("skipped_scans", stream.next_fault_s, t_s):
            mono = dev.epoch_mono + start_s * 1e9
            k = int((dev.ticks_at_mono(mono) - stream.start_ticks) // stream.ticks_per_scan)
            k = max(k, stream.consumed)
            stream.skipped.append((k, k + int(getattr(fault, "scans", 10))))
        stream.next_fault_s = t_s

    def _scans(self, stream: _Stream, first: int, count: int) -> np.ndarray:
        """(count, addresses) values as the T8 streams them."""
        dev = self.device
        k = np.arange(first, first + count, dtype=np.float64)
        ticks = stream.start_ticks + k * stream.ticks_per_scan
        t = (ticks - dev.tick0) / dev.ticks_per_s
        ticks32 = np.floor(ticks).astype(np.int64) % _TWO32
        out = np.empty((count, len(stream.addresses)))
        ains = [a // 2 for a in stream.addresses if a < 16]
        waves = dev.wave.sample(t) if ains else None
        for col, a in enumerate(stream.addresses):
            if a == CORE_TIMER_ADDRESS:
                out[:, col] = ticks32 & 0xFFFF
            elif a == CAPTURE_16_ADDRESS:
                out[:, col] = ticks32 >> 16
            else:
                assert waves is not None
                rng = dev.registers[f"AIN{a // 2}_RANGE"]
                np.clip(waves[:, a // 2], -rng, rng, out=out[:, col])
        for lo, hi in stream.skipped:
            a, b = max(lo, first), min(hi, first + count)
            if a < b:
                out[a - first : b - first] = constants.DUMMY_VALUE
        stream.skipped = [(lo, hi) for lo, hi in stream.skipped if hi > first + count]
        return out

    # -- truth (for tests and the timing bench) ----------------------------------------------

    def scan_time_ns(self, index: int) -> int:
        """Host CLOCK_REALTIME at which scan `index` of the current stream was sampled."""
        dev = self.device
        stream = dev.stream
        if stream is None:
            raise RuntimeError("no stream")
        ticks = stream.start_ticks + index * stream.ticks_per_scan
        return dev.on_real + round((ticks - dev.tick0) * 1e9 / dev.ticks_per_s)

    def core_timer_at_scan(self, index: int) -> int:
        """The device's CORE_TIMER (unwrapped, from power-on value) at scan `index`."""
        stream = self.device.stream
        if stream is None:
            raise RuntimeError("no stream")
        return math.floor(stream.start_ticks + index * stream.ticks_per_scan)


def t8_transport(
    cfg: LabJackT8Stream | LabJackT8PollStream | LabJackT8DacOutput | LabJackT8DioOutput,
    clock: TimeSource,
    shared: SharedDevices | None = None,
) -> SimLJM:
    """The `ljm` the T8 drivers get when their config has `sim:` (fleetdaq.edge.drivers.table): one
    simulated T8 per identifier in an agent (the first driver's `sim:` settings make it)."""
    sim = cfg.sim
    assert sim is not None
    return (shared or SharedDevices()).get(
        ("sim_t8", cfg.identifier), lambda: SimLJM(sim, clock), SimLJM
    )
