"""fleetdaq hub: embedded Zenoh router, recorder, supervision, dashboard and the CLI."""

from __future__ import annotations
