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

A partition hub runs the router, the event bus and events.log, the recorder, its snapshot
buffer (triggered with the main hub's: `fleetdaq.hub.partitions.snapshots`), the node watch of
its slice, its own health, the report (`PartitionReport`, here), a status request on
``hub/partition/<name>/status`` and recorder requests on ``hub/partition/<name>/recorder`` (the
main hub passes its start, stop and split on: `fleetdaq.hub.partitions.recorders`).
Supervision (alarms, notifications), rules, commands and the dashboard run on the main hub only
(`PartitionWatch` puts the partitions' streams into its read model, so the stream alarms, the
dashboard and ``hub/status`` cover the whole fleet). Both kinds of hub are composed by
`fleetdaq.hub.composition` and run by `fleetdaq.hub.runtime` (`PartitionRuntime`)."""

from __future__ import annotations

import json
import logging
import time
from pathlib import Path
from typing import Any

from fleetdaq.contract.cdr import encode
from fleetdaq.contract.keys import SiteKeys
from fleetdaq.contract.messages import Event
from fleetdaq.hub.bus import EventBus
from fleetdaq.hub.config.site import SiteConfig
from fleetdaq.hub.context import event_node
from fleetdaq.hub.periodic import Periodic
from fleetdaq.hub.read_model import (
    DiskView,
    HubView,
    ReadModel,
    to_jsonable,
)
from fleetdaq.hub.routing.router import Router
from fleetdaq.runtime.paths import default_data_dir

log = logging.getLogger("fleetdaq.hub")

REPORT_PERIOD_S = 1.0


def partition_key(keys: SiteKeys, name: str, what: str) -> str:
    """``fleetdaq/<site>/hub/partition/<name>/<what>`` (report, events, alive, status)."""
    return keys.hub(f"partition/{name}/{what}")


def partition_event_node(name: str) -> str:
    """The `node` of a partition hub's own events (the main hub's are ``hub``)."""
    return event_node(name)


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
