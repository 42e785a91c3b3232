"""The Foxglove live view as a hub service: a Foxglove WebSocket server (foxglove-sdk) that
Foxglove and Lichtblick connect to ("Open connection" -> "Foxglove WebSocket" ->
``ws://HUB:8765``), with these channels (JSON, with a JSON Schema each):

- ``/<node>/<stream>`` for every stream of the site: decimated on the hub to at most 200
  messages a second, each channel's mean, min and max per interval
  (`fleetdaq.hub.live.foxglove.decimate`,
  `fleetdaq.hub.live.foxglove.messages.StreamMessages`); log time and ``header.stamp`` =
  acquisition time;
- ``/events``: every event; ``/log``: the same as ``foxglove.Log`` for the Log panel;
- ``/alarms``: every alarm transition; ``/alarms/current``: every alarm's state, once a second;
- ``/diagnostics``: ``diagnostic_msgs/msg/DiagnosticArray`` once a second
  (`fleetdaq.hub.live.foxglove.diagnostics`).

Nothing is computed for a channel nobody subscribes to (the SDK says whether a channel has a
subscriber): without a Foxglove client the service costs a queue hand-off per batch. Batches
come from the batch feed on this service's own thread and bounded queue; events from the event
bus on its own thread; the diagnostics and the server's clock (the "time" capability, so a
viewer's clock is the hub's, whatever its own) from a ticker thread. A slow viewer never holds
anything up: the SDK drops the oldest messages queued for it. Whatever a client sends is the
SDK's to check (it answers a bad message with a status message and goes on).
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, Final, cast

from fleetdaq.contract.messages import Event
from fleetdaq.contract.wire import batch_values, plausible_time
from fleetdaq.hub.bus import EventBus, worth_telling
from fleetdaq.hub.config.dashboard import split_listen, url_host
from fleetdaq.hub.config.site import SiteConfig
from fleetdaq.hub.errors import HubError
from fleetdaq.hub.live import server_tls
from fleetdaq.hub.live.foxglove import diagnostics
from fleetdaq.hub.live.foxglove.decimate import INTERVAL_NS, Decimator
from fleetdaq.hub.live.foxglove.front import SubprotocolFront
from fleetdaq.hub.live.foxglove.messages import (
    ALARM_TABLE_SCHEMA,
    ALARM_TRANSITION_SCHEMA,
    EVENT_SCHEMA,
    LOG_SCHEMA,
    StreamMessages,
    alarm_table,
    alarm_transition,
    dumps,
    event_message,
    log_message,
)
from fleetdaq.hub.read_model import HubView
from fleetdaq.hub.recording.batch_feed import BatchFeed, FedBatch
from fleetdaq.runtime.threads import NamedThread

if TYPE_CHECKING:  # imported when the service starts: only a hub that uses it needs the SDK
    from foxglove import Channel, Context
    from foxglove.websocket import ChannelView, Client, ServerListener, WebSocketServer

log = logging.getLogger("fleetdaq.foxglove")

TICK_S: Final = 0.05
"""The server's time goes to the clients 20 times a second (while anyone subscribes)."""
STATE_PERIOD_S: Final = 1.0
"""Diagnostics and the alarm table: once a second (the ticker's pace when nobody watches)."""
FEED_QUEUE_BYTES: Final = 32 << 20

FIXED_TOPICS: Final = {
    "/events": EVENT_SCHEMA,
    "/log": LOG_SCHEMA,
    "/alarms": ALARM_TRANSITION_SCHEMA,
    "/alarms/current": ALARM_TABLE_SCHEMA,
    "/diagnostics": diagnostics.SCHEMA,
}


@dataclass(slots=True)
class _Stream:
    names: tuple[str, ...]
    messages: StreamMessages
    decimator: Decimator
    channel: Channel | None = None


class FoxgloveLive:
    """The hub's Foxglove WebSocket server (a service: start, stop, failure)."""

    name = "foxglove-live"

    def __init__(
        self, site: SiteConfig, feed: BatchFeed, bus: EventBus, snapshot: Callable[[], HubView]
    ) -> None:
        self.site = site
        self.listen = site.hub.dashboard.foxglove.listen
        self.snapshot = snapshot
        self._configured = diagnostics.configured_streams(site)
        self._streams: dict[tuple[str, str], _Stream] = {}
        for node, cfg in site.nodes.items():
            for stream, s in cfg.streams.items():
                names = tuple(c.name for c in s.channels)
                units = tuple(c.unit for c in s.channels)
                self._streams[(node, stream)] = _Stream(
                    names,
                    StreamMessages(node, stream, names, units, INTERVAL_NS),
                    Decimator(len(names)),
                )
        self._channels: dict[str, Channel] = {}
        self._server: WebSocketServer | None = None
        self._front: SubprotocolFront | None = None
        self._context: Context | None = None
        self._subscriptions = 0
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._running = False
        self._ticker = NamedThread(target=self._tick, name="foxglove-tick", daemon=True)
        self.counts = {"messages": 0, "batches": 0, "implausible": 0, "mismatched": 0, "errors": 0}
        self._consumers = [feed.subscribe(self.name, self._on_batch, max_bytes=FEED_QUEUE_BYTES)]
        self._by_topic = {st.messages.topic: f"{n}/{s}" for (n, s), st in self._streams.items()}
        self._topic_subs: dict[str, int] = {}
        self._on_demand: Callable[[frozenset[str]], None] | None = None
        self._demanded: frozenset[str] = frozenset()
        bus.subscribe(self.name, self._on_event)

    @classmethod
    def if_enabled(
        cls, site: SiteConfig, feed: BatchFeed, bus: EventBus, snapshot: Callable[[], HubView]
    ) -> list[FoxgloveLive]:
        """The service when the site file enables it (``hub.dashboard.foxglove.enabled``)."""
        return [cls(site, feed, bus, snapshot)] if site.hub.dashboard.foxglove.enabled else []

    # --- lifecycle ----------------------------------------------------------------------------

    def start(self) -> None:
        try:
            import foxglove
            from foxglove.websocket import Capability
        except ImportError as err:
            raise HubError(
                "the Foxglove live view needs foxglove-sdk (pip install 'fleetdaq[hub]'); "
                "or set hub.dashboard.foxglove.enabled: false"
            ) from err
        _route_sdk_logs()
        tls = self.site.hub.dashboard.foxglove.tls
        pair = server_tls.load(tls, "hub.dashboard.foxglove.tls") if tls else None
        # Held for the service's life: the channels and the server are bound through it, and
        # the SDK lets go of them (nothing advertised) once the Python object is gone.
        self._context = context = foxglove.Context()
        # Every channel exists before the server: a client sees them all in its first advertise.
        for st in self._streams.values():
            st.channel = _channel(context, st.messages.topic, st.messages.schema)
        for topic, schema in FIXED_TOPICS.items():
            self._channels[topic] = _channel(context, topic, schema)
        host, port = split_listen(self.listen)
        # The front takes the configured address first (a taken port fails before anything
        # else starts); the SDK listens behind it, on loopback, in clear
        # (`fleetdaq.hub.live.foxglove.front`).
        self._front = front = SubprotocolFront(host, port, 0, pair.context if pair else None)
        try:
            front.bind()
        except OSError as err:
            self._close_channels()
            raise HubError(
                f"the Foxglove live view cannot listen on {self.listen}: "
                f"{err.strerror or err} (site file: hub.dashboard.foxglove.listen, "
                "or enabled: false)"
            ) from err
        try:
            self._server = foxglove.start_server(
                name=f"fleetdaq hub, site {self.site.site}",
                host="127.0.0.1",
                port=0,
                capabilities=[Capability.Time],
                server_listener=cast("ServerListener", _Listener(self)),
                context=context,
            )
            front.upstream_port = int(self._server.port)
            front.start()
        except (RuntimeError, OSError) as err:
            self._close_channels()
            front.stop()
            reason = str(err).removeprefix("FoxgloveError: ")
            raise HubError(
                f"the Foxglove live view cannot start its server: {reason} "
                "(site file: hub.dashboard.foxglove, or enabled: false)"
            ) from err
        self._running = True
        for c in self._consumers:
            c.start()
        self._ticker.start()
        log.info("Foxglove live view on %s", self.url)

    @property
    def url(self) -> str:
        """``ws://HOST:PORT`` (``wss://`` with `tls`) as bound (port 0 in the site file: the
        one the system gave)."""
        host, port = split_listen(self.listen)
        if self._front is not None:
            port = self._front.port
        scheme = "wss" if self.site.hub.dashboard.foxglove.tls else "ws"
        return f"{scheme}://{url_host(host)}:{port}"

    def stop(self) -> None:
        if self._front is not None:
            self.counts.update(self._front.counts)
        if self._running:
            log.info(
                "Foxglove live view stopping: %s",
                ", ".join(f"{k} {v}" for k, v in self.counts.items()),
            )
        self._running = False
        self._stop.set()
        if self._ticker.is_alive():
            self._ticker.join(10)
        for c in self._consumers:
            c.stop()
        if self._front is not None:
            self._front.stop()
            self._front = None
        if self._server is not None:
            self._server.stop()
            self._server = None
        self._close_channels()
        self._context = None

    def failure(self) -> str | None:
        if not self._running:
            return None
        if not self._ticker.is_alive():
            return "its ticker thread (diagnostics, time) died"
        if self._front is not None and not self._front.alive():
            return "its front (the listening port) stopped"
        if not all(c.alive for c in self._consumers):
            return "its batch-feed thread died"
        return None

    def _close_channels(self) -> None:
        for ch in [*(s.channel for s in self._streams.values()), *self._channels.values()]:
            if ch is not None:
                ch.close()
        for st in self._streams.values():
            st.channel = None
        self._channels = {}

    def add_feed(self, feed: BatchFeed, name: str) -> None:
        """Also take the batches of `feed` (before `start`): a partition's streams, fetched
        across the mesh while a client subscribes to them (`fleetdaq.hub.partitions.live`)."""
        self._consumers.append(feed.subscribe(name, self._on_batch, max_bytes=FEED_QUEUE_BYTES))

    def on_demand(self, callback: Callable[[frozenset[str]], None] | None) -> None:
        """Call `callback` with the ``node/stream`` names clients subscribe to whenever they
        change."""
        self._on_demand = callback

    def _subscribed(self, delta: int, topic: str = "") -> None:
        with self._lock:
            self._subscriptions = max(0, self._subscriptions + delta)
            if topic in self._by_topic:
                n = self._topic_subs.get(topic, 0) + delta
                if n > 0:
                    self._topic_subs[topic] = n
                else:
                    self._topic_subs.pop(topic, None)
            demanded = frozenset(self._by_topic[t] for t in self._topic_subs)
            changed, self._demanded = demanded != self._demanded, demanded
        callback = self._on_demand
        if changed and callback is not None:
            callback(demanded)

    # --- streams (the batch feed's thread) -----------------------------------------------------

    def _on_batch(self, b: FedBatch) -> None:
        st = self._streams.get((b.node, b.stream))
        if st is None or st.channel is None:
            return
        if not st.channel.has_sinks():
            st.decimator.reset()  # nobody watches: no work, nothing carried over
            return
        if b.late:
            return  # a replay fills a hole in the recording; live, that time has passed
        h = b.header
        if h.channel_names != st.names:
            self.counts["mismatched"] += 1
            return
        now = time.time_ns()
        last_ns = h.first_sample_time_ns + h.scan_count * h.sample_period_ns
        if not (plausible_time(h.first_sample_time_ns, now) and plausible_time(int(last_ns), now)):
            self.counts["implausible"] += 1  # an edge whose clock was never set, or a lie
            return
        rows = st.decimator.add(
            h.first_sample_time_ns, h.sample_period_ns, batch_values(h, b.payload)
        )
        out = st.messages.encode(rows)
        for t, msg in out:
            st.channel.log(msg, log_time=t)
        self.counts["batches"] += 1
        self.counts["messages"] += len(out)

    # --- events (the event bus's thread) -------------------------------------------------------

    def _on_event(self, e: Event) -> None:
        if not self._running:
            return
        now = time.time_ns()
        t = e.time_ns if plausible_time(e.time_ns, now) else now
        for topic, build in (("/events", event_message), ("/log", log_message)):
            ch = self._channels.get(topic)
            if ch is not None and ch.has_sinks():
                ch.log(dumps(build(e, t)), log_time=t)
        ch = self._channels.get("/alarms")
        alarm = e.source == "alarms" and e.tag.startswith("alarm_")
        if alarm and ch is not None and ch.has_sinks():
            name = e.get("alarm")
            view = next((a for a in self.snapshot().alarms if a.name == name), None)
            ch.log(dumps(alarm_transition(e, t, view)), log_time=t)

    # --- diagnostics, alarm table, time (the ticker's thread) ----------------------------------

    def _tick(self) -> None:
        next_state = time.monotonic() + STATE_PERIOD_S
        while not self._stop.wait(TICK_S if self._subscriptions > 0 else STATE_PERIOD_S):
            try:
                server = self._server
                if server is not None and self._subscriptions > 0:
                    server.broadcast_time(time.time_ns())
                now = time.monotonic()
                if now >= next_state:
                    next_state = now + STATE_PERIOD_S
                    self._publish_state()
            except Exception:
                self.counts["errors"] += 1
                if worth_telling(self.counts["errors"], first=10):
                    log.exception("Foxglove live view: tick failed")

    def _publish_state(self) -> None:
        diag = self._channels.get("/diagnostics")
        table = self._channels.get("/alarms/current")
        diag = diag if diag is not None and diag.has_sinks() else None
        table = table if table is not None and table.has_sinks() else None
        if diag is None and table is None:
            return
        view = self.snapshot()
        now = time.time_ns()
        if diag is not None:
            diag.log(dumps(diagnostics.diagnostic_array(view, self._configured, now)), log_time=now)
        if table is not None:
            in_alarm = sum(a.state in diagnostics.IN_ALARM for a in view.alarms)
            table.log(dumps(alarm_table(view.alarms, now, in_alarm)), log_time=now)


class _Listener:
    """The SDK calls these (on its own threads) as clients subscribe and go."""

    def __init__(self, live: FoxgloveLive) -> None:
        self.live = live

    def on_subscribe(self, client: Client, channel: ChannelView) -> None:
        self.live._subscribed(+1, str(channel.topic))
        log.debug("Foxglove client %s subscribed to %s", client.id, channel.topic)

    def on_unsubscribe(self, client: Client, channel: ChannelView) -> None:
        self.live._subscribed(-1, str(channel.topic))
        log.debug("Foxglove client %s unsubscribed from %s", client.id, channel.topic)


def _channel(context: Context, topic: str, schema: Mapping[str, object]) -> Channel:
    from foxglove import Channel, Schema

    return Channel(
        topic,
        schema=Schema(name=str(schema["title"]), encoding="jsonschema", data=dumps(schema)),
        message_encoding="json",
        context=context,
    )


# --- the SDK's own log -------------------------------------------------------------------------

_routed: list[bool] = []


class _SdkLog(logging.Handler):
    """The SDK's log records (it logs every bad message a client sends) into ours, at most
    `burst` a minute, with a count of what was left out: a client sending garbage in a loop
    must not fill the hub's log."""

    def __init__(self, burst: int = 20, window_s: float = 60.0) -> None:
        super().__init__()
        self.burst = burst
        self.window_s = window_s
        self._window_start = 0.0
        self._in_window = 0
        self._suppressed = 0

    def emit(self, record: logging.LogRecord) -> None:
        now = time.monotonic()
        if now - self._window_start > self.window_s:
            self._window_start, self._in_window = now, 0
        self._in_window += 1
        if self._in_window > self.burst:
            self._suppressed += 1
            return
        note = ""
        if self._suppressed:
            note = f" ({self._suppressed} more SDK messages left out before this one)"
            self._suppressed = 0
        log.log(record.levelno, "foxglove-sdk %s: %s%s", record.name, record.getMessage(), note)


def _route_sdk_logs() -> None:
    """Once per process (the SDK's logging is global)."""
    import foxglove

    if _routed:
        return
    _routed.append(True)
    sdk = logging.getLogger("foxglove")
    sdk.setLevel(logging.WARNING)
    sdk.propagate = False
    sdk.addHandler(_SdkLog())
    foxglove.set_log_level(logging.WARNING)
