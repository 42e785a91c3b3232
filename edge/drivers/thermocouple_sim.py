"""Simulated MAX31855-like thermocouple on an additive-manufacturing cell.

Channel 0 is the hot junction: it heats towards `peak_c` while a weld layer is deposited and
cools exponentially towards ambient between layers, quantised to the MAX31855's 0.25 °C.
Channel 1 (if configured) is the cold junction at 0.0625 °C resolution.
"""

from __future__ import annotations

import math
from typing import Annotated, Literal

import numpy as np
import numpy.typing as npt
from pydantic import Field

from fleetdaq.contract.drivers import DriverKind, DriverPlugin
from fleetdaq.contract.schema import Float, StreamBase
from fleetdaq.edge.drivers.pacing import PacedSim


class ThermocoupleSimStream(StreamBase):
    """A MAX31855-like simulated thermocouple on a weld cell: heats per layer, cools between."""

    driver: Literal["thermocouple_sim"]
    ambient_c: Float = 25.0
    peak_c: Float = 450.0
    layer_s: Annotated[Float, Field(gt=0)] = 20.0
    cool_s: Annotated[Float, Field(gt=0)] = 15.0
    drift_ppm: Float = 0.0


class ThermocoupleSim(PacedSim):
    def __init__(self, cfg: ThermocoupleSimStream, seed: int | None = None) -> None:
        self.cfg = cfg
        super().__init__(cfg.rate_hz, cfg.batch_scans, cfg.drift_ppm)
        self._rng = np.random.default_rng(seed)
        self._temp = cfg.ambient_c

    def _target(self, t: float) -> tuple[float, float]:
        cycle = self.cfg.layer_s + self.cfg.cool_s
        welding = (t % cycle) < self.cfg.layer_s
        return (self.cfg.peak_c, 4.0) if welding else (self.cfg.ambient_c, 10.0)

    def generate(self, first: int) -> npt.NDArray[np.float64]:
        t0, dt = self.pacer.seconds_of(first, self.scans)
        out = np.empty((self.scans, len(self.cfg.channels)))
        for i in range(self.scans):  # a few scans per second: a first-order thermal model
            target, tau = self._target(t0 + i * dt)
            self._temp += (target - self._temp) * (1 - math.exp(-dt / tau))
            out[i, 0] = self._temp
        out[:, 0] += self._rng.normal(0, 0.3, self.scans)
        out[:, 0] = np.round(out[:, 0] * 4) / 4  # MAX31855: 14-bit, 0.25 °C
        if out.shape[1] > 1:
            cj = self.cfg.ambient_c + 2.0 + self._rng.normal(0, 0.05, self.scans)
            out[:, 1:] = (np.round(cj * 16) / 16)[:, None]  # 12-bit, 0.0625 °C
        return out


PLUGIN = DriverPlugin(DriverKind.STREAM, ThermocoupleSimStream, ThermocoupleSim)
