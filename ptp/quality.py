"""The clock quality every batch carries: state, offset from the grandmaster, grandmaster id."""

from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum


class ClockState(IntEnum):
    """Values match fleetdaq_msgs/ClockQuality's STATE_* constants on the wire."""

    UNSYNCED = 0
    LOCKED = 1
    HOLDOVER = 2


@dataclass(frozen=True, slots=True)
class ClockQuality:
    state: ClockState = ClockState.UNSYNCED
    offset_ns: int = 0
    grandmaster_id: str = ""
    source: str = "none"
    """Where the state came from: "ptp4l", "chrony" or "none" (nothing checked yet)."""


UNSYNCED = ClockQuality()
