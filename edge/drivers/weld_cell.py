"""A simulated wire-arc additive-manufacturing cell: a weld robot that deposits a layer, says so
(`layer_done`), and waits for a rising edge on its `resume` input before the next layer.

Three drivers of one node see the same cell, keyed by its name (`cell: weld1`) through the
agent's shared devices: the robot's stream (`weld_robot_sim`), the thermocouple on the
substrate (the MAX31855 sim heats while the robot welds) and the `resume` output
(`weld_robot_resume`). The cell is a pure function of time and of the edges on `resume`: any of
them advances it to "now" on the shared clock, so it runs in virtual time in tests.

Each inter-layer wait (from `layer_done` to the resume, by pulse or by giving up after
`max_wait_s` like today's fixed pause) is recorded.
"""

from __future__ import annotations

import threading
from collections import deque
from dataclasses import dataclass

from fleetdaq.edge.drivers.pacing import TimeSource


@dataclass(frozen=True, slots=True)
class LayerWait:
    layer: int
    """The layer that had just been finished."""
    wait_s: float
    timed_out: bool
    """True when the robot gave up waiting after `max_wait_s` and resumed by itself."""


@dataclass(frozen=True, slots=True)
class CellState:
    welding: bool
    layer_done: bool
    layer: int
    """Layers completed."""
    waits: int
    """Inter-layer waits recorded (one per resume)."""
    timeouts: int
    last_wait_s: float
    """The latest inter-layer wait (0 before the first)."""
    finished: bool


class WeldCell:
    """The robot's state machine; every method takes the lock and advances to now first."""

    def __init__(self, name: str, clock: TimeSource) -> None:
        self.name = name
        self.clock = clock
        self.layer_s = 20.0
        self.max_wait_s: float | None = 120.0
        self.layers: int | None = None
        self._lock = threading.Lock()
        self._start: int | None = None  # monotonic ns the current layer started (None: waiting)
        self._done_at: int | None = None  # monotonic ns of the last layer_done
        self._layer = 0
        self._resume = False
        self._intervals: deque[tuple[int, int]] = deque(maxlen=256)  # past welding [start, end)
        self.waits: deque[LayerWait] = deque(maxlen=1000)
        self._waits = 0
        self._timeouts = 0
        self._begun = False

    def configure(self, layer_s: float, max_wait_s: float | None, layers: int | None) -> None:
        with self._lock:
            self.layer_s, self.max_wait_s, self.layers = layer_s, max_wait_s, layers

    def _advance(self, now: int) -> None:
        if not self._begun:
            self._begun = True
            self._start = now
        while True:
            if self._start is not None:
                end = self._start + round(self.layer_s * 1e9)
                if now < end:
                    return
                self._intervals.append((self._start, end))
                self._layer += 1
                self._start, self._done_at = None, end
            if self._done_at is None or self.finished:
                return
            if self.max_wait_s is None:
                return
            give_up = self._done_at + round(self.max_wait_s * 1e9)
            if now < give_up:
                return
            self._resume_at(give_up, timed_out=True)

    def _resume_at(self, when: int, timed_out: bool) -> None:
        assert self._done_at is not None
        self.waits.append(LayerWait(self._layer, (when - self._done_at) / 1e9, timed_out))
        self._waits += 1
        self._timeouts += timed_out
        self._start, self._done_at = when, None

    @property
    def finished(self) -> bool:
        return self.layers is not None and self._layer >= self.layers

    def set_resume(self, level: bool) -> None:
        """The `resume` input: a rising edge while waiting starts the next layer."""
        with self._lock:
            now = self.clock.monotonic_ns()
            self._advance(now)
            rising = level and not self._resume
            self._resume = level
            if rising and self._start is None and self._done_at is not None and not self.finished:
                self._resume_at(now, timed_out=False)

    @property
    def resume_level(self) -> bool:
        with self._lock:
            return self._resume

    def state(self) -> CellState:
        with self._lock:
            self._advance(self.clock.monotonic_ns())
            last = self.waits[-1].wait_s if self.waits else 0.0
            return CellState(
                welding=self._start is not None,
                layer_done=self._start is None and self._layer > 0,
                layer=self._layer,
                waits=self._waits,
                timeouts=self._timeouts,
                last_wait_s=last,
                finished=self.finished,
            )

    def welding_at(self, mono_ns: float) -> bool:
        """Was the robot welding at `mono_ns` (now or in the recent past)?"""
        with self._lock:
            self._advance(self.clock.monotonic_ns())
            if self._start is not None and mono_ns >= self._start:
                return True
            return any(a <= mono_ns < b for a, b in reversed(self._intervals))


def cell_key(name: str) -> tuple[str, str]:
    """The cell's key in the agent's shared devices."""
    return ("weld_cell", name)
