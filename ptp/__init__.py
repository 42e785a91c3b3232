"""Time-sync status (linuxptp / chrony). A leaf package: it imports nothing of fleetdaq's.

- `fleetdaq.ptp.management`: a client for ptp4l's management interface over its UDS socket;
  `fleetdaq.ptp.pmc`: the same through linuxptp's pmc (its text parsed); both yield
  `fleetdaq.ptp.datasets`.
- `fleetdaq.ptp.chrony`: ``chronyc -c tracking``; `fleetdaq.ptp.host`: the kernel clock status
(read-only
  adjtimex), the interface's timestamping capabilities, PHC time.
- `fleetdaq.ptp.checks`: thresholds and checks, and the clock state (LOCKED / HOLDOVER / FREERUN);
  `fleetdaq.ptp.reader`: one reading after another with the memory holdover needs;
  `fleetdaq.ptp.time_status`: the
  result (`TimeStatus`), which node health carries and the hub's fleet view reads.
- `ptp/templates/`: ptp4l and phc2sys configuration for grandmaster and slave.
"""

from __future__ import annotations

from fleetdaq.ptp.quality import ClockQuality, ClockState

__all__ = ["ClockQuality", "ClockState"]
