"""A partition's streams live on the main hub, while somebody looks at them, and always for
the ones the main hub's alarms, rules and interlocks watch.

A partition hub records its own nodes; their batches never cross the mesh to the main hub
(`fleetdaq.hub.partitions.runtime`), so the main hub's dashboard would list those streams without
ever being able to draw them (nor Foxglove show them). This service subscribes to a partition node's
stream across the mesh only while a dashboard viewer plots it (`LivePlots.demand`) or a Foxglove
client subscribes to it (`FoxgloveLive.on_demand`), and hands its batches to those two: never to the
recorder, the acks or the snapshot buffer, which stay the partition hub's. When the last viewer of
the stream leaves, the subscription goes and the batches stay on the partition's side of the mesh
again.

A partition stream whose channel a channel alarm, a rule or an interlock watches
(`SiteConfig.watched_partition_streams`) is followed for as long as the main hub runs, and its
batches go to the main hub's supervisor and rule engine too (`supervised`). What they see is
what crosses the mesh live: a batch the link between the hubs loses is not replayed to the
main hub (the partition hub records it all the same), and a replay arriving later is marked
late, which alarms and rules skip, as they do the main hub's own replays.

Everything that arrives is checked in full like the recorder's input (`BatchDecoder`): a
payload that is not a well-formed batch of that stream, or that names another stream than its
key, is counted (`malformed`), raised as an event (the first, then every 1000th) and dropped: never
shown and never fatal."""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Sequence
from typing import Any

from fleetdaq.contract.errors import WireError
from fleetdaq.contract.keys import SiteKeys
from fleetdaq.contract.wire import BatchDecoder, SampleFormat
from fleetdaq.hub.bus import EventBus
from fleetdaq.hub.config.site import SiteConfig
from fleetdaq.hub.live.foxglove.service import FoxgloveLive
from fleetdaq.hub.live.plots import LivePlots
from fleetdaq.hub.recording.batch_feed import BatchFeed, FedBatch
from fleetdaq.hub.routing.router import Router

log = logging.getLogger("fleetdaq.partition_live")


class _Remote:
    """One partition stream the main hub may plot."""

    def __init__(self, node: str, stream: str, sample_format: SampleFormat) -> None:
        self.node = node
        self.stream = stream
        self.key = f"{node}/{stream}"
        self.sample_format = sample_format
        self.decoder = BatchDecoder()
        self.lock = threading.Lock()  # Zenoh may call back from more than one thread
        self.last_sequence: int | None = None
        self.sub: Any = None


class PartitionLive:
    name = "partition-live"

    def __init__(
        self,
        router: Router,
        site: SiteConfig,
        bus: EventBus,
        plots: LivePlots | None = None,
        foxglove: Sequence[FoxgloveLive] = (),
    ) -> None:
        """`plots`, `foxglove`: the viewers it feeds while they show a partition's stream."""
        self.router = router
        self.bus = bus
        self.keys = SiteKeys(site.site)
        self.feed = BatchFeed()
        """Batches of the streams a viewer shows (the dashboard, Foxglove)."""
        self.supervised = BatchFeed()
        """Batches of the streams the alarms, rules and interlocks watch."""
        self.watched = site.watched_partition_streams()
        self._remotes: dict[str, _Remote] = {}
        for part in site.hub.partitions:
            for node in site.nodes_of(part):
                for stream, cfg in site.nodes[node].streams.items():
                    self._remotes[f"{node}/{stream}"] = _Remote(node, stream, cfg.sample_format)
        self._lock = threading.Lock()
        self._running = False
        self.batches = 0
        self.malformed = 0
        self._wants: dict[str, frozenset[str]] = {"supervision": self.watched}
        self._viewed: frozenset[str] = frozenset()
        self._withdraw: list[Callable[[str, str], None]] = []
        if plots is not None:
            self._serve_plots(plots)
        for fox in foxglove:
            self._serve_foxglove(fox)

    def _serve_plots(self, live_plots: LivePlots) -> None:
        """The dashboard's live plots: fed while they plot a partition's stream."""
        live_plots.add_feed(self.feed, "live-plots-partitions")
        live_plots.on_demand(lambda streams: self.want("dashboard", streams))
        self._withdraw.append(live_plots.forget_latest)

    def _serve_foxglove(self, foxglove: FoxgloveLive) -> None:
        """The Foxglove live view: fed while a client subscribes to a partition's stream."""
        foxglove.add_feed(self.feed, "foxglove-partitions")
        foxglove.on_demand(lambda streams: self.want("foxglove", streams))

    def start(self) -> None:
        with self._lock:
            self._running = True
            self._apply()

    def stop(self) -> None:
        with self._lock:
            self._running = False
            for r in self._remotes.values():
                self._drop(r)

    def failure(self) -> str | None:
        return None

    def want(self, viewer: str, streams: frozenset[str]) -> None:
        """`viewer` (``dashboard``, ``foxglove``) shows exactly `streams` now (any thread):
        follow the partition streams any viewer shows, and only those."""
        with self._lock:
            self._wants[viewer] = streams
            if self._running:
                self._apply()

    def _apply(self) -> None:
        wanted = frozenset().union(*self._wants.values())
        was_viewed = self._viewed
        self._viewed = frozenset().union(*(v for k, v in self._wants.items() if k != "supervision"))
        for key, r in self._remotes.items():
            if key in wanted and r.sub is None:
                r.last_sequence = None
                try:
                    r.sub = self.router.session.declare_subscriber(
                        self.keys.data(r.node, r.stream), self._handler(r)
                    )
                except Exception:  # the session is closing: the viewer sees no data, says so
                    log.exception("live view of %s: cannot subscribe to it", key)
                    continue
                why = "live view" if key in self._viewed else "alarms and rules"
                log.info("%s of %s: following it across the mesh", why, key)
            elif key not in wanted and r.sub is not None:
                self._drop(r)
                for withdraw in self._withdraw:
                    withdraw(r.node, r.stream)
                log.info("live view of %s: nobody looks at it, no longer followed", key)
            elif key in was_viewed - self._viewed:  # still followed for the alarms only
                for withdraw in self._withdraw:
                    withdraw(r.node, r.stream)

    @staticmethod
    def _drop(r: _Remote) -> None:
        if r.sub is not None:
            sub, r.sub = r.sub, None
            try:
                sub.undeclare()
            except Exception as err:  # the session closed first: nothing left to undeclare
                log.debug("undeclaring %s/%s: %s", r.node, r.stream, err)

    def _handler(self, r: _Remote) -> Any:
        def on_data(sample: Any) -> None:
            recv_ns = time.time_ns()
            payload = sample.payload.to_bytes()
            with r.lock:
                try:
                    h = r.decoder.read_header(payload, r.sample_format)
                    if (h.node, h.stream) != (r.node, r.stream):
                        raise WireError(f"payload says {h.node}/{h.stream}")
                except (WireError, ValueError, TypeError) as err:  # whatever the bytes were
                    self.malformed += 1
                    self.bus.emit_counted(
                        self.malformed,
                        logging.WARNING,
                        "partition-live",
                        "malformed",
                        f"live view of {r.node}/{r.stream}: dropped a payload that is not "
                        f"a valid batch of this stream ({err})",
                        node=r.node,
                        stream=r.stream,
                    )
                    return
                # A replay (the partition's edge catching up) is older than what was drawn.
                late = r.last_sequence is not None and h.sequence <= r.last_sequence
                if not late:
                    r.last_sequence = h.sequence
            self.batches += 1
            b = FedBatch(r.node, r.stream, h, payload, recv_ns, late)
            if r.key in self._viewed:
                self.feed.publish(b)
            if r.key in self.watched:
                self.supervised.publish(b)

        return on_data
