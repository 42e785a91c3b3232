"""Alarms in the site file: the ones a site defines (`alarms:`), evaluated on the hub. The
universal ones every site gets without config (`hub.universal_alarms:`) are in
`fleetdaq.contract.config.universal_alarms`: a node reads them too (when to warn of its
certificate).

One entry is one alarm, about a channel, a stream, a node or the hub (which of `channel:`,
`stream:`, `node:` or `hub:` it names). A channel alarm with several limits (`hihi`, `hi`,
`lo`, `lolo`) is one alarm per limit (``name.hihi``, ``name.hi``...), each with its own
severity, and a ``name.fault`` alarm for invalid samples (a sensor fault) unless switched off.
"""

from __future__ import annotations

from typing import Annotated, Any, Literal

from pydantic import Discriminator, Field, Tag, model_validator

from fleetdaq.contract.config.universal_alarms import Severity
from fleetdaq.contract.schema import NAME, Float, Int, Strict

SEVERITIES: tuple[Severity, ...] = ("critical", "major", "minor", "info")
"""Most severe first."""

LIMITS = ("hihi", "hi", "lo", "lolo")
DEFAULT_LIMIT_SEVERITY: dict[str, Severity] = {
    "hihi": "critical",
    "hi": "major",
    "lo": "major",
    "lolo": "critical",
}

AlarmName = Annotated[str, Field(pattern=NAME)]
Seconds = Annotated[Float, Field(ge=0, le=7 * 24 * 3600)]


class _Common(Strict):
    severity: Severity = "major"
    delay_s: Seconds = 0.0
    """On-delay: the condition must hold this long before the alarm is raised."""
    off_delay_s: Seconds = 0.0
    """Off-delay: the condition must be gone this long before the alarm clears."""
    latch: bool = False
    """A latched alarm that clears before it was acked stays returned-unacked until acked."""
    description: str = ""
    """For people: what it means and what to do (goes into the e-mail)."""


class ChannelAlarm(_Common):
    """Limits on one channel's value, over every sample of every batch."""

    channel: Annotated[str, Field(pattern=r"^[^/\s]+/[^/\s]+/[^/\s]+$")]
    """``node/stream/channel``."""
    above: Float | None = None
    """Shorthand for one high limit (severity: `severity`)."""
    below: Float | None = None
    """Shorthand for one low limit (severity: `severity`)."""
    hihi: Float | None = None
    hi: Float | None = None
    lo: Float | None = None
    lolo: Float | None = None
    severities: dict[Literal["hihi", "hi", "lo", "lolo"], Severity] = {}
    """Per-limit severities (default: hihi/lolo critical, hi/lo major)."""
    deadband: Annotated[Float, Field(ge=0)] = 0.0
    """A raised limit alarm clears only once the value is this far back inside the limit."""
    sensor_fault: bool = True
    """Raise ``name.fault`` while samples are invalid (NaN, an open thermocouple, ...)."""
    fault_severity: Severity = "minor"

    @model_validator(mode="after")
    def _limits(self) -> ChannelAlarm:
        given = {k: getattr(self, k) for k in ("above", "below", *LIMITS)}
        given = {k: v for k, v in given.items() if v is not None}
        if not given:
            raise ValueError("a channel alarm needs a limit: above, below, hihi, hi, lo or lolo")
        if ("above" in given or "below" in given) and set(given) & set(LIMITS):
            raise ValueError("use either above/below or hihi/hi/lo/lolo, not both")
        order = [given.get(k) for k in ("lolo", "lo", "hi", "hihi")]
        present = [v for v in order if v is not None]
        if present != sorted(present):
            raise ValueError("limits must increase: lolo < lo < hi < hihi")
        return self

    def limits(self) -> list[tuple[str, str, float, Severity]]:
        """(suffix, direction "above"/"below", limit, severity) per limit; suffix "" for
        above/below."""
        out: list[tuple[str, str, float, Severity]] = []
        if self.above is not None:
            out.append(("", "above", self.above, self.severity))
        if self.below is not None:
            out.append(("", "below", self.below, self.severity))
        for name in LIMITS:
            value = getattr(self, name)
            if value is not None:
                direction = "above" if name in ("hi", "hihi") else "below"
                severity = self.severities.get(name, DEFAULT_LIMIT_SEVERITY[name])  # type: ignore[call-overload]
                out.append((f".{name}", direction, value, severity))
        return out


class BacklogLimit(Strict):
    key: str
    """A counter the driver reports in node health (e.g. ``ljm_scan_backlog``)."""
    above: Float


class StreamAlarm(_Common):
    """A stream's delivery: stale, slow, gaps, invalid samples, a device backlog, late polls."""

    stream: Annotated[str, Field(pattern=r"^[^/\s]+/[^/\s]+$")]
    """``node/stream``."""
    stale_s: Annotated[Float, Field(gt=0)] | None = None
    """No batch for this long."""
    min_rate_share: Annotated[Float, Field(gt=0, le=1)] | None = None
    """Scans per second below this share of the configured rate (over `window_s`)."""
    gaps: bool = False
    """Batches missing (waiting for a replay longer than `delay_s`) or lost for good."""
    invalid_share: Annotated[Float, Field(gt=0, le=1)] | None = None
    """More than this share of the samples invalid (over `window_s`)."""
    backlog: BacklogLimit | None = None
    late_polls: Annotated[Int, Field(ge=1)] | None = None
    """At least this many polls of a polled device not made on time (over `window_s`): the
    edge's host was too busy or stopped (not a sensor fault; no scans for those slots)."""
    window_s: Annotated[Float, Field(gt=0, le=3600)] = 10.0

    @model_validator(mode="after")
    def _one_condition(self) -> StreamAlarm:
        _exactly_one(
            self, ("stale_s", "min_rate_share", "gaps", "invalid_share", "backlog", "late_polls")
        )
        return self


HUB_MACHINE_CHECKS = (
    "cpu_percent_above",
    "memory_percent_above",
    "disk_free_percent_below",
    "temperature_above_c",
)
"""What a node alarm may watch on a hub's own machine (``node: hub``, or a partition hub's,
``node: hub/<name>``, which may also be `down_s`): a hub has no spool and no clock status."""


class NodeAlarm(_Common):
    """A node's health: down, its machine, its spool, its clock. ``node: hub`` (or a partition
    hub's ``hub/<name>``) watches a hub's own machine (`HUB_MACHINE_CHECKS`)."""

    node: Annotated[str, Field(pattern=r"^(hub/)?[a-z][a-z0-9_-]{0,62}$")]
    down_s: Annotated[Float, Field(gt=0)] | None = None
    """Not alive (no liveliness token) for this long."""
    cpu_percent_above: Annotated[Float, Field(gt=0, le=100)] | None = None
    memory_percent_above: Annotated[Float, Field(gt=0, le=100)] | None = None
    disk_free_percent_below: Annotated[Float, Field(gt=0, lt=100)] | None = None
    """Free space of the spool's filesystem."""
    temperature_above_c: Float | None = None
    spool_bytes_above: Annotated[Int, Field(gt=0)] | None = None
    unacked_age_above_s: Annotated[Float, Field(gt=0)] | None = None
    """The oldest batch waiting for the hub's ack is older than this."""
    clock_unlocked_s: Annotated[Float, Field(gt=0)] | None = None
    """The clock has not been LOCKED for this long."""
    offset_above_ns: Annotated[Int, Field(gt=0)] | None = None
    """|offset from the grandmaster| above this."""

    @model_validator(mode="after")
    def _one_condition(self) -> NodeAlarm:
        _exactly_one(
            self,
            (
                "down_s",
                "cpu_percent_above",
                "memory_percent_above",
                "disk_free_percent_below",
                "temperature_above_c",
                "spool_bytes_above",
                "unacked_age_above_s",
                "clock_unlocked_s",
                "offset_above_ns",
            ),
        )
        if self.node == "hub" or self.node.startswith("hub/"):
            allowed = HUB_MACHINE_CHECKS + (("down_s",) if self.node != "hub" else ())
            if not any(getattr(self, k) is not None for k in allowed):
                raise ValueError(
                    f"node: {self.node} is a hub's own machine: it may watch "
                    f"{', '.join(allowed)} (a hub has no spool and no clock status)"
                )
        return self


class HubAlarm(_Common):
    """The hub itself."""

    hub: Literal[
        "disk_free_percent_below", "write_errors", "notifications_failing", "recorder_stopped"
    ]
    threshold: Float | None = None
    """For disk_free_percent_below: the percentage; for notifications_failing: seconds."""

    @model_validator(mode="after")
    def _threshold(self) -> HubAlarm:
        needs = self.hub in ("disk_free_percent_below", "notifications_failing")
        if needs and self.threshold is None:
            raise ValueError(f"hub: {self.hub} needs a threshold")
        return self


def _exactly_one(model: Strict, names: tuple[str, ...]) -> None:
    given = [n for n in names if getattr(model, n) not in (None, False)]
    if len(given) != 1:
        raise ValueError(
            f"one condition per alarm (one of {', '.join(names)}); "
            + (f"got {', '.join(given)}: split it into several alarms" if given else "got none")
        )


def _kind(value: Any) -> str | None:
    """Which kind of alarm: the key it names (from YAML) or the field it has (a model)."""
    for key in ("channel", "stream", "node", "hub"):
        if key in value if isinstance(value, dict) else hasattr(value, key):
            return key
    return None


AlarmSpec = Annotated[
    Annotated[ChannelAlarm, Tag("channel")]
    | Annotated[StreamAlarm, Tag("stream")]
    | Annotated[NodeAlarm, Tag("node")]
    | Annotated[HubAlarm, Tag("hub")],
    Discriminator(_kind, custom_error_type="alarm_kind", custom_error_message=(
        "an alarm names what it watches: channel: node/stream/channel, stream: node/stream, "
        "node: NAME or hub: WHAT"
    )),
]  # fmt: skip


def alarm_names(site: Any) -> set[str]:
    """Every alarm name a site has (what `fleetdaq.hub.supervision.alarms.definitions` builds; a
    test keeps the two equal): so rules and the CLI can be checked against them when the site file
    is loaded."""
    u = site.hub.universal_alarms
    names: set[str] = set()
    if u.node_down:
        names |= {f"node_down/{n}" for n in site.nodes}
    if u.stream_stale:
        names |= {f"stream_stale/{n}/{s}" for n, c in site.nodes.items() for s in c.streams}
    if u.stream_gaps:
        names |= {f"stream_gaps/{n}/{s}" for n, c in site.nodes.items() for s in c.streams}
    if u.disk_nearly_full:
        names |= {"disk_nearly_full/hub", *(f"disk_nearly_full/{n}" for n in site.nodes)}
    if u.clock_unsynced:
        names |= {f"clock_unsynced/{n}" for n, c in site.nodes.items() if c.clock.source != "none"}
    if u.recorder:
        names.add("recorder/hub")
    if u.notifications_failing and site.hub.notify.groups:
        names.add("notifications_failing/hub")
    certificates = bool(u.certificate_expiring and site.security.tls)
    if certificates:
        names |= {"certificate_expiring/hub", *(f"certificate_expiring/{n}" for n in site.nodes)}
    for p in site.hub.partitions:  # each partition hub, watched from the main hub
        for kind, on in (("node_down", u.node_down), ("disk_nearly_full", u.disk_nearly_full),
                         ("recorder", u.recorder),
                         ("certificate_expiring", certificates)):  # fmt: skip
            if on:
                names.add(f"{kind}/hub/{p}")
    for name, spec in site.alarms.items():
        if isinstance(spec, ChannelAlarm):
            names |= {name + suffix for suffix, *_ in spec.limits()}
            if spec.sensor_fault:
                names.add(f"{name}.fault")
        else:
            names.add(name)
    return names
