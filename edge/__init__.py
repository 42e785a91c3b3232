"""The fleetdaq edge agent: drivers, acquisition loops, the spool, the device-clock fit, outputs
and their safe state. It imports the contract, the runtime and `fleetdaq.ptp`, never the hub."""

from __future__ import annotations
