"""The hub's composition root: every service of a hub, built from one `HubContext` by the wings'
factories, wired to each other here and nowhere else, and put in start order.

The main hub and a partition hub are composed by the same `compose`; what differs is said in
two places only, both here: which parts a hub runs (`HubShape`: `MAIN_HUB`, `PARTITION_HUB`)
and the start order (`_start_order`).

Each service gets what it needs of another wing through its constructor (a callable, or an
object typed by a small protocol); none sets another's attributes. Two pairs need each other:
the event log and the event delivery (the log tells which events it wrote, the delivery asks
the log to fsync before an ack), and the recorder and the snapshot buffer (the recorder hands
the buffer every message; the buffer asks whether the recorder records). For each pair one
side gets a callable that reaches the other once both exist, made here; no service is running
before both are built."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from fleetdaq.contract.keys import SiteKeys
from fleetdaq.hub.bus import EventBus
from fleetdaq.hub.config.site import SiteConfig
from fleetdaq.hub.context import HubContext, HubPaths, event_node
from fleetdaq.hub.control import wiring as control
from fleetdaq.hub.control.wiring import ControlWing
from fleetdaq.hub.live import wiring as live
from fleetdaq.hub.live.web.service import WebService
from fleetdaq.hub.live.wiring import LiveWing
from fleetdaq.hub.nodes import wiring as nodes
from fleetdaq.hub.nodes.wiring import NodeIntake, NodesWing
from fleetdaq.hub.partitions import wiring as partitions
from fleetdaq.hub.partitions.live import PartitionLive
from fleetdaq.hub.partitions.recorders import PartitionRecorders
from fleetdaq.hub.partitions.wiring import OwnPartition, Partitions
from fleetdaq.hub.read_model import HubView, ReadModel
from fleetdaq.hub.recording import wiring as recording
from fleetdaq.hub.recording.data_lock import DataFolderClaim, DataFolderLock, Place
from fleetdaq.hub.recording.recorder import Recorder
from fleetdaq.hub.recording.requests import RecorderRequests
from fleetdaq.hub.recording.seams import FORWARDED
from fleetdaq.hub.recording.snapshots import SnapshotBuffer
from fleetdaq.hub.recording.wiring import RecordingWing
from fleetdaq.hub.routing.refused_traffic import RefusedTraffic
from fleetdaq.hub.routing.router import Router
from fleetdaq.hub.services import Service
from fleetdaq.hub.supervision import wiring as supervision
from fleetdaq.hub.supervision.event_log import EventLog
from fleetdaq.hub.supervision.wiring import SupervisionWing


class BusService:
    """The event bus's lifecycle in the stack (its subscribers' threads)."""

    name = "event-bus"

    def __init__(self, bus: EventBus) -> None:
        self.bus = bus

    def start(self) -> None:
        self.bus.start()

    def stop(self) -> None:
        self.bus.stop()

    def failure(self) -> str | None:
        dead = self.bus.dead()
        return f"event subscriber thread(s) died: {', '.join(dead)}" if dead else None


def open_context(
    site: SiteConfig, data_dir: Path, listen: list[str], partition: str | None = None
) -> tuple[HubContext, RefusedTraffic]:
    """The shared parts of a hub (nothing opened yet: the router binds at start), and the
    counter of what its router refuses.

    Raises:
        TypeError: `site` was loaded with the edges' schema (`fleetdaq.contract.config.load`),
            which leaves the hub's own sections unchecked; the hub needs
            `fleetdaq.hub.config.load`.
    """
    if not isinstance(site, SiteConfig):
        raise TypeError(
            "a hub needs its site file loaded with the hub's schema (fleetdaq.hub.config.load),"
            f" not {type(site).__module__}.{type(site).__name__}"
        )
    bus = EventBus(node=event_node(partition))
    model = ReadModel(site.site)
    refused = (
        RefusedTraffic(bus, model)
        if partition is None
        else RefusedTraffic(bus, model, f"partition hub {partition}")
    )
    router = Router(
        listen,
        site,
        connect=site.mesh_connect(partition),
        partition=partition,
        refused=refused,
    )
    ctx = HubContext(
        site, SiteKeys(site.site), router, bus, model, HubPaths.of(site, data_dir), partition
    )
    return ctx, refused


@dataclass(frozen=True, slots=True)
class HubShape:
    """Which parts a hub runs: where the main hub and a partition hub differ. Every hub runs
    the router, the bus, events.log, the recorder (and its snapshot buffer if the site keeps
    one), the node watch of its nodes, its own health and certificates, recorder requests and
    the status request."""

    whole_fleet: bool
    """The fleet's time view and the heartbeat every edge's dead-man hears (nodes wing)."""
    alarms: bool
    """The supervisor, alarm requests and the e-mail notifier (supervision wing)."""
    control: bool
    """Commands, rules and the hub's interlocks (control wing): outputs are the main hub's."""
    viewers: bool
    """Live plots, Foxglove and the dashboard (live wing)."""
    partitions: bool
    """On a partitioned site, the view of the partition hubs: their reports, recorder requests
    passed on, snapshot triggers, their streams while watched (partitions wing)."""
    own_report: bool
    """This hub's report to the main hub and the snapshot triggers it takes: a partition hub."""


MAIN_HUB = HubShape(
    whole_fleet=True, alarms=True, control=True, viewers=True, partitions=True, own_report=False
)
PARTITION_HUB = HubShape(
    whole_fleet=False, alarms=False, control=False, viewers=False, partitions=False, own_report=True
)


class RecordActions:
    """A rule's ``record:`` action on the main hub: start, stop and split reach every partition
    hub too (passed on, not waited for); a snapshot reaches them by its trigger."""

    def __init__(
        self,
        recorder: Recorder,
        snapshots: SnapshotBuffer | None,
        partitions: PartitionRecorders | None,
    ) -> None:
        self.recorder = recorder
        self.snapshots = snapshots
        self.partitions = partitions

    def __call__(self, action: str, who: str) -> str:
        parts = self.partitions
        if parts is not None and action in FORWARDED and action != "snapshot":  # its trigger
            parts.pass_on({"action": action, "user": who, "host": "hub", "note": ""})
        if action == "split":
            return self.recorder.split(who)
        if action == "stop":
            return self.recorder.stop_recording(who)
        if action == "snapshot":
            if self.snapshots is None:
                return "snapshot: the snapshot buffer is switched off"
            _, what = self.snapshots.snapshot(who)
            return f"snapshot: {what}"
        return self.recorder.start_recording(who)


@dataclass(frozen=True, slots=True)
class ComposedHub:
    """Every service of one hub, by wing, and the order they start in."""

    ctx: HubContext
    shape: HubShape
    claim: DataFolderClaim
    intake: NodeIntake
    event_log: EventLog
    recording: RecordingWing
    nodes: NodesWing
    supervision: SupervisionWing
    live: LiveWing
    recorder_requests: RecorderRequests
    control: ControlWing | None
    """The main hub's only."""
    partitions: Partitions | None
    """The main hub's of a partitioned site."""
    partition_live: PartitionLive | None
    own: OwnPartition | None
    """A partition hub's only."""
    dashboard: WebService | None
    services: list[Service]


def compose(
    ctx: HubContext,
    view: Callable[[], HubView],
    lock: DataFolderLock,
    lock_owned: bool = True,
    keep_plots: bool = False,
) -> ComposedHub:
    """Build and wire every service of the hub `ctx` describes (the main hub's, or a partition
    hub's when `ctx.partition` is set). `view`: the hub's read model with its runtime's parts
    (failures, bus and snapshot counters). `lock_owned`: False when the caller took the data
    folder's lock itself. `keep_plots`: keep the live plots without the dashboard."""
    shape = MAIN_HUB if ctx.partition is None else PARTITION_HUB

    def log_sync() -> bool:  # made before the event log, called only once it runs
        return event_log.sync()

    intake = nodes.intake(ctx, log_sync)
    event_log = supervision.event_log(ctx, intake.events)
    fleet = partitions.fleet(ctx) if shape.partitions else None
    rec = recording.build(
        ctx,
        intake.refused,
        intake.events,
        on_trigger=fleet.triggers.send if fleet is not None and fleet.triggers else None,
    )
    node_wing = nodes.build(ctx, intake, rec.recorder, shape.whole_fleet)
    own = partitions.own(ctx, rec.snapshots) if shape.own_report else None
    live_wing = live.build(
        ctx,
        rec.feed,
        view,
        shape.viewers,
        keep_plots,
        status_key=own.status_key if own is not None else None,
    )
    remote = partitions.live(ctx, live_wing.plots, live_wing.foxglove) if shape.partitions else None
    # Only the streams the alarms, rules and interlocks watch: `PartitionLive.supervised`.
    watched = [remote.supervised] if remote is not None and remote.watched else []
    sup = supervision.build(ctx, rec.recorder, rec.feed, view, shape.alarms, also_from=watched)
    others = fleet.recorders if fleet is not None else None
    ctl = (
        control.build(
            ctx,
            rec.recorder,
            rec.feed,
            view,
            RecordActions(rec.recorder, rec.snapshots, others),
            also_from=watched,
        )
        if shape.control
        else None
    )
    requests = recording.requests(
        ctx, rec, view, key=own.recorder_key if own is not None else None, others=others
    )
    dashboard = None
    if shape.viewers and sup.alarms is not None and ctl is not None:
        dashboard = live.dashboard(
            ctx, live_wing, view, sup.alarms.requests, ctl.commands, requests
        )
    places = [Place(ctx.paths.events_log, "events.log")]
    if shape.alarms:
        if ctx.site.hub.notify.smtp is not None:
            places.append(Place(ctx.paths.outbox, "the e-mail outbox", folder=True))
        places.append(Place(ctx.paths.alarm_journal, "the alarm journal"))
    claim = DataFolderClaim(lock, places, owned=lock_owned)
    hub = ComposedHub(
        ctx, shape, claim, intake, event_log, rec, node_wing, sup, live_wing, requests, ctl, fleet,
        remote, own, dashboard, services=[],
    )  # fmt: skip
    hub.services.extend(_start_order(hub))
    return hub


def _some(*services: Service | None) -> list[Service]:
    return [s for s in services if s is not None]


def _start_order(h: ComposedHub) -> list[Service]:
    """The order the hub's services start in (they stop in reverse); hub/runtime.py's docstring
    says why. Add a new service to the list of the hub that runs it."""
    rec, sup, live_wing = h.recording, h.supervision, h.live
    if h.shape is PARTITION_HUB:
        assert h.own is not None
        return [
            h.claim,  # before any port or file: one hub per data folder
            h.ctx.router,
            BusService(h.ctx.bus),
            h.event_log,
            rec.recorder,
            *_some(rec.snapshots, h.own.snapshot_requests),
            h.nodes.watch,
            sup.hub_health,
            h.own.report,  # before the certificates: their warning goes to the main hub
            *_some(sup.certificates),
            h.recorder_requests,
            live_wing.status,
        ]
    assert sup.alarms is not None
    assert h.control is not None
    assert h.nodes.fleet is not None
    assert h.nodes.heartbeat is not None
    fleet = h.partitions
    return [
        h.claim,  # before any port or file
        h.ctx.router,
        BusService(h.ctx.bus),
        h.event_log,
        sup.alarms.notifier,  # before the supervisor: its last transitions still mailed
        rec.recorder,
        h.nodes.watch,
        *_some(fleet.watch if fleet is not None else None),
        h.nodes.fleet,
        sup.hub_health,
        *_some(sup.certificates, rec.snapshots),
        *_some(fleet.triggers if fleet is not None else None),
        *_some(live_wing.plots, h.partition_live),
        sup.alarms.supervisor,
        sup.alarms.requests,
        h.control.commands,
        h.control.rules,
        h.recorder_requests,
        *live_wing.foxglove,
        h.nodes.heartbeat,
        live_wing.status,
        *_some(h.dashboard),
    ]
