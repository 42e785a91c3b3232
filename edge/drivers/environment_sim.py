"""Simulated slow environment sensor: air temperature, relative humidity, pressure.

Channels are filled in that order (extra channels repeat the pattern); values wander slowly
like weather on a pier.
"""

from __future__ import annotations

from typing import Literal

import numpy as np
import numpy.typing as npt

from fleetdaq.contract.drivers import DriverKind, DriverPlugin
from fleetdaq.contract.schema import Float, StreamBase
from fleetdaq.edge.drivers.pacing import PacedSim


class EnvironmentSimStream(StreamBase):
    """A slow simulated environment sensor (air temperature, humidity, pressure)."""

    driver: Literal["environment_sim"]
    drift_ppm: Float = 0.0


_BASE = np.array([14.0, 78.0, 1013.0])  # °C, %RH, hPa
_SWING = np.array([3.0, 10.0, 4.0])
_NOISE = np.array([0.05, 0.3, 0.1])


class EnvironmentSim(PacedSim):
    def __init__(self, cfg: EnvironmentSimStream, seed: int | None = None) -> None:
        self.cfg = cfg
        super().__init__(cfg.rate_hz, cfg.batch_scans, cfg.drift_ppm)
        self._rng = np.random.default_rng(seed)
        n = len(cfg.channels)
        self._idx = np.arange(n) % 3

    def generate(self, first: int) -> npt.NDArray[np.float64]:
        t0, dt = self.pacer.seconds_of(first, self.scans)
        t = t0 + np.arange(self.scans) * dt
        slow = np.sin(2 * np.pi * t / 600.0)[:, None]  # a 10-minute swing, visible in a demo
        base, swing, noise = _BASE[self._idx], _SWING[self._idx], _NOISE[self._idx]
        out: npt.NDArray[np.float64] = base + swing * slow
        out += self._rng.normal(0, 1, (self.scans, len(base))) * noise
        return out


PLUGIN = DriverPlugin(DriverKind.STREAM, EnvironmentSimStream, EnvironmentSim)
