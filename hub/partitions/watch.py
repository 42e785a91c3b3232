"""The main hub's view of the partition hubs (`PartitionWatch`): whether each is there, what
its report says (its streams' accounting and its recorder), its own machine's health, and its
events. All of it crosses the LAN (without TLS anyone there may put on these keys), so each is
checked in full where it arrives and refused whole, counted and raised as an event when
anything is wrong; the last good one stands."""

from __future__ import annotations

import dataclasses
import logging
import threading
import time
from typing import Any

import zenoh

from fleetdaq.contract.cdr import decode
from fleetdaq.contract.errors import WireError
from fleetdaq.contract.keys import SiteKeys
from fleetdaq.contract.messages import Event, NodeHealth
from fleetdaq.hub.bus import EventBus
from fleetdaq.hub.config.site import SiteConfig
from fleetdaq.hub.nodes.watch import MAX_PAYLOAD_BYTES
from fleetdaq.hub.partitions.runtime import partition_event_node, partition_key
from fleetdaq.hub.read_model import (
    PARTITION_HUBS,
    PARTITION_STREAMS,
    PARTITIONS,
    DiskView,
    NodeView,
    ReadModel,
    RecorderView,
    StreamView,
    from_jsonable,
    to_jsonable,
)
from fleetdaq.hub.requests import json_object
from fleetdaq.hub.routing.router import Router


class PartitionWatch:
    """The main hub's view of the partition hubs: whether each is there (its liveliness token),
    its streams' accounting (into the read model next to the main hub's own, marked with the
    hub that records them) and its recorder, and its events onto the main hub's bus."""

    name = "partition-watch"

    def __init__(self, router: Router, site: SiteConfig, bus: EventBus, model: ReadModel) -> None:
        self.router = router
        self.keys = SiteKeys(site.site)
        self.bus = bus
        self.model = model
        self.owned = {name: set(site.nodes_of(name)) for name in site.hub.partitions}
        """The nodes each partition records: the only streams its report may speak for."""
        self._lock = threading.Lock()
        self._streams: dict[str, tuple[StreamView, ...]] = {}
        self._state: dict[str, dict[str, Any]] = {
            name: {"alive": False, "report_received_ns": 0, "recorder": {}, "data_disk": {}}
            for name in self.owned
        }
        self._health: dict[str, tuple[NodeHealth, int]] = {}
        """Each partition hub's last good health, with when it came (this hub's clock)."""
        self.malformed = 0
        self._subs: list[Any] = []

    def start(self) -> None:
        session = self.router.session
        self._publish()
        any_part = partition_key(self.keys, "*", "")
        self._subs = [
            session.declare_subscriber(any_part + "report", self._on_report),
            session.declare_subscriber(any_part + "events", self._on_event),
            session.declare_subscriber(any_part + "health", self._on_health),
            session.liveliness().declare_subscriber(
                any_part + "alive", self._on_alive, history=True
            ),
        ]

    def stop(self) -> None:
        for sub in self._subs:
            sub.undeclare()
        self._subs = []

    def failure(self) -> str | None:
        return None

    def _partition_of(self, sample: Any, what: str) -> str | None:
        key = str(sample.key_expr)
        parts = key.split("/")
        name = parts[-2] if len(parts) >= 2 and parts[-1] == what else ""
        if name not in self.owned:
            self.malformed += 1
            return None
        return name

    def _on_alive(self, sample: Any) -> None:
        name = self._partition_of(sample, "alive")
        if name is None:
            return
        alive = sample.kind == zenoh.SampleKind.PUT
        with self._lock:
            changed = self._state[name]["alive"] != alive
            self._state[name]["alive"] = alive
        if not changed:
            return
        self._publish()
        self.bus.emit(
            logging.INFO if alive else logging.ERROR,
            "hub",
            "partition_up" if alive else "partition_gone",
            f"partition hub {name}: "
            + (
                "connected"
                if alive
                else "gone; its nodes spool until it returns ("
                + ", ".join(sorted(self.owned[name]))
                + ")"
            ),
            partition=name,
        )

    def _on_report(self, sample: Any) -> None:
        name = self._partition_of(sample, "report")
        if name is None:
            return
        payload = sample.payload.to_bytes()
        try:
            report = json_object(payload, MAX_PAYLOAD_BYTES)
            unknown = set(report) - {"partition", "time_ns", "streams", "recorder", "data_disk"}
            if unknown:
                raise ValueError(f"unknown field(s) {sorted(unknown)[:5]}")
            if not isinstance(report.get("streams"), list):
                raise ValueError("streams is not a list")
            # Checked field by field: /metrics, the dashboard and `fleetdaq status` use them.
            views = [from_jsonable(StreamView, s) for s in report["streams"]]
            streams = tuple(
                dataclasses.replace(s, hub=name) for s in views if s.node in self.owned[name]
            )
            recorder = to_jsonable(from_jsonable(RecorderView, report.get("recorder")))
            disk = to_jsonable(from_jsonable(DiskView, report.get("data_disk", {})))
        except ValueError as err:
            self._refused(name, "a report", str(err))
            return
        with self._lock:
            self._streams[name] = streams
            self._state[name]["report_received_ns"] = time.time_ns()
            self._state[name]["recorder"] = recorder
            self._state[name]["data_disk"] = disk
        self._publish()

    def _on_health(self, sample: Any) -> None:
        name = self._partition_of(sample, "health")
        if name is None:
            return
        payload = sample.payload.to_bytes()
        try:
            if len(payload) > MAX_PAYLOAD_BYTES:
                raise ValueError(f"{len(payload)} bytes")
            health = decode(payload, NodeHealth)
            if health.node != partition_event_node(name):
                raise ValueError(f"it says it is of {health.node[:100]!r}")
        except (WireError, ValueError) as err:
            self._refused(name, "its health", str(err))
            return
        with self._lock:
            self._health[name] = (health, time.time_ns())
        self._publish()

    def _refused(self, name: str, what: str, why: str) -> None:
        self.malformed += 1
        self.bus.emit_counted(
            self.malformed,
            logging.WARNING,
            "hub",
            "malformed",
            f"partition hub {name}: refused {what}, which is not valid ({why})",
            partition=name,
        )

    def _on_event(self, sample: Any) -> None:
        name = self._partition_of(sample, "events")
        if name is None:
            return
        payload = sample.payload.to_bytes()
        if len(payload) > MAX_PAYLOAD_BYTES:
            self.malformed += 1
            return
        try:
            event = decode(payload, Event)
        except WireError:
            self.malformed += 1
            return
        if event.node != partition_event_node(name):
            self.malformed += 1
            return
        self.bus.publish(event)

    def _publish(self) -> None:
        with self._lock:
            streams = tuple(s for name in sorted(self._streams) for s in self._streams[name])
            state = {name: dict(s) for name, s in self._state.items()}
            hubs = tuple(
                NodeView(
                    node=partition_event_node(name),
                    alive=bool(state[name]["alive"]),
                    health=self._health[name][0] if name in self._health else None,
                    health_received_ns=self._health[name][1] if name in self._health else 0,
                )
                for name in sorted(state)
            )
        self.model.put(PARTITION_STREAMS, streams)
        self.model.put(PARTITIONS, state)
        self.model.put(PARTITION_HUBS, hubs)
