"""Simulated SPI thermocouple converters: fake `spidev.SpiDev` objects with a chip behind them.

Both chips measure the same weld-cell thermocouple (`WeldThermal`): the substrate heats
towards `peak_c` while a layer is deposited and cools towards ambient between layers (a
first-order model), the board's cold junction sits near ambient. The layers come from a fixed
cycle, or from a simulated weld robot (`fleetdaq.edge.drivers.weld_cell`) when the sim names its
cell. The chips convert on their own schedule (a MAX31855 about every 100 ms; a MAX31856 per its
mode, filter and averaging), so a read returns the last finished conversion, as the hardware does.
Faults from config set the chips' fault bits, or make MISO read all ones (no response)."""

from __future__ import annotations

import math
import threading
from collections.abc import Callable

import numpy as np

from fleetdaq.edge.drivers.max31855 import Max31855Stream, ThermocoupleSim, encode_max31855
from fleetdaq.edge.drivers.max31856 import (
    CR0_1SHOT,
    CR0_50HZ,
    CR0_CMODE,
    SR_CJRANGE,
    SR_OPEN,
    SR_OVUV,
    SR_TCRANGE,
    WRITE,
    Max31856Sim,
    Max31856Stream,
    encode_max31856,
)
from fleetdaq.edge.drivers.pacing import TimeSource
from fleetdaq.edge.drivers.shared import SharedDevices
from fleetdaq.edge.drivers.simfaults import FaultSchedule
from fleetdaq.edge.drivers.spibus import SpiFactory
from fleetdaq.edge.drivers.weld_cell import WeldCell, cell_key

_STEP_S = 0.05


class WeldThermal:
    """Substrate temperature on an additive-manufacturing cell, layer after layer.

    The layers follow a fixed cycle (`layer_s` welding, `cool_s` not), or, when the sim names a
    `cell`, whatever that cell's robot does (`welding` is then set by the chip).
    """

    def __init__(self, cfg: ThermocoupleSim | Max31856Sim, rng: np.random.Generator) -> None:
        self.cfg = cfg
        self.rng = rng
        self._t = 0.0
        self._temp = cfg.ambient_c
        self.robot: Callable[[float], bool] | None = None
        """Is the robot welding at `t_s` s after the chip powered up? (a weld cell)"""

    def welding(self, t_s: float) -> bool:
        if self.robot is not None:
            return self.robot(t_s)
        return (t_s % (self.cfg.layer_s + self.cfg.cool_s)) < self.cfg.layer_s

    def at(self, t_s: float) -> float:
        """Temperature (°C, with measurement noise) at `t_s` s after the chip powered up."""
        cfg = self.cfg
        while self._t < t_s:
            dt = min(_STEP_S, t_s - self._t)
            target, tau = (cfg.peak_c, 4.0) if self.welding(self._t) else (cfg.ambient_c, 10.0)
            self._temp += (target - self._temp) * (1.0 - math.exp(-dt / tau))
            self._t += dt
        return self._temp + float(self.rng.normal(0.0, cfg.noise_c)) if cfg.noise_c else self._temp

    def cold_junction(self) -> float:
        return self.cfg.ambient_c + 2.0 + float(self.rng.normal(0.0, 0.05))


class _SimSpiChip:
    mode = 0
    max_speed_hz = 500_000
    bits_per_word = 8

    def __init__(
        self, sim: ThermocoupleSim | Max31856Sim, clock: TimeSource, cell: WeldCell | None = None
    ) -> None:
        self.clock = clock
        self.rng = np.random.default_rng(sim.seed)
        self.faults = FaultSchedule(sim.faults, self.rng)
        self.thermal = WeldThermal(sim, self.rng)
        self.cell = cell
        self._epoch: int | None = None
        self.is_open = False
        self.lock = threading.Lock()

    def open(self, bus: int, device: int) -> None:
        if self._epoch is None:
            epoch = self._epoch = self.clock.monotonic_ns()
            cell = self.cell
            if cell is not None:
                self.thermal.robot = lambda t_s: cell.welding_at(epoch + t_s * 1e9)
        self.is_open = True

    def close(self) -> None:
        self.is_open = False

    def now_s(self) -> float:
        if not self.is_open or self._epoch is None:
            raise OSError(9, "Bad file descriptor")
        return (self.clock.monotonic_ns() - self._epoch) / 1e9

    def readbytes(self, n: int) -> list[int]:
        return self.xfer2([0] * n)

    def xfer2(self, data: list[int]) -> list[int]:
        raise NotImplementedError


class SimMax31855(_SimSpiChip):
    """A fake SpiDev with a MAX31855: 32-bit frames of the last ~100 ms conversion."""

    CONVERSION_S = 0.1

    def xfer2(self, data: list[int]) -> list[int]:
        with self.lock:
            t = self.now_s()
            if self.faults.hits("no_response", t):
                return [0xFF] * len(data)
            converted = math.floor(t / self.CONVERSION_S) * self.CONVERSION_S
            frame = encode_max31855(
                self.thermal.at(converted),
                self.thermal.cold_junction(),
                open_circuit=self.faults.hits("open_circuit", t),
                short_gnd=self.faults.hits("short_gnd", t),
                short_vcc=self.faults.hits("short_vcc", t),
            )
            return list((frame + bytes(max(0, len(data) - 4)))[: len(data)])


_DEFAULTS = [0x00, 0x03, 0xFF, 0x7F, 0xC0, 0x7F, 0xFF, 0x80, 0x00, 0x00, 0, 0, 0, 0, 0, 0]
"""MAX31856 power-on register values (datasheet, Register Memory Map)."""


class SimMax31856(_SimSpiChip):
    """A fake SpiDev with a MAX31856: a register file and a conversion engine."""

    def __init__(self, sim: Max31856Sim, clock: TimeSource, cell: WeldCell | None = None) -> None:
        super().__init__(sim, clock, cell)
        self.regs = list(_DEFAULTS)
        self._next_conversion = 0.0
        self._one_shot_done: float | None = None

    def _conversion_s(self) -> float:
        cr0, cr1 = self.regs[0], self.regs[1]
        avg = 1 << min((cr1 >> 4) & 0x7, 4)
        fifty = bool(cr0 & CR0_50HZ)
        continuous = bool(cr0 & CR0_CMODE)
        first = {(True, True): 0.100, (True, False): 0.090, (False, True): 0.185}.get(
            (continuous, fifty), 0.155
        )
        return first + (avg - 1) * (0.040 if fifty else 0.03333)

    def _convert(self, t: float) -> None:
        sr = 0
        for kind, bit in (
            ("open_circuit", SR_OPEN),
            ("overvoltage", SR_OVUV),
            ("tc_range", SR_TCRANGE),
            ("cj_range", SR_CJRANGE),
        ):
            if self.faults.hits(kind, t):
                sr |= bit
        values = encode_max31856(self.thermal.at(t), self.thermal.cold_junction(), sr)
        self.regs[0x0A:0x10] = list(values)

    def _update(self, t: float) -> None:
        if self.regs[0] & CR0_CMODE:
            period = self._conversion_s()
            if t >= self._next_conversion:
                done = math.floor(t / period) * period
                self._convert(done)
                self._next_conversion = done + period
        elif self._one_shot_done is not None and t >= self._one_shot_done:
            self._convert(self._one_shot_done)
            self._one_shot_done = None
            self.regs[0] &= ~CR0_1SHOT & 0xFF

    def xfer2(self, data: list[int]) -> list[int]:
        with self.lock:
            t = self.now_s()
            if self.faults.hits("no_response", t):
                return [0xFF] * len(data)
            self._update(t)
            address = data[0] & 0x0F
            if data[0] & WRITE:
                for i, value in enumerate(data[1:]):
                    reg = (address + i) & 0x0F
                    if reg <= 0x0B:  # 0C..0F are read-only
                        self.regs[reg] = value & 0xFF
                if (
                    address == 0
                    and len(data) > 1
                    and data[1] & CR0_1SHOT
                    and not data[1] & CR0_CMODE
                ):
                    self._one_shot_done = t + self._conversion_s()
                if address == 0 and len(data) > 1 and data[1] & CR0_CMODE:
                    self._next_conversion = t + self._conversion_s()
                return [0xFF] * len(data)
            return [0xFF] + [self.regs[(address + i) & 0x0F] for i in range(len(data) - 1)]


def _cell(
    sim: ThermocoupleSim | Max31856Sim, clock: TimeSource, shared: SharedDevices | None
) -> WeldCell | None:
    if sim.cell is None:
        return None
    name = sim.cell
    return (shared or SharedDevices()).get(cell_key(name), lambda: WeldCell(name, clock), WeldCell)


def max31855_transport(
    cfg: Max31855Stream, clock: TimeSource, shared: SharedDevices | None = None
) -> SpiFactory:
    """The SpiDev factory `max31855` gets when its config has `sim:`
    (fleetdaq.edge.drivers.table)."""
    sim = cfg.sim
    assert sim is not None
    cell = _cell(sim, clock, shared)
    return lambda: SimMax31855(sim, clock, cell)


def max31856_transport(
    cfg: Max31856Stream, clock: TimeSource, shared: SharedDevices | None = None
) -> SpiFactory:
    """The SpiDev factory `max31856` gets when its config has `sim:`
    (fleetdaq.edge.drivers.table)."""
    sim = cfg.sim
    assert sim is not None
    cell = _cell(sim, clock, shared)
    return lambda: SimMax31856(sim, clock, cell)
