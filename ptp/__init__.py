"""Time-sync status (linuxptp / chrony). A leaf package: it imports nothing of fleetdaq's."""

from __future__ import annotations

from ptp.quality import ClockQuality, ClockState

__all__ = ["ClockQuality", "ClockState"]
