"""The nodes wing's factory: what a hub builds to hear its nodes.

`intake` comes first (the recorder needs it: refused keys are counted and spooled events acked
where data arrives); `build` then makes the node watch, and on the main hub the fleet's time
view and the heartbeat every edge's dead-man hears."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from fleetdaq.hub.context import HubContext
from fleetdaq.hub.nodes.event_delivery import EventDelivery
from fleetdaq.hub.nodes.fleet_time import FleetTimeService
from fleetdaq.hub.nodes.heartbeat import Heartbeat
from fleetdaq.hub.nodes.refused import RefusedKeys
from fleetdaq.hub.nodes.watch import NodeWatch
from fleetdaq.hub.recording.recorder import Recorder


@dataclass(frozen=True, slots=True)
class NodeIntake:
    """What the recorder and the node watch share: refused keys, and the nodes' spooled events
    (ordered, deduplicated, acked once recorded and in events.log)."""

    refused: RefusedKeys
    events: EventDelivery


@dataclass(frozen=True, slots=True)
class NodesWing:
    watch: NodeWatch
    fleet: FleetTimeService | None
    """The main hub's only (the whole fleet's time)."""
    heartbeat: Heartbeat | None
    """The main hub's only (outputs, and so their dead-man, are the main hub's)."""


def intake(ctx: HubContext, log_sync: Callable[[], bool]) -> NodeIntake:
    """`log_sync`: the event log's fsync, done before spooled events are acked."""
    recorded = set(ctx.site.nodes_of(ctx.partition))
    return NodeIntake(RefusedKeys(ctx.bus, ctx.model), EventDelivery(recorded, log_sync=log_sync))


def build(ctx: HubContext, intake: NodeIntake, recorder: Recorder, whole_fleet: bool) -> NodesWing:
    """`whole_fleet`: also the fleet's time view and the heartbeat (the main hub)."""
    fleet = FleetTimeService(ctx.bus, ctx.model) if whole_fleet else None
    watch = NodeWatch(
        ctx.router,
        ctx.site,
        ctx.bus,
        ctx.model,
        recorder,
        intake.refused,
        intake.events,
        partition=ctx.partition,
        health_listeners=[fleet.fleet.update] if fleet is not None else None,
        alive_listeners=[fleet.fleet.on_alive] if fleet is not None else None,
    )

    def session_name() -> str:
        s = recorder.session
        return s.name if s is not None else ""

    heartbeat = Heartbeat(ctx.router, ctx.keys, session_name) if whole_fleet else None
    return NodesWing(watch, fleet, heartbeat)
