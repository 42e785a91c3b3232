"""The node watch: which nodes are alive (liveliness tokens), their typed health, their events.

Everything here arrives from the network and is checked in full before anyone sees it: the key
must name a node of the site file (anything else is refused and counted), a health payload
must decode into `NodeHealth` and an event into `Event` (bounded lengths, no trailing bytes)
and name the node its key names. Health goes to the read model, to the listeners (the fleet's
time view) and into the recording (``/<node>/health``); events go onto the event bus, at most
`events_per_s` per node (a burst of `event_burst`): a flooding node cannot drown the others.
An event an edge spooled carries its sequence (`fleetdaq.contract.wire.encode_event_mark`): it goes
onto the bus in sequence order and once (`fleetdaq.hub.nodes.event_delivery`), and is acked once
written for good."""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable

import zenoh

from fleetdaq.contract.cdr import decode
from fleetdaq.contract.errors import WireError
from fleetdaq.contract.keys import Kind, SiteKeys
from fleetdaq.contract.messages import NODE_HEALTH_TYPE, Event, NodeHealth
from fleetdaq.contract.wire import decode_event_mark, plausible_time
from fleetdaq.hub.bus import EventBus
from fleetdaq.hub.config.site import SiteConfig
from fleetdaq.hub.nodes.event_delivery import EventDelivery, Verdict
from fleetdaq.hub.nodes.refused import RefusedKeys
from fleetdaq.hub.read_model import MALFORMED, NODES, NodeView, ReadModel
from fleetdaq.hub.recording.recorder import Recorder
from fleetdaq.hub.recording.session import health_topic
from fleetdaq.hub.routing.router import Router, undeclare

log = logging.getLogger("fleetdaq.hub")

MAX_PAYLOAD_BYTES = 1024 * 1024
"""Health and events are small; anything bigger is refused before it is decoded."""

HealthListener = Callable[[str, NodeHealth], None]
AliveListener = Callable[[str, bool], None]


class _Bucket:
    """A token bucket: `rate` per second, at most `burst` at once."""

    def __init__(self, rate: float, burst: float) -> None:
        self.rate, self.burst = rate, burst
        self.tokens = burst
        self.stamp = time.monotonic()
        self.dropped = 0
        self.reported = 0.0

    def take(self) -> bool:
        now = time.monotonic()
        self.tokens = min(self.burst, self.tokens + (now - self.stamp) * self.rate)
        self.stamp = now
        if self.tokens >= 1.0:
            self.tokens -= 1.0
            return True
        self.dropped += 1
        return False


class NodeWatch:
    name = "node-watch"

    def __init__(
        self,
        router: Router,
        site: SiteConfig,
        bus: EventBus,
        model: ReadModel,
        recorder: Recorder,
        refused: RefusedKeys,
        events: EventDelivery,
        events_per_s: float = 200.0,
        event_burst: float = 2000.0,
        partition: str | None = None,
        health_listeners: list[HealthListener] | None = None,
        alive_listeners: list[AliveListener] | None = None,
    ) -> None:
        """`partition`: a partition hub watches only its own nodes (each by name, so nothing of
        the others crosses the mesh); the main hub (None) watches the whole fleet. `events`: the
        order, dedup and acks of the nodes' spooled events (the recorder's too)."""
        self.router = router
        self.keys = SiteKeys(site.site)
        self.partition = partition
        self.known = frozenset(site.nodes if partition is None else site.nodes_of(partition))
        self.bus = bus
        self.model = model
        self.recorder = recorder
        self.refused = refused
        self.events = events
        self.health_listeners: list[HealthListener] = list(health_listeners or [])
        """Called with (node, health) for every valid health message, on a Zenoh thread:
        must not block."""
        self.alive_listeners: list[AliveListener] = list(alive_listeners or [])
        """Called with (node, alive) when a node's liveliness token appears or goes."""
        self._alive: dict[str, bool] = dict.fromkeys(sorted(self.known), False)
        self._health: dict[str, tuple[NodeHealth, int]] = {}
        self._malformed: dict[str, int] = {}
        self._buckets = {n: _Bucket(events_per_s, event_burst) for n in self.known}
        self._lock = threading.Lock()
        self._subs: list[zenoh.Subscriber[None]] = []

    def start(self) -> None:
        session = self.router.session
        self._publish()
        k = self.keys
        if self.partition is None:
            selectors = [(k.all_health, k.all_events, k.all_alive)]
        else:
            selectors = [(k.health(n), k.events(n), k.alive(n)) for n in sorted(self.known)]
        for health, events, alive in selectors:
            self._subs += [
                session.declare_subscriber(health, self._on_health),
                session.declare_subscriber(events, self._on_event),
                session.liveliness().declare_subscriber(alive, self._on_alive, history=True),
            ]

    def stop(self) -> None:
        for sub in self._subs:
            undeclare(sub)
        self._subs = []

    def failure(self) -> str | None:
        return None

    # --- what others read -----------------------------------------------------------------------

    def alive(self) -> set[str]:
        with self._lock:
            return {n for n, a in self._alive.items() if a}

    def health(self, node: str) -> NodeHealth | None:
        with self._lock:
            got = self._health.get(node)
        return got[0] if got is not None else None

    def accept_health(self, node: str, health: NodeHealth, payload: bytes, recv_ns: int) -> None:
        """A checked health message (from the network, or the hub's own): keep, tell, record."""
        with self._lock:
            self._health[node] = (health, recv_ns)
        self._publish()
        for listener in self.health_listeners:
            listener(node, health)
        publish = health.time_ns if plausible_time(health.time_ns, recv_ns) else recv_ns
        self.recorder.record(health_topic(node), payload, publish, recv_ns, NODE_HEALTH_TYPE)

    # --- from the network ------------------------------------------------------------------------

    def _node_of(self, sample: zenoh.Sample, kind: Kind, what: str) -> str | None:
        key_text = str(sample.key_expr)
        key = self.keys.parse(key_text)
        if key is None or key.kind is not kind or key.node not in self.known:
            self.refused.refuse(key_text, what)
            return None
        return key.node

    def _bad(self, node: str, what: str, err: str) -> None:
        with self._lock:
            n = self._malformed.get(node, 0) + 1
            self._malformed[node] = n
            malformed = tuple(sorted(self._malformed.items()))
        self.model.put(MALFORMED, malformed)
        self.bus.emit_counted(
            n,
            logging.WARNING,
            "hub",
            "malformed",
            f"{node}: refused a {what} payload that is not valid ({err})",
            node=node,
        )

    def _on_alive(self, sample: zenoh.Sample) -> None:
        node = self._node_of(sample, Kind.ALIVE, "a liveliness token")
        if node is None:
            return
        alive = sample.kind == zenoh.SampleKind.PUT
        with self._lock:
            changed = self._alive.get(node) != alive
            self._alive[node] = alive
        if not changed:
            return
        self._publish()
        for listener in self.alive_listeners:
            listener(node, alive)
        self.bus.emit(
            logging.INFO if alive else logging.WARNING,
            "hub",
            "node_alive" if alive else "node_gone",
            f"{node}: {'connected' if alive else 'gone (its liveliness token went away)'}",
            node=node,
        )

    def _on_health(self, sample: zenoh.Sample) -> None:
        node = self._node_of(sample, Kind.HEALTH, "health")
        if node is None:
            return
        recv_ns = time.time_ns()
        payload = sample.payload.to_bytes()
        if len(payload) > MAX_PAYLOAD_BYTES:
            self._bad(node, "health", f"{len(payload)} bytes")
            return
        try:
            health = decode(payload, NodeHealth)
        except WireError as err:
            self._bad(node, "health", str(err))
            return
        if health.node != node:
            self._bad(node, "health", f"it says it is from {health.node!r}")
            return
        self.accept_health(node, health, payload, recv_ns)

    def _on_event(self, sample: zenoh.Sample) -> None:
        node = self._node_of(sample, Kind.EVENTS, "an event")
        if node is None:
            return
        bucket = self._buckets[node]
        if not bucket.take():
            now = time.monotonic()
            if now - bucket.reported >= 10.0:
                bucket.reported = now
                self.bus.emit(
                    logging.ERROR,
                    "hub",
                    "event_flood",
                    f"{node}: more than {bucket.rate:g} events/s; {bucket.dropped} dropped so far",
                    node=node,
                    dropped=bucket.dropped,
                )
            return
        payload = sample.payload.to_bytes()
        if len(payload) > MAX_PAYLOAD_BYTES:
            self._bad(node, "event", f"{len(payload)} bytes")
            return
        try:
            event = decode(payload, Event)
        except WireError as err:
            self._bad(node, "event", str(err))
            return
        if event.node != node:
            self._bad(node, "event", f"it says it is from {event.node!r}")
            return
        att = sample.attachment
        if att is None:  # a peer without an event spool: best effort, as it sent it
            self.bus.publish(event)
            return
        mark = decode_event_mark(att.to_bytes())
        if mark is None:
            self._bad(node, "event", "its attachment is not a sequence, floor and epoch")
            return
        seq, floor, epoch = mark
        if floor > seq:
            self._bad(node, "event", f"floor {floor} above its own sequence {seq}")
            return
        offer = self.events.offer(node, seq, floor, epoch, event, self.bus.publish)
        if offer.lost:
            self.bus.emit(
                logging.ERROR,
                "hub",
                "events_lost",
                f"{node}: {offer.lost} event(s) before sequence {floor} never came: its event "
                "spool dropped them unacked",
                node=node,
                lost=offer.lost,
            )
        if offer.verdict is Verdict.DUPLICATE:
            bucket.tokens = min(bucket.burst, bucket.tokens + 1.0)  # a replay is not a flood

    def _publish(self) -> None:
        with self._lock:
            views = tuple(
                NodeView(
                    node=n,
                    alive=self._alive.get(n, False),
                    health=self._health[n][0] if n in self._health else None,
                    health_received_ns=self._health[n][1] if n in self._health else 0,
                )
                for n in sorted(self._alive)
            )
        self.model.put(NODES, views)
