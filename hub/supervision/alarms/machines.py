"""Node and hub-machine alarms judged from the read model: a node's (or a hub machine's) last
health, and a partition hub's state as the main hub sees it (`fleetdaq.hub.partitions.watch`).
Pure functions of a `HubView`; the supervisor calls them on its tick."""

from __future__ import annotations

import math

from fleetdaq.contract.keys import HUB
from fleetdaq.hub.read_model import HubView, JsonObject, NodeView, member, number
from fleetdaq.hub.supervision.alarms.definitions import AlarmDef

HEALTH_FRESH_NS = 10_000_000_000
"""Health older than this is not used for node alarms (node_down says the node is gone)."""


def node_check(d: AlarmDef, node: NodeView | None, now: int) -> tuple[bool, float]:
    """A node alarm's condition and value, from the node's (or a hub machine's) last health;
    nothing to judge (False, NaN) without a fresh one."""
    if d.check == "down":
        return not (node is not None and node.alive), math.nan
    health = node.health if node is not None else None
    if d.check == "certificate" and health is not None:
        # From its last health, fresh or not: a node whose pair has expired cannot connect
        # to say so, and this alarm says why it is down. 0: no TLS, or it cannot tell.
        ends = health.certificate_not_after_ns
        if ends <= 0:
            return False, math.nan
        days = (ends - now) / 86_400e9
        return days < d.threshold, days
    if health is None or now - health.time_ns > HEALTH_FRESH_NS:
        return False, math.nan
    host = health.host
    if d.check == "cpu":
        return host.cpu_percent > d.threshold, host.cpu_percent
    if d.check == "memory":
        total = host.memory_total_bytes
        used = 100.0 * (1 - host.memory_available_bytes / total) if total else 0.0
        return used > d.threshold, used
    if d.check == "disk":  # where a node spools; where a hub records
        disk = host.disk("data" if d.node.split("/")[0] == HUB else "spool")
        if disk is None or not disk.total_bytes:
            return False, math.nan
        free = 100.0 * disk.free_bytes / disk.total_bytes
        return free < d.threshold, free
    if d.check == "temperature":
        temp = host.cpu_temperature_c
        return bool(temp > d.threshold), temp
    if d.check == "spool":
        total_bytes = float(sum(s.spool_bytes for s in health.streams))
        return total_bytes > d.threshold, total_bytes
    if d.check == "unacked_age":
        age = max((s.oldest_unacked_age_s for s in health.streams), default=0.0)
        return age > d.threshold, age
    status = health.time_status()
    if d.check == "clock_unlocked":
        locked = status is not None and status.state.value == "locked"
        return not locked, math.nan
    if d.check == "offset":
        if status is None or status.offset_ns is None:
            return False, math.nan
        return abs(status.offset_ns) > d.threshold, float(status.offset_ns)
    return False, math.nan


def machine(view: HubView, node: str) -> NodeView | None:
    """A node, or a hub's own machine: ``hub`` (this hub's health) or ``hub/<name>`` (a
    partition hub's, as the main hub last heard it)."""
    if node == HUB:
        h = view.hub_health
        return NodeView(HUB, True, h, h.time_ns) if h is not None else None
    if node.startswith(HUB + "/"):
        return next((p for p in view.partition_hubs if p.node == node), None)
    return view.node(node)


def partition_check(d: AlarmDef, p: JsonObject) -> tuple[bool, float]:
    """A partition hub's alarm from its state in the read model (`PartitionWatch`: its
    liveliness, and its last report, checked field by field)."""
    if d.check == "partition_down":
        return not p.get("alive"), math.nan
    if d.check == "partition_recorder":
        rec = member(p, "recorder")
        errors = number(rec, "write_errors") or 0
        return rec.get("state") in ("disk_error", "failed"), float(errors)
    disk = member(p, "data_disk")
    total = number(disk, "total_bytes")
    if not total:
        return False, math.nan
    free = 100.0 * (number(disk, "free_bytes") or 0) / total
    return free < d.threshold, free
