"""Real-time pacing for sims: a device clock that runs at the configured rate, with drift."""

from __future__ import annotations

import threading
import time

import numpy as np
import numpy.typing as npt

from edge.drivers import Block


class DevicePacer:
    """Hands out scan indices at the rate a real device would produce them.

    The sim's device clock runs `drift_ppm` fast (positive) or slow against the host, so the
    timing fit has something real to find.
    """

    def __init__(self, rate_hz: float, drift_ppm: float = 0.0) -> None:
        self.rate_hz = rate_hz * (1.0 + drift_ppm * 1e-6)
        self._start_mono = 0
        self.next_index = 0
        self._stop = threading.Event()

    def start(self) -> None:
        self._start_mono = time.monotonic_ns()
        self.next_index = 0
        self._stop.clear()

    def wait_for(self, scans: int) -> int | None:
        """Sleep until `scans` more scans exist; return the index of the first, None if stopped.

        Scan k is sampled at device time k / rate, so the block is complete once its last scan
        (first + scans - 1) has been sampled.
        """
        first = self.next_index
        due_ns = self._start_mono + (first + scans - 1) * 1e9 / self.rate_hz
        delay = (due_ns - time.monotonic_ns()) / 1e9
        if delay > 0 and self._stop.wait(delay):
            return None
        self.next_index = first + scans
        return first

    def seconds_of(self, first: int, scans: int) -> tuple[float, float]:
        """Device time (s since start) of scan `first` and the scan period (s)."""
        return first / self.rate_hz, 1.0 / self.rate_hz

    def stop(self) -> None:
        self._stop.set()


class PacedSim:
    """Shared behaviour of the sims: real-time pacing and the Driver protocol around
    `generate(first) -> (scans, channels)`, which each sim implements."""

    def __init__(self, rate_hz: float, scans: int, drift_ppm: float) -> None:
        self.scans = scans
        self.pacer = DevicePacer(rate_hz, drift_ppm)

    def generate(self, first: int) -> npt.NDArray[np.float64]:
        raise NotImplementedError

    def open(self) -> None:
        self.pacer.start()

    def read(self) -> Block:
        first = self.pacer.wait_for(self.scans)
        if first is None:
            raise InterruptedError("driver closed")
        return Block(self.generate(first), time.time_ns())

    def close(self) -> None:
        self.pacer.stop()
