"""A simulated I2C bus behind a fake `smbus2` module, with an SHT3x, an HD44780 LCD, PCF8574 port
expanders and MCP4725 DACs on it.

`SimSmbus2` has what the drivers use of smbus2 (`SMBus(bus)` with `i2c_rdwr`, `write_byte`,
`read_byte`, `close`; `i2c_msg.read` / `i2c_msg.write`) and answers like Linux i2c-dev: a
NACK, or nobody at the address, is OSError(EREMOTEIO); a bus that does not exist is
FileNotFoundError. Devices model their registers and timing:

- `SimSht3x`: single-shot measurements that are NACKed until done, CRC-8 on every word,
  slowly wandering air temperature and humidity; faults: NACKs, corrupted CRCs.
- `SimLcd`: a PCF8574 port expander driving an HD44780 in 4-bit mode: nibbles latched on E's
  falling edge, instructions executed, DDRAM kept, so a test can read what the LCD shows.
- `SimPcf8574`: the quasi-bidirectional port (NXP PCF8574 Rev. 5, 8.1-8.3): HIGH at power-on,
  every written byte sets the port, a read returns the pin levels (pins held low outside read
  0 whatever was written).
- `SimMcp4725`: the DAC register and EEPROM (Microchip DS22039D, 6.1-6.2): fast writes, write
  DAC register (and EEPROM, busy for 25 ms meanwhile, writes ignored), the 5-byte read.
"""

from __future__ import annotations

import ctypes
import errno
import math
import threading
from collections.abc import Iterator, Sequence
from typing import ClassVar, Protocol

import numpy as np

from fleetdaq.edge.drivers.hd44780 import BACKLIGHT, DEGREE, ROW_OFFSETS, RS, E, LcdDisplay, LcdSim
from fleetdaq.edge.drivers.i2cbus import I2cMessage
from fleetdaq.edge.drivers.mcp4725 import WRITE_DAC, WRITE_DAC_EEPROM, Mcp4725Output, Mcp4725Sim
from fleetdaq.edge.drivers.pacing import TimeSource
from fleetdaq.edge.drivers.pcf8574 import POWER_ON_PORT, Pcf8574Output, Pcf8574Sim
from fleetdaq.edge.drivers.shared import SharedDevices
from fleetdaq.edge.drivers.sht3x import (
    COMMANDS,
    MEASUREMENT_S,
    SOFT_RESET,
    Sht3xSim,
    Sht3xStream,
    encode_sht3x,
)
from fleetdaq.edge.drivers.simfaults import Fault, FaultSchedule


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
    def write(cls, address: int, buf: bytes | list[int] | str) -> SimI2cMsg:
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

    def i2c_rdwr(self, *i2c_msgs: I2cMessage) -> None:
        with self._lock:
            for msg in i2c_msgs:
                device = self._device(msg.addr)
                if msg.flags & SimI2cMsg.I2C_M_RD:
                    data = device.read(msg.len)
                    if isinstance(msg, SimI2cMsg):
                        msg.buf[:] = data
                    else:  # a real smbus2.i2c_msg: fill its ctypes buffer
                        buf = getattr(msg, "buf")  # noqa: B009 (a ctypes pointer: not in I2cMessage)
                        ctypes.memmove(buf, data, msg.len)
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
    def __init__(self, faults: Sequence[Fault], seed: int | None, clock: TimeSource) -> None:
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


class SimPcf8574(_Faulty):
    """A PCF8574: one quasi-bidirectional 8-bit port (datasheet 8.1-8.3)."""

    def __init__(self, sim: Pcf8574Sim | None, clock: TimeSource) -> None:
        super().__init__(sim.faults if sim else [], None, clock)
        self.latch = POWER_ON_PORT  # 8.1: all HIGH at power-on
        self.stuck_low = sim.stuck_low if sim else 0
        self.writes = 0

    @property
    def pins(self) -> int:
        """The pin levels: a latch bit at 1 is only a weak pull-up, so a pin held low reads 0."""
        return self.latch & ~self.stuck_low & 0xFF

    def write(self, data: bytes) -> None:
        if self.faults.hits("nack", self.now_s()):
            raise nack()
        for value in data:  # 8.2: each byte sets P7..P0; the last one stays
            self.latch = value
            self.writes += 1

    def read(self, length: int) -> bytes:
        if self.faults.hits("nack", self.now_s()):
            raise nack()
        return bytes([self.pins]) * length  # 8.3: the pin levels, as often as clocked


class SimMcp4725(_Faulty):
    """An MCP4725: DAC register, EEPROM, RDY/BSY (DS22039D 6.1-6.2)."""

    EEPROM_WRITE_NS = 25_000_000  # Table 1-1: 25 ms typical

    def __init__(self, sim: Mcp4725Sim | None, clock: TimeSource) -> None:
        super().__init__(sim.faults if sim else [], None, clock)
        self.eeprom_code = sim.eeprom_code if sim else 0
        self.eeprom_power_down = 0
        self.code = self.eeprom_code  # power-on: the DAC register is loaded from the EEPROM
        self.power_down = self.eeprom_power_down
        self.por = True
        self._busy_until = 0
        self.eeprom_writes = 0
        self.ignored = 0

    def volts(self, vref: float) -> float:
        """What VOUT is (0 when powered down)."""
        return 0.0 if self.power_down else self.code * vref / 4096

    def _busy(self) -> bool:
        return self.clock.monotonic_ns() < self._busy_until

    def write(self, data: bytes) -> None:
        if self.faults.hits("nack", self.now_s()):
            raise nack()
        if self._busy():
            self.ignored += 1  # Figure 6-2 note 1: writes during an EEPROM write are ignored
            return
        i = 0
        while i < len(data):
            first = data[i]
            command = first >> 5
            if first >> 6 == 0 and i + 1 < len(data):  # 6.1.1 fast mode: C2 C1 = 0 0
                self.power_down = first >> 4 & 0x3
                self.code = (first & 0x0F) << 8 | data[i + 1]
                i += 2
            elif command in (WRITE_DAC, WRITE_DAC_EEPROM) and i + 2 < len(data):  # 6.1.2/6.1.3
                self.power_down = first >> 1 & 0x3
                self.code = data[i + 1] << 4 | data[i + 2] >> 4
                if command == WRITE_DAC_EEPROM:
                    self.eeprom_code, self.eeprom_power_down = self.code, self.power_down
                    self.eeprom_writes += 1
                    self._busy_until = self.clock.monotonic_ns() + self.EEPROM_WRITE_NS
                    return
                i += 3
            else:
                return  # a reserved command, or a cut-off one: ignored (6.1)

    def read(self, length: int) -> bytes:
        if self.faults.hits("nack", self.now_s()):
            raise nack()
        status = (0 if self._busy() else 0x80) | (0x40 if self.por else 0) | self.power_down << 1
        frame = bytes(
            [
                status,
                self.code >> 4,
                (self.code & 0x0F) << 4,
                self.eeprom_power_down << 5 | self.eeprom_code >> 8,
                self.eeprom_code & 0xFF,
            ]
        )
        return (frame * (length // 5 + 1))[:length]  # Figure 6-3 note 1: bytes repeat


def shared_bus(clock: TimeSource, shared: SharedDevices | None) -> SimSmbus2:
    """The agent's simulated I2C buses (every simulated chip of a node on the same ones)."""
    return (shared or SharedDevices()).get(("sim_smbus",), lambda: SimSmbus2(clock), SimSmbus2)


def pcf8574_transport(
    cfg: Pcf8574Output, clock: TimeSource, shared: SharedDevices | None = None
) -> SimSmbus2:
    """The `smbus2` a `pcf8574` output gets when its config has `sim:` (the chip is made by
    the first of its pins; ``smbus.buses[bus][address]`` is the `SimPcf8574`)."""
    smbus = shared_bus(clock, shared)
    if cfg.address not in smbus.buses.get(cfg.bus, {}):
        smbus.attach(cfg.bus, cfg.address, SimPcf8574(cfg.sim, clock))
    return smbus


def mcp4725_transport(
    cfg: Mcp4725Output, clock: TimeSource, shared: SharedDevices | None = None
) -> SimSmbus2:
    """The `smbus2` an `mcp4725` output gets when its config has `sim:`."""
    smbus = shared_bus(clock, shared)
    if cfg.address not in smbus.buses.get(cfg.bus, {}):
        smbus.attach(cfg.bus, cfg.address, SimMcp4725(cfg.sim, clock))
    return smbus


def sht3x_transport(
    cfg: Sht3xStream, clock: TimeSource, shared: SharedDevices | None = None
) -> SimSmbus2:
    """The `smbus2` `sht3x` gets when its config has `sim:`: a bus with the sensor on it."""
    assert cfg.sim is not None
    smbus = SimSmbus2(clock)
    smbus.attach(cfg.bus, cfg.address, SimSht3x(cfg.sim, clock))
    return smbus


def lcd_transport(
    cfg: LcdDisplay, clock: TimeSource, shared: SharedDevices | None = None
) -> SimSmbus2:
    """The `smbus2` an LCD display gets when its config has `sim:`: a bus with the LCD on it
    (``smbus.buses[bus][address]`` is the `SimLcd`, whose `lines()` tests read)."""
    smbus = SimSmbus2(clock)
    smbus.attach(cfg.bus, cfg.address, SimLcd(cfg.sim, clock, cfg.cols, cfg.rows))
    return smbus
