"""The node's clock monitor: what every batch says about the host clock at acquisition.

`make_clock_monitor` builds the monitor a node's config asks for. The agent reads `quality`
for every batch (cheap: a field read) and puts `status()` into node health; the monitor polls
its source (ptp4l, chrony, ...) on its own thread and calls `emit(level, tag, message)` when
the state changes.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, Protocol

from edge.config import NodeConfig
from ptp.quality import UNSYNCED, ClockQuality

Emit = Callable[[int, str, str], None]
"""emit(level, tag, message): raise an event from the clock monitor."""


class ClockMonitor(Protocol):
    @property
    def quality(self) -> ClockQuality: ...

    def status(self) -> dict[str, Any]:
        """The full status for node health (JSON-serialisable)."""
        ...

    def start(self) -> None: ...

    def close(self) -> None:
        """Idempotent."""
        ...


class NoClockMonitor:
    """Nothing checks the clock: every batch says unsynced."""

    quality: ClockQuality = UNSYNCED

    def status(self) -> dict[str, Any]:
        return {"source": "none", "state": "unsynced"}

    def start(self) -> None:
        pass

    def close(self) -> None:
        pass


def make_clock_monitor(node: NodeConfig, emit: Emit) -> ClockMonitor:
    return NoClockMonitor()
