"""Simulated LabJack-T8-like stream: wave-driven signals on every channel, in volts.

Each channel is a sum of a swell and a wind-sea component with its own amplitude and phase,
plus Gaussian noise. Noise comes from a pre-drawn table sliced at random offsets, so a
320 kS/s stream costs a few numpy slices per batch instead of fresh random draws.
`WaveModel` is the signal alone: the simulated T8 (`sim_ljm`) plays it on its AIN channels.
"""

from __future__ import annotations

from typing import Annotated, Literal

import numpy as np
import numpy.typing as npt
from pydantic import Field

from fleetdaq.contract.drivers import DriverKind, DriverPlugin
from fleetdaq.contract.schema import Float, StreamBase
from fleetdaq.edge.drivers.pacing import PacedSim


class WaveSimStream(StreamBase):
    """A LabJack-T8-like simulated stream: wave-like signals plus noise, in volts."""

    driver: Literal["wave_sim"]
    wave_period_s: Annotated[Float, Field(gt=0)] = 8.0
    noise_v: Annotated[Float, Field(ge=0)] = 0.002
    drift_ppm: Float = 0.0


_NOISE_TABLE = 1 << 20


class WaveModel:
    """Wave-like signals on `channels` channels, in volts, at any device times."""

    def __init__(
        self, channels: int, wave_period_s: float, noise_v: float, rng: np.random.Generator
    ) -> None:
        self._amp = rng.uniform(0.5, 4.0, size=(2, channels))
        self._phase = rng.uniform(0, 2 * np.pi, size=(2, channels))
        self._omega = 2 * np.pi / np.array([wave_period_s, wave_period_s / 3.1])
        self._noise = (rng.standard_normal(_NOISE_TABLE) * noise_v).astype(np.float64)
        self._rng = rng
        # A sin(w t + p) = (A cos p) sin(w t) + (A sin p) cos(w t): with the per-channel
        # factors in one (4, channels) matrix, a block costs 4 trig calls per scan and one
        # matrix product, instead of a sine per sample.
        self._mix = np.vstack(
            [
                self._amp[0] * np.cos(self._phase[0]),
                self._amp[0] * np.sin(self._phase[0]),
                self._amp[1] * np.cos(self._phase[1]),
                self._amp[1] * np.sin(self._phase[1]),
            ]
        )

    def sample(self, t: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
        """(len(t), channels) volts at device times `t` (s)."""
        ph = np.multiply.outer(t, self._omega)  # (scans, 2)
        basis = np.empty((len(t), 4))
        np.sin(ph[:, 0], out=basis[:, 0])
        np.cos(ph[:, 0], out=basis[:, 1])
        np.sin(ph[:, 1], out=basis[:, 2])
        np.cos(ph[:, 1], out=basis[:, 3])
        out: npt.NDArray[np.float64] = basis @ self._mix
        n = out.size
        start = int(self._rng.integers(0, _NOISE_TABLE - n)) if n < _NOISE_TABLE else 0
        noise = self._noise[start : start + n]
        if noise.size < n:  # a block larger than the table: tile it
            noise = np.resize(self._noise, n)
        out += noise.reshape(out.shape)
        return out


class WaveSim(PacedSim):
    def __init__(self, cfg: WaveSimStream, seed: int | None = None) -> None:
        self.cfg = cfg
        super().__init__(cfg.rate_hz, cfg.batch_scans, cfg.drift_ppm)
        self.model = WaveModel(
            len(cfg.channels), cfg.wave_period_s, cfg.noise_v, np.random.default_rng(seed)
        )

    def generate(self, first: int) -> npt.NDArray[np.float64]:
        """Scans [first, first + scans) as (scans, channels) volts."""
        t0, dt = self.pacer.seconds_of(first, self.scans)
        t: npt.NDArray[np.float64] = t0 + np.arange(self.scans, dtype=np.float64) * dt
        return self.model.sample(t)


PLUGIN = DriverPlugin(DriverKind.STREAM, WaveSimStream, WaveSim)
