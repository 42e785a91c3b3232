"""The supervision wing's factory: events.log, the hub's own health and certificates, and on
the main hub the alarms (supervisor, alarm requests) and the e-mail notifier."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

from fleetdaq.hub.context import HubContext
from fleetdaq.hub.nodes.event_delivery import EventDelivery
from fleetdaq.hub.read_model import HubView
from fleetdaq.hub.recording.batch_feed import BatchFeed
from fleetdaq.hub.recording.recorder import Recorder
from fleetdaq.hub.supervision.alarms.requests import AlarmRequests
from fleetdaq.hub.supervision.alarms.supervisor import Supervisor
from fleetdaq.hub.supervision.certificates import CertificateWatch
from fleetdaq.hub.supervision.event_log import EventLog
from fleetdaq.hub.supervision.hub_health import HubHealth
from fleetdaq.hub.supervision.notify.service import EmailNotifier


@dataclass(frozen=True, slots=True)
class Alarms:
    """The main hub's alarms and where they are mailed."""

    notifier: EmailNotifier
    supervisor: Supervisor
    requests: AlarmRequests


@dataclass(frozen=True, slots=True)
class SupervisionWing:
    certificates: CertificateWatch | None
    """With TLS on only."""
    hub_health: HubHealth
    alarms: Alarms | None
    """The main hub's only."""


def event_log(ctx: HubContext, delivery: EventDelivery | None) -> EventLog:
    """events.log; `delivery` is told which of the nodes' spooled events it wrote."""
    return EventLog(ctx.paths.events_log, ctx.bus, ctx.model, delivery=delivery)


def build(
    ctx: HubContext,
    recorder: Recorder,
    feed: BatchFeed,
    view: Callable[[], HubView],
    alarms: bool,
    also_from: Sequence[BatchFeed] = (),
) -> SupervisionWing:
    """`alarms`: also the alarms and the notifier (the main hub). `also_from`: batches the
    recorder never takes that the alarms watch (a partition's)."""
    site = ctx.site
    certificates = (
        CertificateWatch(site, ctx.model, ctx.bus, ctx.partition) if site.security.tls else None
    )
    hub_health = HubHealth(
        ctx.paths.data_dir,
        ctx.model,
        recorder,
        node=ctx.event_node,
        certificates=certificates,
    )
    if not alarms:
        return SupervisionWing(certificates, hub_health, None)
    notifier = EmailNotifier(site.hub.notify, site.site, ctx.paths.outbox, ctx.bus, ctx.model)
    supervisor = Supervisor(
        site,
        ctx.bus,
        ctx.model,
        recorder,
        feed,
        ctx.paths.alarm_journal,
        notifier=notifier,
        snapshot=view,
        also_from=also_from,
    )
    requests = AlarmRequests(ctx.router, ctx.keys, supervisor, site.security)
    return SupervisionWing(certificates, hub_health, Alarms(notifier, supervisor, requests))
