"""Partitioned hubs: several hubs, each recording a slice of the nodes, their routers meshed.

The site file's ``hub.partitions`` names the extra hubs (`fleetdaq.hub.config.hub.PartitionConfig`);
every node belongs to exactly one hub (`SiteConfig.partition_of`) and connects to that hub's
router. A hub subscribes to the data of its own nodes only and acks only them, so each stream
is acked by exactly one hub and no batch crosses the mesh. The scale-out is Zenoh's own: the
routers link to each other (`SiteConfig.mesh_connect`) and route each key to whoever
subscribes; nothing here relays data.

What crosses the mesh is small:

- every node's health, events and liveliness token, which the main hub watches for the whole
  fleet (its node watch subscribes with wildcards);
- the main hub's heartbeat, which every edge's dead-man hears (outputs are the main hub's:
  rules and commands run there, and a command to a partition's node travels over the mesh);
- each partition hub's report, about once a second on ``hub/partition/<name>/report``: its
  streams' accounting and its recorder's state, as JSON (like ``hub/status``), its own
  machine's health on ``hub/partition/<name>/health`` (a `NodeHealth` of node
  ``hub/<name>``, as a node's), and its own events on ``hub/partition/<name>/events``; its
  liveliness token ``hub/partition/<name>/alive`` tells the main hub that it is there
  (`fleetdaq.hub.partitions.watch.PartitionWatch` reads them all).

A partition hub runs the router, the event bus and events.log, the recorder, the node watch of
its slice, its own health, the report, a status request on ``hub/partition/<name>/status`` and
recorder requests on ``hub/partition/<name>/recorder`` (the main hub passes its start, stop and
split on: `fleetdaq.hub.partitions.recorders`). Supervision (alarms, notifications), rules,
commands, snapshots and the dashboard run on the main hub only (`PartitionWatch` puts the
partitions' streams into its read model, so the stream alarms, the dashboard and ``hub/status``
cover the whole fleet)."""

from __future__ import annotations

import dataclasses
import json
import logging
import time
from pathlib import Path
from types import TracebackType
from typing import Any

from fleetdaq.contract.cdr import encode
from fleetdaq.contract.keys import SiteKeys
from fleetdaq.contract.messages import Event
from fleetdaq.hub.bus import EventBus
from fleetdaq.hub.config.site import SiteConfig
from fleetdaq.hub.live.status import StatusService
from fleetdaq.hub.nodes.refused import RefusedKeys
from fleetdaq.hub.nodes.watch import NodeWatch
from fleetdaq.hub.partitions.recorders import recorder_key
from fleetdaq.hub.partitions.snapshots import PartitionSnapshots
from fleetdaq.hub.periodic import Periodic
from fleetdaq.hub.read_model import (
    DiskView,
    HubView,
    ReadModel,
    to_jsonable,
)
from fleetdaq.hub.recording.data_lock import DataFolderClaim, DataFolderLock, Place
from fleetdaq.hub.recording.recorder import Recorder
from fleetdaq.hub.recording.requests import RecorderRequests
from fleetdaq.hub.recording.snapshots import SnapshotBuffer
from fleetdaq.hub.routing.refused_traffic import RefusedTraffic
from fleetdaq.hub.routing.router import Router
from fleetdaq.hub.services import ServiceStack
from fleetdaq.hub.supervision.certificates import CertificateWatch
from fleetdaq.hub.supervision.event_log import EventLog
from fleetdaq.hub.supervision.hub_health import HubHealth
from fleetdaq.runtime.paths import default_data_dir
from fleetdaq.runtime.systemd import Systemd

log = logging.getLogger("fleetdaq.hub")

REPORT_PERIOD_S = 1.0


def partition_key(keys: SiteKeys, name: str, what: str) -> str:
    """``fleetdaq/<site>/hub/partition/<name>/<what>`` (report, events, alive, status)."""
    return keys.hub(f"partition/{name}/{what}")


def partition_event_node(name: str) -> str:
    """The `node` of a partition hub's own events (the main hub's are ``hub``)."""
    return f"hub/{name}"


def partition_data_dir(site: SiteConfig, name: str, override: Path | None = None) -> Path:
    """Where a partition hub records: `--data`, else its `data_dir`, else a folder named after
    it in the main hub's recording root (two hubs never share session folders)."""
    if override is not None:
        return override
    own = site.hub.partitions[name].data_dir
    if own:
        return Path(own)
    main = site.hub.data_dir
    return (Path(main) if main else default_data_dir()) / name


# --- on a partition hub ------------------------------------------------------------------------


class PartitionReport(Periodic):
    """A partition hub's presence on the mesh: its liveliness token, its report about once a
    second (the first at start) and its own events, for the main hub's `PartitionWatch`."""

    name = "partition-report"

    def __init__(
        self,
        router: Router,
        keys: SiteKeys,
        partition: str,
        model: ReadModel,
        bus: EventBus,
        period_s: float = REPORT_PERIOD_S,
    ) -> None:
        super().__init__("partition-report", period_s)
        self.router = router
        self.partition = partition
        self.model = model
        self.report_key = partition_key(keys, partition, "report")
        self.events_key = partition_key(keys, partition, "events")
        self.health_key = partition_key(keys, partition, "health")
        self.alive_key = partition_key(keys, partition, "alive")
        self.own = partition_event_node(partition)
        self.reports = 0
        self._token: Any = None
        self._pubs: dict[str, Any] = {}
        self._bus_sub = bus.subscribe(self.name, self._on_event, maxsize=10_000)

    def start(self) -> None:
        session = self.router.session
        self._pubs = {
            "report": session.declare_publisher(self.report_key),
            "events": session.declare_publisher(self.events_key),
            "health": session.declare_publisher(self.health_key),
        }
        self._token = session.liveliness().declare_token(self.alive_key)
        self.start_ticking(at_once=True)

    def report(self, view: HubView | None = None) -> bytes:
        view = view or self.model.snapshot(time.time_ns())
        disk = view.hub_health.host.disk("data") if view.hub_health is not None else None
        return json.dumps(
            {
                "partition": self.partition,
                "time_ns": view.time_ns,
                "streams": to_jsonable(view.streams),
                "recorder": to_jsonable(view.recorder),
                "data_disk": to_jsonable(
                    DiskView(disk.free_bytes, disk.total_bytes) if disk else DiskView()
                ),
            },
            separators=(",", ":"),
        ).encode()

    def tick(self) -> None:
        view = self.model.snapshot(time.time_ns())
        self._pubs["report"].put(self.report(view))
        if view.hub_health is not None:  # its machine, as a node's health (CDR)
            self._pubs["health"].put(encode(view.hub_health))
        self.reports += 1

    def _on_event(self, e: Event) -> None:
        # Only this hub's own events: its nodes' events reach the main hub directly.
        pub = self._pubs.get("events")
        if e.node == self.own and pub is not None:
            pub.put(encode(e))

    def stop(self) -> None:
        self._bus_sub.flush()
        super().stop()
        if self._token is not None:
            self._token.undeclare()
            self._token = None
        pubs, self._pubs = self._pubs, {}
        for pub in pubs.values():
            pub.undeclare()


class PartitionRuntime:
    """A partition hub (`fleetdaq hub --partition NAME`): a context manager, like `HubRuntime`,
    with the services a partition hub runs (see the module's docstring), composed here."""

    def __init__(
        self,
        site: SiteConfig,
        partition: str,
        data_dir: Path | None = None,
        listen: list[str] | None = None,
    ) -> None:
        if partition not in site.hub.partitions:
            raise KeyError(partition)
        self.site = site
        self.partition = partition
        self.listen = listen or list(site.hub.partitions[partition].listen)
        self.data_dir = partition_data_dir(site, partition, data_dir)
        self.lock = DataFolderLock(self.data_dir, f"fleetdaq hub --partition {partition}")
        self.keys = SiteKeys(site.site)
        self.model = ReadModel(site.site)
        self.bus = EventBus(node=partition_event_node(partition))
        self.refused = RefusedKeys(self.bus, self.model)
        self.refused_traffic = RefusedTraffic(self.bus, self.model, f"partition hub {partition}")
        self.router = Router(
            self.listen,
            site,
            connect=site.mesh_connect(partition),
            partition=partition,
            refused=self.refused_traffic,
        )
        self.event_log = EventLog(self.data_dir / "events.log", self.bus, self.model)
        self.recorder = Recorder(
            self.router,
            site,
            self.data_dir,
            self.bus,
            self.model,
            self.refused,
            partition=partition,
        )
        self.event_log.deliver(self.recorder.event_delivery)
        self.nodes = NodeWatch(
            self.router,
            site,
            self.bus,
            self.model,
            self.recorder,
            self.refused,
            partition=partition,
        )
        # The minute before an event, of this hub's slice: triggered with the main hub's.
        self.snapshots = SnapshotBuffer.of_recorder(
            site,
            self.data_dir,
            self.bus,
            self.model,
            self.recorder,
            site.hub.partitions[partition].snapshot,
        )
        self.snapshot_requests = (
            PartitionSnapshots(self.router, self.keys, self.snapshots, self.bus)
            if self.snapshots is not None
            else None
        )
        # Start, stop and split, from the main hub (which passes its own on) or for this hub alone.
        self.recorder_requests = RecorderRequests(
            self.router,
            self.keys,
            self.recorder,
            self.snapshot,
            self.snapshots.snapshot if self.snapshots is not None else None,
            site.security,
            key=recorder_key(self.keys, partition),
            snapshot_setting=(
                f"hub.partitions.{partition}.snapshot.enabled"
                if site.hub.partitions[partition].snapshot is not None
                else "hub.snapshot.enabled"
            ),
        )
        certificates = (
            CertificateWatch(site, self.model, self.bus, partition) if site.security.tls else None
        )
        self.hub_health = HubHealth(
            self.data_dir, self.model, self.recorder, node=partition_event_node(partition),
            certificates=certificates,
        )  # fmt: skip
        self.report = PartitionReport(self.router, self.keys, partition, self.model, self.bus)
        self.status = StatusService(
            self.router,
            self.keys,
            self.snapshot,
            site.security,
            key=partition_key(self.keys, partition, "status"),
        )
        self.services = ServiceStack(
            [
                # Before any port or file: one hub per data folder.
                DataFolderClaim(self.lock, [Place(self.event_log.path, "events.log")]),
                self.router,
                _BusService(self.bus),
                self.event_log,
                self.recorder,
                *([self.snapshots] if self.snapshots is not None else []),
                *([self.snapshot_requests] if self.snapshot_requests is not None else []),
                self.nodes,
                self.hub_health,
                self.report,  # before the certificates: their warning goes to the main hub
                *([certificates] if certificates is not None else []),
                self.recorder_requests,
                self.status,
            ]
        )
        self.started = False
        self.systemd = Systemd()

    def __enter__(self) -> PartitionRuntime:
        self.start()
        return self

    def __exit__(
        self, t: type[BaseException] | None, e: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    def start(self) -> None:
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
            f"partition hub {self.partition} started: site {self.site.site}, listening on "
            f"{', '.join(self.listen)}, meshed with {', '.join(self.router.connect)}, "
            f"recording {', '.join(self.recorder.nodes)} into session {session.name}",
            session=session.name,
        )
        log.info(
            "partition hub %r of site %r listening on %s, recording %s into %s",
            self.partition,
            self.site.site,
            self.listen,
            self.recorder.nodes,
            session.dir,
        )

    def status_line(self) -> str:
        view = self.snapshot()
        r = view.recorder
        alive = sum(n.alive for n in view.nodes)
        return (
            f"partition {self.partition}: {r.state} {r.session or '-'}, "
            f"{r.bytes_written / 1e9:.2f} GB written; {alive}/{len(view.nodes)} nodes alive"
        )

    def close(self) -> None:
        if self.started:
            self.systemd.stopping("stopping: closing files")
        self.services.stop()
        self.refused.publish()

    def failures(self) -> list[tuple[str, str]]:
        return self.services.failures()

    def snapshot(self) -> HubView:
        view = self.model.snapshot(time.time_ns())
        failures = tuple(self.failures()) if self.started else ()
        snapshots = self.snapshots.counters() if self.snapshots is not None else {}
        return dataclasses.replace(view, failures=failures, snapshots=snapshots)

    def summary(self) -> dict[str, Any]:
        out = self.recorder.summary()
        out["partition"] = self.partition
        out["events"] = dict(self.event_log.counts)
        out["failures"] = [f"{name}: {why}" for name, why in self.failures()]
        return out


class _BusService:
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
