"""A simulated serial barometer: the port `serial_barometer` gets when its config has `sim:`.

One instrument per driver, powered up when its port is first opened: the fault schedule
(seconds since then) runs on across reopening, as a real instrument's power does. It answers
``SEND`` with the pressure at that moment; faults from config make it silent (readline waits
the port's timeout and returns nothing), send a garbled line, or vanish (unplugged: the
port's calls fail with EIO and opening it fails with ENOENT, as a USB-serial adapter's do).
"""

from __future__ import annotations

import errno
import math
import threading

import numpy as np

from fleetdaq.edge.drivers.pacing import TimeSource
from fleetdaq.edge.drivers.shared import SharedDevices
from fleetdaq.edge.drivers.simfaults import FaultSchedule
from fleetdaq_driver_example.barometer import (
    SEND,
    BarometerSim,
    PortOpener,
    SerialBarometerStream,
    SerialPort,
    encode_line,
)


class SimBarometer:
    """The instrument: pressure, its faults, its power-up time."""

    def __init__(self, sim: BarometerSim, clock: TimeSource) -> None:
        self.sim = sim
        self.clock = clock
        self.rng = np.random.default_rng(sim.seed)
        self.faults = FaultSchedule(sim.faults, self.rng)
        self.epoch: int | None = None

    def now_s(self) -> float:
        if self.epoch is None:
            self.epoch = self.clock.monotonic_ns()
        return (self.clock.monotonic_ns() - self.epoch) / 1e9

    def pressure(self, t_s: float) -> float:
        slow = math.sin(2 * math.pi * t_s / 900.0)  # a 15-minute swing, visible in a demo
        return (
            self.sim.pressure_hpa
            + self.sim.swing_hpa * slow
            + self.rng.normal(0, 1) * (self.sim.noise_hpa)
        )


class SimPort:
    """An open port to the simulated barometer (what `serial.Serial` is to a real one)."""

    def __init__(self, device: SimBarometer, timeout: float) -> None:
        self.device = device
        self.timeout = timeout
        self._asked = False
        self._closed = threading.Event()

    def _check(self) -> float:
        if self._closed.is_set():
            raise OSError(errno.EBADF, "Bad file descriptor")
        t = self.device.now_s()
        if self.device.faults.in_window("unplug", t):
            raise OSError(errno.EIO, "Input/output error")
        return t

    def write(self, data: bytes, /) -> int:
        self._check()
        self._asked = self._asked or data == SEND
        return len(data)

    def readline(self) -> bytes:
        t = self._check()
        asked, self._asked = self._asked, False
        faults = self.device.faults
        if not asked or faults.hits("no_response", t):
            clock = self.device.clock
            clock.sleep_until(clock.monotonic_ns() + round(self.timeout * 1e9), self._closed)
            return b""
        line = encode_line(self.device.pressure(t))
        if faults.hits("garbled", t):
            line = line[:4] + b"#" + line[5:]
        return line

    def close(self) -> None:
        self._closed.set()


def barometer_transport(
    cfg: SerialBarometerStream, clock: TimeSource, shared: SharedDevices | None = None
) -> PortOpener:
    """The port opener `serial_barometer` gets when its config has `sim:`."""
    assert cfg.sim is not None
    device = SimBarometer(cfg.sim, clock)

    def opener(port: str, baudrate: int, timeout: float) -> SerialPort:
        if device.faults.in_window("unplug", device.now_s()):
            raise OSError(errno.ENOENT, f"could not open port {port}: No such file or directory")
        return SimPort(device, timeout)

    return opener
