"""The fleet's health as a ROS ``diagnostic_msgs/msg/DiagnosticArray`` (in JSON), what the
Diagnostics - Summary and Diagnostics - Detail panels of Foxglove and Lichtblick read.

One `DiagnosticStatus` per configured node (name ``fleetdaq/<node>``, hardware_id the node),
one for the hub (``fleetdaq/hub``) and one for the alarms (``fleetdaq/alarms``), built from the
hub's read model (pure: no I/O). The level is the worst of what is wrong, the message lists
it (``ok`` when nothing is):

- STALE: the node is not connected, or its health is older than 10 s (or never came);
- ERROR: a stream sends nothing (no batch for 5 s, or 3 batch lengths if longer) while its
  node is connected; the recording disk or the spool's filesystem under 5 % free; on the hub:
  a dead service, the recorder failed or refusing the disk;
- WARN: the clock is not locked to a grandmaster (holdover, free-running, unknown); under 10 %
  free; a spool backlog (oldest unacked batch older than 10 s) or batches the spool dropped;
  gaps in a stream this session (lost, missing, acquisition gaps); read errors; the hub not
  recording.

The alarms' status is ERROR while a critical or major alarm is in alarm (active or returned
unacked), WARN for a minor one.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Final

from fleetdaq.contract.messages import HostMetrics, NodeHealth
from fleetdaq.hub.config.site import SiteConfig
from fleetdaq.hub.live.foxglove.messages import HEADER, KEY_VALUES, iso, stamp
from fleetdaq.hub.read_model import HubView, JsonObject, NodeView, StreamView, member, number

OK: Final = 0
WARN: Final = 1
ERROR: Final = 2
STALE: Final = 3

HEALTH_STALE_NS: Final = 10_000_000_000
SILENT_STREAM_S: Final = 5.0
BACKLOG_S: Final = 10.0
IN_ALARM: Final = frozenset({"active_unacked", "active_acked", "returned_unacked"})
_SEVERITY_LEVEL: Final = {"critical": ERROR, "major": ERROR, "minor": WARN}

SCHEMA_NAME: Final = "diagnostic_msgs/msg/DiagnosticArray"
"""A name both apps' Diagnostics panels accept (their list: ``diagnostic_msgs/DiagnosticArray``,
``diagnostic_msgs/msg/DiagnosticArray``, ``ros.diagnostic_msgs.DiagnosticArray``)."""
SCHEMA: Final = {
    "title": SCHEMA_NAME,
    "description": "one status per node, the hub and the alarms, once a second",
    "type": "object",
    "properties": {
        "header": HEADER,
        "status": {
            "type": "array",
            "items": {
                "type": "object",
                "properties": {
                    "level": {"type": "integer", "minimum": 0, "description": "0 OK .. 3 STALE"},
                    "name": {"type": "string"},
                    "message": {"type": "string"},
                    "hardware_id": {"type": "string"},
                    "values": KEY_VALUES,
                },
            },
        },
    },
}


@dataclass(frozen=True, slots=True)
class ConfiguredStream:
    name: str
    rate_hz: float
    batch_s: float


def configured_streams(site: SiteConfig) -> dict[str, tuple[ConfiguredStream, ...]]:
    return {
        node: tuple(
            ConfiguredStream(name, s.rate_hz, s.batch_scans / s.rate_hz)
            for name, s in cfg.streams.items()
        )
        for node, cfg in site.nodes.items()
    }


class _Status:
    """One DiagnosticStatus being built: the worst level wins, every reason is kept."""

    def __init__(self, name: str, hardware_id: str) -> None:
        self.name = name
        self.hardware_id = hardware_id
        self.level = OK
        self.reasons: list[str] = []
        self.values: list[dict[str, str]] = []

    def problem(self, level: int, reason: str) -> None:
        # STALE outranks everything: nothing else said about a stale node is current.
        if self.level != STALE:
            self.level = level if level == STALE else max(self.level, level)
        self.reasons.append(reason)

    def value(self, key: str, value: object) -> None:
        self.values.append({"key": key, "value": str(value)})

    def done(self) -> JsonObject:
        return {
            "level": self.level,
            "name": self.name,
            "message": "; ".join(self.reasons) or "ok",
            "hardware_id": self.hardware_id,
            "values": self.values,
        }


def diagnostic_array(
    view: HubView, streams: dict[str, tuple[ConfiguredStream, ...]], now_ns: int
) -> JsonObject:
    status = [node_status(view.node(n), n, cs, view, now_ns) for n, cs in streams.items()]
    status.append(hub_status(view, now_ns))
    status += [partition_hub_status(view, h, now_ns) for h in view.partition_hubs]
    status.append(alarms_status(view))
    return {"header": {"stamp": stamp(now_ns), "frame_id": ""}, "status": status}


def node_status(
    nv: NodeView | None,
    node: str,
    streams: tuple[ConfiguredStream, ...],
    view: HubView,
    now_ns: int,
) -> JsonObject:
    s = _Status(f"fleetdaq/{node}", node)
    alive = nv is not None and nv.alive
    health = nv.health if nv is not None else None
    s.value("connected", "yes" if alive else "no")
    if not alive:
        s.problem(STALE, "not connected")
    if health is None:
        s.problem(STALE, "no health received")
    elif nv is not None and now_ns - nv.health_received_ns > HEALTH_STALE_NS:
        s.problem(STALE, f"health is {(now_ns - nv.health_received_ns) / 1e9:.0f} s old")
    if health is not None:
        _software(s, health)
        _host(s, health.host, "spool")
        _clock(s, health)
    for cs in streams:
        _stream(s, cs, view.stream(node, cs.name), health, alive, now_ns)
    return s.done()


def _software(s: _Status, h: NodeHealth) -> None:
    s.value("version", h.version)
    s.value("uptime", _duration(h.uptime_s))
    s.value("health time", iso(h.time_ns))
    if h.certificate_not_after_ns > 0:  # with TLS: the first of its pair and the CA
        s.value("certificate expires", iso(h.certificate_not_after_ns))


def _host(s: _Status, host: HostMetrics, disk_role: str) -> None:
    s.value("cpu", f"{host.cpu_percent:.1f} %")
    s.value("load (1, 5, 15 min)", f"{host.load_1m:.2f} {host.load_5m:.2f} {host.load_15m:.2f}")
    total, avail = host.memory_total_bytes, host.memory_available_bytes
    used = 100.0 * (total - avail) / total if total > 0 else math.nan
    s.value("memory used", f"{used:.1f} % of {_bytes(total)}")
    s.value("process memory (RSS)", _bytes(host.process_rss_bytes))
    temp = host.cpu_temperature_c
    s.value("cpu temperature", f"{temp:.1f} °C" if math.isfinite(temp) else "n/a")
    s.value("host uptime", _duration(host.host_uptime_s))
    for d in host.disks:
        free = 100.0 * d.free_bytes / d.total_bytes if d.total_bytes > 0 else math.nan
        s.value(f"disk {d.role} free", f"{_bytes(d.free_bytes)} of {_bytes(d.total_bytes)} "
                f"({free:.1f} %) at {d.path}")  # fmt: skip
        if d.role == disk_role and free < 5:
            s.problem(ERROR, f"{d.role} disk {free:.1f} % free")
        elif d.role == disk_role and free < 10:
            s.problem(WARN, f"{d.role} disk {free:.1f} % free")


def _clock(s: _Status, h: NodeHealth) -> None:
    c = h.clock
    s.value("clock state", c.state if c.known else "unknown")
    s.value("clock source", c.source)
    s.value("clock check", c.level or "n/a")
    s.value("clock offset", f"{c.offset_ns} ns" if c.known and c.has_offset else "n/a")
    s.value("grandmaster", c.grandmaster_id or "none")
    s.value("port state", c.port_state or "n/a")
    if not c.known:
        s.problem(WARN, "clock sync unknown")
    elif c.state != "locked":
        s.problem(WARN, f"clock {c.state} ({c.source})")


def _stream(
    s: _Status,
    cs: ConfiguredStream,
    sv: StreamView | None,
    health: NodeHealth | None,
    alive: bool,
    now_ns: int,
) -> None:
    n = cs.name
    if sv is not None:
        s.value(f"{n} rate", f"{sv.scan_rate:.1f} of {cs.rate_hz:g} scans/s")
        s.value(f"{n} batches", sv.batches)
        s.value(f"{n} gaps", f"{sv.gaps} (lost {sv.lost}, missing {sv.missing}, "
                f"acquisition gaps {sv.acquisition_gaps})")  # fmt: skip
        if sv.lost or sv.missing or sv.acquisition_gaps:
            s.problem(WARN, f"{n}: gaps this session (lost {sv.lost}, missing {sv.missing}, "
                      f"acquisition gaps {sv.acquisition_gaps})")  # fmt: skip
        silent_s = (now_ns - sv.last_receive_ns) / 1e9
        if alive and sv.last_receive_ns == 0:
            s.problem(WARN, f"{n}: no batch yet")
        elif alive and silent_s > max(SILENT_STREAM_S, 3 * cs.batch_s):
            s.problem(ERROR, f"{n}: no batch for {silent_s:.0f} s")
    st = health.stream(n) if health is not None else None
    if st is None:
        return
    s.value(f"{n} spool", f"{_bytes(st.spool_bytes)}, last ack {st.spool_acked}, "
            f"oldest unacked {st.oldest_unacked_age_s:.1f} s")  # fmt: skip
    s.value(f"{n} invalid samples", st.invalid_samples)
    s.value(f"{n} read errors", st.read_errors)
    if st.oldest_unacked_age_s > BACKLOG_S:
        s.problem(WARN, f"{n}: spool backlog {st.oldest_unacked_age_s:.0f} s")
    if st.spool_dropped_batches:
        s.problem(WARN, f"{n}: spool dropped {st.spool_dropped_batches} batches")
    if st.read_errors:
        s.problem(WARN, f"{n}: {st.read_errors} read errors")


def _hub_machine(
    s: _Status, h: NodeHealth | None, received_ns: int, now_ns: int, none: str, what: str
) -> None:
    """A hub's own machine (its health, received at `received_ns`): stale or missing said
    (`none`, "`what` is N s old"), else its software and host with the recording disk."""
    if h is None:
        s.problem(STALE, none)
        return
    if now_ns - received_ns > HEALTH_STALE_NS:
        s.problem(STALE, f"{what} is {(now_ns - received_ns) / 1e9:.0f} s old")
    _software(s, h)
    _host(s, h.host, "data")


def hub_status(view: HubView, now_ns: int) -> JsonObject:
    s = _Status("fleetdaq/hub", "hub")
    h = view.hub_health
    _hub_machine(s, h, h.time_ns if h is not None else 0, now_ns, "no hub health yet", "hub health")
    r = view.recorder
    s.value("recorder", r.state)
    s.value("session", r.session or "none")
    s.value("current file", f"{r.current_file or 'none'} ({_bytes(r.current_file_bytes)})")
    s.value("files closed", len(r.files))
    s.value("write errors", r.write_errors)
    s.value("refused traffic", view.refused_total)
    s.value("events not recorded", r.events_not_recorded)
    dropped = sum(int(number(b, "dropped") or 0) for b in view.bus)
    s.value("event bus drops", dropped)
    if view.notifier:
        s.value("mails queued", view.notifier.get("queued", 0))
    for name, why in view.failures:
        s.problem(ERROR, f"service {name} failed: {why}")
    if r.state in ("failed", "disk_error"):
        s.problem(ERROR, f"recorder {r.state}")
    elif r.state != "recording":
        s.problem(WARN, f"recorder {r.state}")
    return s.done()


def partition_hub_status(view: HubView, hub: NodeView, now_ns: int) -> JsonObject:
    """A partition hub (``hub/<name>``): its machine, from its own health, and its recorder,
    from its report."""
    s = _Status(f"fleetdaq/{hub.node}", hub.node)
    if not hub.alive:
        s.problem(ERROR, "gone (its nodes spool until it returns)")
    _hub_machine(
        s, hub.health, hub.health_received_ns, now_ns, "no health from it yet", "its health"
    )
    r = member(view.partitions.get(hub.node.removeprefix("hub/")) or {}, "recorder")
    s.value("recorder", r.get("state", "no report yet"))
    s.value("session", r.get("session") or "none")
    if r.get("state") in ("failed", "disk_error"):
        s.problem(ERROR, f"recorder {r['state']}")
    elif r and r.get("state") != "recording":
        s.problem(WARN, f"recorder {r.get('state')}")
    return s.done()


def alarms_status(view: HubView) -> JsonObject:
    s = _Status("fleetdaq/alarms", "hub")
    in_alarm = [a for a in view.alarms if a.state in IN_ALARM]
    s.value("alarms", len(view.alarms))
    s.value("in alarm", len(in_alarm))
    s.value("shelved", sum(a.state == "shelved" for a in view.alarms))
    for a in in_alarm:
        value = f", value {a.value:.6g} {a.unit}".rstrip() if math.isfinite(a.value) else ""
        since = f", since {iso(a.since_ns)}" if a.since_ns > 0 else ""
        s.value(a.name, f"{a.state}, {a.severity}{value}{since}")
        s.problem(_SEVERITY_LEVEL.get(a.severity, OK), f"{a.name} ({a.severity}, {a.state})")
    return s.done()


def _bytes(n: int) -> str:
    x = float(n)
    for unit in ("B", "KB", "MB", "GB", "TB"):
        if abs(x) < 1000 or unit == "TB":
            return f"{x:.0f} {unit}" if unit == "B" else f"{x:.1f} {unit}"
        x /= 1000
    return f"{x:.1f} TB"


def _duration(s: float) -> str:
    if not math.isfinite(s) or s < 0:
        return "n/a"
    d, rest = divmod(int(s), 86400)
    h, rest = divmod(rest, 3600)
    m, sec = divmod(rest, 60)
    return (f"{d} d " if d else "") + f"{h:02d}:{m:02d}:{sec:02d}"
