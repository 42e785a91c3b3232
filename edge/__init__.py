"""fleetdaq edge agent: drivers, acquisition loops, timing and the wire contract."""

from __future__ import annotations

__version__ = "0.1.0"
