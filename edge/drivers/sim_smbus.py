"""A simulated I2C bus behind a fake `smbus2` module, with an SHT3x and an HD44780 LCD on it.

`SimSmbus2` has what the drivers use of smbus2 (`SMBus(bus)` with `i2c_rdwr`, `write_byte`,
`read_byte`, `close`; `i2c_msg.read` / `i2c_msg.write`) and answers like Linux i2c-dev: a
NACK, or nobody at the address, is OSError(EREMOTEIO); a bus that does not exist is
FileNotFoundError. Devices model their registers and timing:

- `SimSht3x`: single-shot measurements that are NACKed until done, CRC-8 on every word,
  slowly wandering air temperature and humidity; faults: NACKs, corrupted CRCs.
- `SimLcd`: a PCF8574 port expander driving an HD44780 in 4-bit mode: nibbles latched on E's
  falling edge, instructions executed, DDRAM kept, so a test can read what the LCD shows.
"""

from __future__ import annotations

import ctypes
import errno
import math
import threading
from collections.abc import Iterator
from typing import Any, ClassVar, Protocol

import numpy as np

from edge.drivers.hd44780 import BACKLIGHT, DEGREE, ROW_OFFSETS, RS, E, LcdDisplay, LcdSim
from edge.drivers.pacing import TimeSource
from edge.drivers.sht3x import (
    COMMANDS,
    MEASUREMENT_S,
    SOFT_RESET,
    Sht3xSim,
    Sht3xStream,
    encode_sht3x,
)
from edge.drivers.simfaults import FaultSchedule


def nack() -> OSError:
    return OSError(errno.EREMOTEIO, "Remote I/O error")


class SimI2cDevice(Protocol):
    def write(self, data: bytes) -> None: ...

    def read(self, length: int) -> bytes: ...


class SimI2cMsg:
    """Like smbus2.i2c_msg: `read(address, length)` / `write(address, buf)`, iterable, bytes."""

    I2C_M_RD = 0x0001

    def __init__(self, addr: int, flags: int, buf: bytearray) -> None:
        self.addr = addr
        self.flags = flags
        self.buf = buf

    @classmethod
    def read(cls, address: int, length: int) -> SimI2cMsg:
        return cls(address, cls.I2C_M_RD, bytearray(length))

    @classmethod
    def write(cls, address: int, buf: Any) -> SimI2cMsg:
        data = buf.encode() if isinstance(buf, str) else bytes(buf)
        return cls(address, 0, bytearray(data))

    @property
    def len(self) -> int:
        return len(self.buf)

    def __iter__(self) -> Iterator[int]:
        return iter(self.buf)

    def __bytes__(self) -> bytes:
        return bytes(self.buf)


class SimSMBus:
    """Like smbus2.SMBus on one simulated bus."""

    def __init__(self, devices: dict[int, SimI2cDevice], lock: threading.Lock) -> None:
        self._devices = devices
        self._lock = lock
        self.closed = False

    def __enter__(self) -> SimSMBus:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _device(self, address: int) -> SimI2cDevice:
        if self.closed:
            raise OSError(errno.EBADF, "Bad file descriptor")
        device = self._devices.get(address)
        if device is None:
            raise nack()  # nobody acknowledges the address
        return device

    def i2c_rdwr(self, *i2c_msgs: Any) -> None:
        with self._lock:
            for msg in i2c_msgs:
                device = self._device(msg.addr)
                if msg.flags & SimI2cMsg.I2C_M_RD:
                    data = device.read(msg.len)
                    if isinstance(msg, SimI2cMsg):
                        msg.buf[:] = data
                    else:  # a real smbus2.i2c_msg: fill its ctypes buffer
                        ctypes.memmove(msg.buf, data, msg.len)
                else:
                    device.write(bytes(msg))

    def write_byte(self, i2c_addr: int, value: int, force: bool | None = None) -> None:
        with self._lock:
            self._device(i2c_addr).write(bytes([value & 0xFF]))

    def read_byte(self, i2c_addr: int, force: bool | None = None) -> int:
        with self._lock:
            return self._device(i2c_addr).read(1)[0]

    def close(self) -> None:
        self.closed = True


class SimSmbus2:
    """A fake `smbus2` module: `SMBus(bus)` opens one of the simulated buses."""

    i2c_msg: ClassVar[type[SimI2cMsg]] = SimI2cMsg

    def __init__(self, clock: TimeSource) -> None:
        self.clock = clock
        self.buses: dict[int, dict[int, SimI2cDevice]] = {}
        self._lock = threading.Lock()

    def attach(self, bus: int, address: int, device: SimI2cDevice) -> None:
        self.buses.setdefault(bus, {})[address] = device

    def SMBus(self, bus: int | None = None, force: bool = False) -> SimSMBus:
        if bus is None or bus not in self.buses:
            raise FileNotFoundError(errno.ENOENT, "No such file or directory", f"/dev/i2c-{bus}")
        return SimSMBus(self.buses[bus], self._lock)


class _Faulty:
    def __init__(self, faults: Any, seed: int | None, clock: TimeSource) -> None:
        self.clock = clock
        self.rng = np.random.default_rng(seed)
        self.faults = FaultSchedule(faults, self.rng)
        self._epoch: int | None = None

    def now_s(self) -> float:
        now = self.clock.monotonic_ns()
        if self._epoch is None:
            self._epoch = now
        return (now - self._epoch) / 1e9


class SimSht3x(_Faulty):
    """An SHT3x: single-shot measurements, NACK while measuring, CRC-8 on every word."""

    def __init__(self, sim: Sht3xSim, clock: TimeSource) -> None:
        super().__init__(sim.faults, sim.seed, clock)
        self.sim = sim
        self._ready_s: float | None = None
        self._result = b""
        self.measurements = 0

    def air(self, t_s: float) -> tuple[float, float]:
        slow = math.sin(2 * math.pi * t_s / 600.0)  # a 10-minute swing, visible in a demo
        t = self.sim.temperature_c + 3.0 * slow + float(self.rng.normal(0, 0.05))
        rh = self.sim.humidity_pct - 10.0 * slow + float(self.rng.normal(0, 0.3))
        return t, min(max(rh, 0.0), 100.0)

    def write(self, data: bytes) -> None:
        t = self.now_s()
        if self.faults.hits("nack", t):
            raise nack()
        command = tuple(data[:2])
        for name, cmd in COMMANDS.items():
            if command == cmd:
                self._ready_s = t + MEASUREMENT_S[name] * 0.9
                self._result = b""
                return
        if command == SOFT_RESET:
            self._ready_s = None
            return
        raise nack()  # an unknown command is not acknowledged

    def read(self, length: int) -> bytes:
        t = self.now_s()
        if self.faults.hits("nack", t) or self._ready_s is None or t < self._ready_s:
            raise nack()  # no measurement, or still measuring (no clock stretching)
        if not self._result:
            self._result = encode_sht3x(*self.air(self._ready_s))
            self.measurements += 1
        data = bytearray(self._result[:length])
        if self.faults.hits("crc_error", t) and len(data) >= 3:
            data[2] ^= 0x5A
        return bytes(data)


class SimLcd(_Faulty):
    """A PCF8574 driving an HD44780 (4-bit): what the LCD would show, readable by tests."""

    def __init__(
        self, sim: LcdSim | None, clock: TimeSource, cols: int = 16, rows: int = 2
    ) -> None:
        super().__init__(sim.faults if sim else [], None, clock)
        self.cols = cols
        self.rows = rows
        self.ddram = bytearray(b" " * 0x80)
        self.address = 0
        self.port = 0
        self.four_bit = False
        self._high: int | None = None
        self.display_on = False
        self.instructions = 0

    @property
    def backlight(self) -> bool:
        return bool(self.port & BACKLIGHT)

    def text(self, row: int) -> str:
        start = ROW_OFFSETS[row]
        raw = self.ddram[start : start + self.cols]
        return "".join("°" if b == DEGREE else chr(b) for b in raw)

    def lines(self) -> list[str]:
        return [self.text(r) for r in range(self.rows)]

    def write(self, data: bytes) -> None:
        if self.faults.hits("nack", self.now_s()):
            raise nack()
        for value in data:
            falling = self.port & E and not value & E
            self.port = value
            if falling:
                self._latch(value >> 4, bool(value & RS))

    def read(self, length: int) -> bytes:
        return bytes([self.port]) * length

    def _latch(self, nibble: int, rs: bool) -> None:
        if not self.four_bit:
            # 8-bit mode after power-up: each E pulse is a whole instruction, D0-D3 unwired (0).
            self._execute(nibble << 4, rs)
            return
        if self._high is None:
            self._high = nibble
            return
        value, self._high = self._high << 4 | nibble, None
        self._execute(value, rs)

    def _execute(self, value: int, rs: bool) -> None:
        self.instructions += 1
        if rs:
            self.ddram[self.address & 0x7F] = value
            self.address = (self.address + 1) & 0x7F
        elif value & 0x80:  # set DDRAM address
            self.address = value & 0x7F
        elif value & 0x40:  # set CGRAM address: custom characters are not modelled
            pass
        elif value & 0x20:  # function set: DL (bit 4) = 0 selects 4-bit
            self.four_bit = not value & 0x10
        elif value & 0x10:  # cursor or display shift
            pass
        elif value & 0x08:  # display control: D (bit 2) = display on
            self.display_on = bool(value & 0x04)
        elif value & 0x04:  # entry mode
            pass
        elif value & 0x02:  # return home
            self.address = 0
        elif value == 0x01:  # clear display
            self.ddram[:] = b" " * 0x80
            self.address = 0


def sht3x_transport(cfg: Sht3xStream, clock: TimeSource) -> SimSmbus2:
    """The `smbus2` `sht3x` gets when its config has `sim:`: a bus with the sensor on it."""
    assert cfg.sim is not None
    smbus = SimSmbus2(clock)
    smbus.attach(cfg.bus, cfg.address, SimSht3x(cfg.sim, clock))
    return smbus


def lcd_transport(cfg: LcdDisplay, clock: TimeSource) -> SimSmbus2:
    """The `smbus2` an LCD display gets when its config has `sim:`: a bus with the LCD on it
    (``smbus.buses[bus][address]`` is the `SimLcd`, whose `lines()` tests read)."""
    smbus = SimSmbus2(clock)
    smbus.attach(cfg.bus, cfg.address, SimLcd(cfg.sim, clock, cfg.cols, cfg.rows))
    return smbus
