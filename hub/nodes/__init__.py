"""The nodes wing: node health and its loss (`watch`), the fleet's time as the nodes report it
(`fleet_time`), the hub heartbeat the edges' dead-man timers listen to (`heartbeat`), the
acked delivery of the nodes' spooled events (`event_delivery`) and traffic on keys the site
file does not define (`refused`). `wiring` builds them."""

from __future__ import annotations
