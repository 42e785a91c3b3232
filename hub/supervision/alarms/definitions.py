"""Every alarm the hub evaluates, as plain definitions built once from the site file: the site's
own alarms (one per limit, plus a sensor-fault alarm per channel alarm) and the universal ones
(per node, per stream, on the hub)."""

from __future__ import annotations

from dataclasses import dataclass, field

from fleetdaq.contract.config.universal_alarms import Severity, UniversalRule
from fleetdaq.hub.config.alarms import ChannelAlarm, HubAlarm, NodeAlarm, StreamAlarm
from fleetdaq.hub.config.site import SiteConfig
from fleetdaq.runtime.certificate_dates import HUB_AGAIN, ROTATE, node_again, partition_again


@dataclass(frozen=True, slots=True)
class AlarmDef:
    name: str
    kind: str
    """"channel", "stream", "node" or "hub"."""
    check: str
    """What is checked: "above", "below", "fault" (channel); "stale", "rate", "gaps",
    "invalid", "backlog", "late_polls" (stream); "down", "cpu", "memory", "disk",
    "temperature", "spool", "unacked_age", "clock_unlocked", "offset", "certificate" (node);
    "hub_disk", "write_errors", "notifications_failing", "recorder_stopped", "recorder",
    "partition_down", "partition_disk", "partition_recorder", "certificate_expiring" (hub)."""
    condition: str
    """For people: "above 400 degC", "no batch for 5 s", ..."""
    severity: Severity
    node: str = ""
    stream: str = ""
    channel: str = ""
    unit: str = ""
    threshold: float = 0.0
    deadband: float = 0.0
    delay_s: float = 0.0
    off_delay_s: float = 0.0
    latch: bool = False
    description: str = ""
    universal: bool = False
    options: dict[str, object] = field(default_factory=dict)


def _unit(site: SiteConfig, node: str, stream: str, channel: str) -> str:
    for ch in site.nodes[node].streams[stream].channels:
        if ch.name == channel:
            return ch.unit
    return ""


def _channel_alarms(site: SiteConfig, name: str, spec: ChannelAlarm) -> list[AlarmDef]:
    node, stream, channel = spec.channel.split("/")
    unit = _unit(site, node, stream, channel)
    common = {
        "kind": "channel",
        "node": node,
        "stream": stream,
        "channel": channel,
        "unit": unit,
        "delay_s": spec.delay_s,
        "off_delay_s": spec.off_delay_s,
        "latch": spec.latch,
        "description": spec.description,
    }
    out = [
        AlarmDef(
            name=name + suffix,
            check=direction,
            condition=f"{channel} {direction} {limit:g} {unit}".rstrip(),
            severity=severity,
            threshold=limit,
            deadband=spec.deadband,
            **common,  # type: ignore[arg-type]
        )
        for suffix, direction, limit, severity in spec.limits()
    ]
    if spec.sensor_fault:
        out.append(
            AlarmDef(
                name=f"{name}.fault",
                check="fault",
                condition=f"{channel}: invalid samples (sensor fault)",
                severity=spec.fault_severity,
                **common,  # type: ignore[arg-type]
            )
        )
    return out


def _stream_alarm(name: str, spec: StreamAlarm) -> AlarmDef:
    node, stream = spec.stream.split("/")
    check, threshold, condition = "stale", 0.0, ""
    options: dict[str, object] = {"window_s": spec.window_s}
    if spec.stale_s is not None:
        check, threshold, condition = "stale", spec.stale_s, f"no batch for {spec.stale_s:g} s"
    elif spec.min_rate_share is not None:
        check, threshold = "rate", spec.min_rate_share
        condition = f"scan rate below {spec.min_rate_share:.0%} of the configured rate"
    elif spec.gaps:
        check, condition = "gaps", "batches missing or lost"
    elif spec.invalid_share is not None:
        check, threshold = "invalid", spec.invalid_share
        condition = f"more than {spec.invalid_share:.0%} of the samples invalid"
    elif spec.late_polls is not None:
        check, threshold = "late_polls", float(spec.late_polls)
        condition = f"{spec.late_polls} poll(s) or more not made on time (a busy or stopped edge)"
    elif spec.backlog is not None:
        check, threshold = "backlog", spec.backlog.above
        options["key"] = spec.backlog.key
        condition = f"{spec.backlog.key} above {spec.backlog.above:g}"
    return AlarmDef(
        name=name,
        kind="stream",
        check=check,
        condition=condition,
        severity=spec.severity,
        node=node,
        stream=stream,
        threshold=threshold,
        delay_s=spec.delay_s,
        off_delay_s=spec.off_delay_s,
        latch=spec.latch,
        description=spec.description,
        options=options,
    )


_NODE_CHECKS = {
    "down_s": ("down", "not alive for {:g} s", "s"),
    "cpu_percent_above": ("cpu", "CPU above {:g} %", "%"),
    "memory_percent_above": ("memory", "memory use above {:g} %", "%"),
    "disk_free_percent_below": ("disk", "spool disk free below {:g} %", "%"),
    "temperature_above_c": ("temperature", "CPU temperature above {:g} °C", "degC"),
    "spool_bytes_above": ("spool", "spool above {:g} bytes", "B"),
    "unacked_age_above_s": ("unacked_age", "oldest unacked batch older than {:g} s", "s"),
    "clock_unlocked_s": ("clock_unlocked", "clock not LOCKED for {:g} s", "s"),
    "offset_above_ns": ("offset", "|clock offset| above {:g} ns", "ns"),
}


def _node_alarm(name: str, spec: NodeAlarm) -> AlarmDef:
    for key, (check, text, unit) in _NODE_CHECKS.items():
        value = getattr(spec, key)
        if value is not None:
            is_hub = spec.node == "hub" or spec.node.startswith("hub/")
            what = "recording disk free below {:g} %" if check == "disk" and is_hub else text
            return AlarmDef(
                name=name,
                kind="node",
                check=check,
                condition=f"{spec.node}: " + what.format(value),
                severity=spec.severity,
                node=spec.node,
                unit=unit,
                threshold=float(value),
                delay_s=spec.delay_s,
                off_delay_s=spec.off_delay_s,
                latch=spec.latch,
                description=spec.description,
            )
    raise AssertionError("a node alarm has one condition (checked by its schema)")


def _hub_alarm(name: str, spec: HubAlarm) -> AlarmDef:
    text = {
        "disk_free_percent_below": "recording disk free below {:g} %",
        "write_errors": "the recorder cannot write",
        "notifications_failing": "notifications undelivered for {:g} s",
        "recorder_stopped": "the recorder is not recording",
    }[spec.hub]
    check = {"disk_free_percent_below": "hub_disk"}.get(spec.hub, spec.hub)
    return AlarmDef(
        name=name,
        kind="hub",
        check=check,
        condition=text.format(spec.threshold or 0),
        severity=spec.severity,
        node="hub",
        threshold=float(spec.threshold or 0),
        delay_s=spec.delay_s,
        off_delay_s=spec.off_delay_s,
        latch=spec.latch,
        description=spec.description,
    )


def _universal(site: SiteConfig) -> list[AlarmDef]:
    u = site.hub.universal_alarms
    out: list[AlarmDef] = []

    def rule(r: UniversalRule | bool) -> UniversalRule | None:
        return r if isinstance(r, UniversalRule) else None

    if (r := rule(u.node_down)) is not None:
        for node in site.nodes:
            after = r.after_s if r.after_s is not None else 10.0
            out.append(
                AlarmDef(
                    f"node_down/{node}", "node", "down", f"{node}: not alive for {after:g} s",
                    r.severity, node=node, threshold=after, latch=r.latch, universal=True,
                )
            )  # fmt: skip
    if (r := rule(u.stream_stale)) is not None:
        for node, cfg in site.nodes.items():
            for stream, s in cfg.streams.items():
                after = (
                    r.after_s if r.after_s is not None else max(5.0, 3 * s.batch_scans / s.rate_hz)
                )
                out.append(
                    AlarmDef(
                        f"stream_stale/{node}/{stream}", "stream", "stale",
                        f"{node}/{stream}: no batch for {after:g} s", r.severity, node=node,
                        stream=stream, threshold=after, latch=r.latch, universal=True,
                    )
                )  # fmt: skip
    if (r := rule(u.stream_gaps)) is not None:
        for node, cfg in site.nodes.items():
            for stream in cfg.streams:
                out.append(
                    AlarmDef(
                        f"stream_gaps/{node}/{stream}", "stream", "gaps",
                        f"{node}/{stream}: batches lost, or missing for {r.after_s or 0:g} s",
                        r.severity, node=node, stream=stream, threshold=r.after_s or 0.0,
                        latch=r.latch, universal=True,
                    )
                )  # fmt: skip
    if (r := rule(u.disk_nearly_full)) is not None:
        pct = r.threshold if r.threshold is not None else 5.0
        out.append(
            AlarmDef(
                "disk_nearly_full/hub", "hub", "hub_disk", f"recording disk free below {pct:g} %",
                r.severity, node="hub", unit="%", threshold=pct, latch=r.latch, universal=True,
            )
        )  # fmt: skip
        for node in site.nodes:
            out.append(
                AlarmDef(
                    f"disk_nearly_full/{node}", "node", "disk",
                    f"{node}: spool disk free below {pct:g} %", r.severity, node=node, unit="%",
                    threshold=pct, latch=r.latch, universal=True,
                )
            )  # fmt: skip
    if (r := rule(u.clock_unsynced)) is not None:
        for node, cfg in site.nodes.items():
            if cfg.clock.source != "none":
                after = r.after_s if r.after_s is not None else 30.0
                out.append(
                    AlarmDef(
                        f"clock_unsynced/{node}", "node", "clock_unlocked",
                        f"{node}: clock not LOCKED for {after:g} s", r.severity, node=node,
                        threshold=after, latch=r.latch, universal=True,
                    )
                )  # fmt: skip
    if (r := rule(u.recorder)) is not None:
        out.append(
            AlarmDef(
                "recorder/hub", "hub", "recorder", "the recorder cannot write or has stopped",
                r.severity, node="hub", latch=r.latch, universal=True,
            )
        )  # fmt: skip
    out += _partition_hubs(site, rule(u.node_down), rule(u.disk_nearly_full), rule(u.recorder))
    if (r := rule(u.certificate_expiring)) is not None and site.security.tls:
        out += _certificates(site, r)
    if (r := rule(u.notifications_failing)) is not None and site.hub.notify.groups:
        after = r.after_s if r.after_s is not None else 600.0
        out.append(
            AlarmDef(
                "notifications_failing/hub", "hub", "notifications_failing",
                f"notifications undelivered for {after:g} s", r.severity, node="hub",
                threshold=after, latch=r.latch, universal=True,
            )
        )  # fmt: skip
    return out


def _certificates(site: SiteConfig, r: UniversalRule) -> list[AlarmDef]:
    """``certificate_expiring/hub`` (this hub's pair or the site CA,
    `fleetdaq.hub.supervision.certificates`),
    ``/<node>`` and ``/hub/<P>`` (the first of a node's or partition hub's pair and the CA,
    from its health): the value is the days left."""
    days = r.threshold if r.threshold is not None else 30.0
    out = [
        AlarmDef(
            "certificate_expiring/hub", "hub", "certificate_expiring",
            f"the hub's certificate or the site CA expires within {days:g} days", r.severity,
            node="hub", unit="days", threshold=days, latch=r.latch, universal=True,
            description=f"Past it no edge connects (they spool). The hub's own pair: {HUB_AGAIN}"
            " (the same CA), copy hub.crt and hub.key to the hub, restart it. The site CA: "
            f"rotate ({ROTATE}), re-issue every pair, copy them out, restart hub and edges.",
        )
    ]  # fmt: skip
    for node in site.nodes:
        out.append(
            AlarmDef(
                f"certificate_expiring/{node}", "node", "certificate",
                f"{node}: its certificate or the site CA expires within {days:g} days",
                r.severity, node=node, unit="days", threshold=days, latch=r.latch,
                universal=True,
                description=f"Past it the hub refuses {node} (it spools). Issue a new pair "
                f"({node_again(node)}), copy it to the node, restart its edge.",
            )
        )  # fmt: skip
    for p in site.hub.partitions:
        out.append(
            AlarmDef(
                f"certificate_expiring/hub/{p}", "node", "certificate",
                f"partition hub {p}: its certificate or the site CA expires within {days:g} days",
                r.severity, node=f"hub/{p}", unit="days", threshold=days, latch=r.latch,
                universal=True,
                description=f"Past it partition {p}'s nodes no longer reach the main hub. Issue "
                f"a new pair ({partition_again(p)}), copy it, restart it.",
            )
        )  # fmt: skip
    return out


def _partition_hubs(
    site: SiteConfig,
    down: UniversalRule | None,
    disk: UniversalRule | None,
    recorder: UniversalRule | None,
) -> list[AlarmDef]:
    """Each partition hub of a partitioned site, watched from the main hub as it watches itself
    and its nodes (from the partition's liveliness token and report): ``node_down/hub/P``,
    ``disk_nearly_full/hub/P``, ``recorder/hub/P``."""
    out: list[AlarmDef] = []
    for p in site.hub.partitions:
        node = f"hub/{p}"
        if down is not None:
            after = down.after_s if down.after_s is not None else 10.0
            out.append(
                AlarmDef(
                    f"node_down/{node}", "hub", "partition_down",
                    f"partition hub {p}: not there for {after:g} s", down.severity, node=node,
                    threshold=after, latch=down.latch, universal=True,
                )
            )  # fmt: skip
        if disk is not None:
            pct = disk.threshold if disk.threshold is not None else 5.0
            out.append(
                AlarmDef(
                    f"disk_nearly_full/{node}", "hub", "partition_disk",
                    f"partition hub {p}: recording disk free below {pct:g} %", disk.severity,
                    node=node, unit="%", threshold=pct, latch=disk.latch, universal=True,
                )
            )  # fmt: skip
        if recorder is not None:
            out.append(
                AlarmDef(
                    f"recorder/{node}", "hub", "partition_recorder",
                    f"partition hub {p}: the recorder cannot write", recorder.severity,
                    node=node, latch=recorder.latch, universal=True,
                )
            )  # fmt: skip
    return out


def build_definitions(site: SiteConfig) -> list[AlarmDef]:
    """Every alarm of the site: universal ones first, then the site's own."""
    out = _universal(site)
    for name, spec in site.alarms.items():
        if isinstance(spec, ChannelAlarm):
            out += _channel_alarms(site, name, spec)
        elif isinstance(spec, StreamAlarm):
            out.append(_stream_alarm(name, spec))
        elif isinstance(spec, NodeAlarm):
            out.append(_node_alarm(name, spec))
        else:
            out.append(_hub_alarm(name, spec))
    return out
