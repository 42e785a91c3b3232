"""The running hub: its services, composed in this one place, started in order, stopped in reverse.

Adding a service is one line in `HubRuntime.__init__`'s list. Services share:

- the router (`fleetdaq.hub.routing.router`): the Zenoh session;
- the event bus (`fleetdaq.hub.bus`): every event, from the nodes and the hub, to every subscriber
on
  its own thread (the recorder, events.log, the fleet's time view, ...);
- the read model (`fleetdaq.hub.read_model`): snapshots anyone may read (`snapshot()`): the demo's
  table, the status request, the dashboard.

The order matters: the router first (everything talks through it), the bus and events.log next
(so every later service's events are kept), the recorder before the node watch (health goes
into the recording), the heartbeat and the status request next (edges and operators see a hub
only once it records), the dashboard last (its page shows a hub that runs whole, and it is
the first to stop). Stopping runs the other way, so the recorder drains what reached it after the
node watch has stopped listening."""

from __future__ import annotations

import dataclasses
import logging
import time
from pathlib import Path
from types import TracebackType
from typing import Any

from fleetdaq.contract.keys import SiteKeys
from fleetdaq.hub.bus import EventBus
from fleetdaq.hub.config.site import SiteConfig
from fleetdaq.hub.control.commands import CommandService
from fleetdaq.hub.control.rules import RuleEngine
from fleetdaq.hub.live.foxglove.service import FoxgloveLive
from fleetdaq.hub.live.plots import LivePlots
from fleetdaq.hub.live.status import StatusService
from fleetdaq.hub.live.web.parts import HubParts
from fleetdaq.hub.live.web.service import WebService
from fleetdaq.hub.nodes.fleet_time import FleetTimeService
from fleetdaq.hub.nodes.heartbeat import Heartbeat
from fleetdaq.hub.nodes.refused import RefusedKeys
from fleetdaq.hub.nodes.watch import NodeWatch
from fleetdaq.hub.partitions.live import PartitionLive
from fleetdaq.hub.partitions.recorders import FORWARDED, PartitionRecorders
from fleetdaq.hub.partitions.snapshots import SnapshotTriggers
from fleetdaq.hub.partitions.watch import PartitionWatch
from fleetdaq.hub.read_model import HubView, ReadModel
from fleetdaq.hub.recording.batch_feed import BatchFeed
from fleetdaq.hub.recording.data_lock import DataFolderClaim, DataFolderLock, Place
from fleetdaq.hub.recording.recorder import Recorder
from fleetdaq.hub.recording.requests import RecorderRequests
from fleetdaq.hub.recording.snapshots import SnapshotBuffer
from fleetdaq.hub.routing.refused_traffic import RefusedTraffic
from fleetdaq.hub.routing.router import Router
from fleetdaq.hub.services import ServiceStack
from fleetdaq.hub.supervision.alarms.requests import AlarmRequests
from fleetdaq.hub.supervision.alarms.supervisor import Supervisor
from fleetdaq.hub.supervision.certificates import CertificateWatch
from fleetdaq.hub.supervision.event_log import EventLog
from fleetdaq.hub.supervision.hub_health import HubHealth
from fleetdaq.hub.supervision.notify.service import EmailNotifier
from fleetdaq.runtime.paths import default_data_dir
from fleetdaq.runtime.systemd import Systemd

log = logging.getLogger("fleetdaq.hub")


class _BusService:
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


class HubRuntime:
    """A context manager: the hub's services running between enter and exit."""

    def __init__(
        self,
        site: SiteConfig,
        data_dir: Path | None = None,
        listen: list[str] | None = None,
        live_plots: bool = False,
        lock: DataFolderLock | None = None,
    ) -> None:
        """`live_plots`: keep the plots' buffers even without the dashboard (the demo's
        layer-wait table reads them); with the dashboard on they are always kept. `lock`: the
        data folder's, already taken by the caller (the demo); else the hub takes it at start."""
        self.site = site
        self.listen = listen or list(site.hub.listen)
        configured = site.hub.data_dir
        self.data_dir = data_dir or (Path(configured) if configured else default_data_dir())
        self.lock = lock or DataFolderLock(self.data_dir, "fleetdaq hub")
        self.keys = SiteKeys(site.site)
        self.model = ReadModel(site.site)
        self.bus = EventBus()
        self.refused = RefusedKeys(self.bus, self.model)

        self.feed = BatchFeed()
        self.refused_traffic = RefusedTraffic(self.bus, self.model)
        self.router = Router(
            self.listen, site, connect=site.mesh_connect(None), refused=self.refused_traffic
        )
        self.event_log = EventLog(self.data_dir / "events.log", self.bus, self.model)
        self.recorder = Recorder(
            self.router, site, self.data_dir, self.bus, self.model, self.refused, self.feed
        )
        self.event_log.deliver(self.recorder.event_delivery)
        self.nodes = NodeWatch(self.router, site, self.bus, self.model, self.recorder, self.refused)
        self.fleet = FleetTimeService(self.bus, self.model, self.nodes)
        self.certificates = (
            CertificateWatch(site, self.model, self.bus) if site.security.tls else None
        )
        self.hub_health = HubHealth(
            self.data_dir, self.model, self.recorder, certificates=self.certificates
        )
        notify = site.hub.notify
        outbox = Path(notify.outbox_dir) if notify.outbox_dir else self.data_dir / "outbox"
        self.notifier = EmailNotifier(notify, site.site, outbox, self.bus, self.model)
        journal = site.hub.alarm_journal
        self.supervisor_journal = Path(journal) if journal else self.data_dir / "alarms.journal"
        self.supervisor = Supervisor(
            site,
            self.bus,
            self.model,
            self.recorder,
            self.feed,
            self.supervisor_journal,
            notifier=self.notifier,
            snapshot=self.snapshot,
        )
        self.alarm_requests = AlarmRequests(self.router, self.keys, self.supervisor, site.security)
        self.commands = CommandService(
            self.router, site, self.bus, self.model, self.recorder, self.snapshot
        )
        self.rules = RuleEngine(
            self.router,
            site,
            self.bus,
            self.model,
            self.feed,
            self.commands,
            self.snapshot,
            self._record_action,
        )
        self.snapshots = SnapshotBuffer.of_recorder(
            site, self.data_dir, self.bus, self.model, self.recorder
        )
        # Filling the plots costs every batch of every stream (a quarter of the hub's CPU with
        # a hundred small edges): only when something shows them.
        self.live_plots = (
            LivePlots(site, self.feed, cache_dir=self.data_dir / "cache")
            if live_plots or site.hub.dashboard.enabled
            else None
        )
        self.recorder_requests = RecorderRequests(
            self.router,
            self.keys,
            self.recorder,
            self.snapshot,
            self._asked_snapshot if self.snapshots is not None else None,
            site.security,
            partitions=(
                PartitionRecorders(
                    self.router,
                    self.keys,
                    list(site.hub.partitions),
                    self.bus,
                    snapshots_off=frozenset(
                        name
                        for name, part in site.hub.partitions.items()
                        if not (part.snapshot or site.hub.snapshot).enabled
                    ),
                )
                if site.hub.partitions
                else None
            ),
        )
        self.heartbeat = Heartbeat(self.router, self.keys, self._session_name)
        self.status = StatusService(self.router, self.keys, self.snapshot, site.security)
        self.dashboard = (
            WebService(
                site,
                HubParts(
                    snapshot=self.snapshot,
                    alarm_requests=self.alarm_requests,
                    commands=self.commands,
                    recorder_requests=self.recorder_requests,
                    live_plots=self.live_plots,
                    bus=self.bus,
                ),
            )
            if site.hub.dashboard.enabled and self.live_plots is not None
            else None
        )
        self.foxglove = FoxgloveLive.if_enabled(site, self.feed, self.bus, self.snapshot)
        self.partitions = (
            PartitionWatch(self.router, site, self.bus, self.model) if site.hub.partitions else None
        )
        # Each partition hub keeps a snapshot buffer of its slice, triggered with this one's.
        self.snapshot_triggers = (
            SnapshotTriggers(self.router, self.keys, self.snapshots)
            if site.hub.partitions and self.snapshots is not None
            else None
        )
        # A partition's streams: fetched across the mesh only while somebody looks at them,
        # and always those whose channels the alarms, rules and interlocks here watch.
        watched = site.watched_partition_streams()
        self.partition_live = (
            PartitionLive(self.router, site, self.bus)
            if site.hub.partitions and (self.live_plots is not None or self.foxglove or watched)
            else None
        )
        if self.partition_live is not None:
            if self.live_plots is not None:
                self.partition_live.serve_plots(self.live_plots)
            for fox in self.foxglove:
                self.partition_live.serve_foxglove(fox)
            if watched:
                self.supervisor.also_from(self.partition_live.supervised)
                self.rules.also_from(self.partition_live.supervised)
        places = [Place(self.event_log.path, "events.log")]
        if notify.smtp is not None:
            places.append(Place(outbox, "the e-mail outbox", folder=True))
        places.append(Place(self.supervisor_journal, "the alarm journal"))
        self.services = ServiceStack(
            [
                DataFolderClaim(self.lock, places, owned=lock is None),  # before any port or file
                self.router,
                _BusService(self.bus),
                self.event_log,
                self.notifier,  # before the supervisor: its last transitions still mailed
                self.recorder,
                self.nodes,
                *([self.partitions] if self.partitions is not None else []),
                self.fleet,
                self.hub_health,
                *([self.certificates] if self.certificates is not None else []),
                *([self.snapshots] if self.snapshots is not None else []),
                *([self.snapshot_triggers] if self.snapshot_triggers is not None else []),
                *([self.live_plots] if self.live_plots is not None else []),
                *([self.partition_live] if self.partition_live is not None else []),
                self.supervisor,
                self.alarm_requests,
                self.commands,
                self.rules,
                self.recorder_requests,
                *self.foxglove,
                self.heartbeat,
                self.status,
                *([self.dashboard] if self.dashboard is not None else []),
            ]
        )
        self.started = False
        self.systemd = Systemd()
        """systemd's READY, STATUS and watchdog (the recorder's writer must keep moving)."""

    def _asked_snapshot(self, who: str, note: str) -> tuple[bool, str]:
        """`fleetdaq rec snapshot` and the dashboard: the partitions are asked by the recorder
        requests themselves (their files named in the reply), not sent the trigger."""
        assert self.snapshots is not None
        return self.snapshots.snapshot(who, note, tell=not self.site.hub.partitions)

    def _record_action(self, action: str, who: str) -> str:
        """A rule's `record:` action (start, stop and split reach every partition hub too)."""
        parts = self.recorder_requests.partitions
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

    def _session_name(self) -> str:
        s = self.recorder.session
        return s.name if s is not None else ""

    def __enter__(self) -> HubRuntime:
        self.start()
        return self

    def __exit__(
        self, t: type[BaseException] | None, e: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    def start(self) -> None:
        """Start every service; on failure (or Ctrl-C) part-way, stop what had started."""
        self.services.start()
        self.started = True
        self.systemd.beats.append(self.recorder.beat)
        self.systemd.status_of = self.status_line
        self.systemd.ready(self.status_line())
        session = self.recorder.session
        assert session is not None
        self.bus.emit(
            logging.INFO,
            "hub",
            "started",
            f"hub started: site {self.site.site}, listening on {', '.join(self.listen)}, "
            f"session {session.name}",
            session=session.name,
        )
        log.info(
            "hub for site %r listening on %s, recording into %s",
            self.site.site,
            self.listen,
            session.dir,
        )

    def status_line(self) -> str:
        """What `systemctl status` shows."""
        view = self.snapshot()
        r = view.recorder
        alive = sum(n.alive for n in view.nodes)
        active = sum(a.active for a in view.alarms)
        return (
            f"{r.state} {r.session or '-'}, {r.bytes_written / 1e9:.2f} GB written; "
            f"{alive}/{len(view.nodes)} nodes alive; {active} alarm(s) active"
        )

    def close(self) -> None:
        """Stop every service, newest first. Idempotent."""
        if self.started:
            self.systemd.stopping("stopping: closing files")
        self.services.stop()
        self.refused.publish()

    def failures(self) -> list[tuple[str, str]]:
        """Services whose worker died: the hub must say so and stop, not run on silently."""
        return self.services.failures()

    def snapshot(self) -> HubView:
        view = self.model.snapshot(time.time_ns())
        bus = tuple(
            {
                "name": s.name,
                "delivered": s.delivered,
                "dropped": s.dropped,
                "errors": s.errors,
                "queued": s.queued,
            }
            for s in self.bus.stats()
        )
        failures = tuple(self.failures()) if self.started else ()
        snapshots = self.snapshots.counters() if self.snapshots is not None else {}
        return dataclasses.replace(view, bus=bus, failures=failures, snapshots=snapshots)

    def summary(self) -> dict[str, Any]:
        """The final accounting (per stream, files, refused traffic, events by level)."""
        out = self.recorder.summary()
        out["events"] = dict(self.event_log.counts)
        out["alarms"] = dict(self.supervisor.totals)
        out["mails"] = dict(self.snapshot().notifier)
        out["bus"] = list(self.snapshot().bus)
        out["failures"] = [f"{name}: {why}" for name, why in self.failures()]
        return out
