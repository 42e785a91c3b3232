"""The supervision wing: ISA-18.2 alarms (`alarms`), notifications through the on-disk outbox
(`notify`, `notification`), the event log (`event_log`), the hub's own health
(`hub_health`) and the certificates it serves with (`certificates`). `wiring` builds them."""

from __future__ import annotations
