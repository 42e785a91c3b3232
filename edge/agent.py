"""The edge agent: every stream of one node, its health, its events and its liveliness token.

Streams start acquiring at once, into their spools; the agent connects to the hub's router in
the background and attaches the publishers when it answers. It publishes typed node health
(`NodeHealth`) about once a second, relays the hub's acks to the spools (refusing any ack for a
sequence not sent yet), and holds a liveliness token so the hub sees the node come and go.

Its events are spooled and acked like batches (`fleetdaq.edge.event_publisher`, spool folder
``events``);
typed health is not: it is a state, sent only while the hub is reachable, and its counters are
totals, so the first health after an outage tells all that the missed ones would have.

Its outputs (`fleetdaq.edge.outputs`) start at their initial values in the safe state; the queryable
that answers commands and the hub-heartbeat watch are attached with the session. Interlocks run
in the stream loops, so they hold whether or not the hub is there.
"""

from __future__ import annotations

import logging
import threading
import time
from pathlib import Path
from types import TracebackType

import zenoh

from fleetdaq import __version__
from fleetdaq.contract.cdr import encode
from fleetdaq.contract.config.site import SiteConfig
from fleetdaq.contract.errors import DriverError
from fleetdaq.contract.keys import EVENTS_STREAM, SiteKeys
from fleetdaq.contract.messages import KeyValue, NodeHealth, StreamHealth
from fleetdaq.contract.wire import decode_mark
from fleetdaq.edge.display import DisplayLoop, create_displays
from fleetdaq.edge.drivers.base import DriverHealth
from fleetdaq.edge.drivers.shared import SharedDevices
from fleetdaq.edge.drivers.table import create_driver
from fleetdaq.edge.event_publisher import EventPublisher
from fleetdaq.edge.outputs import OutputService
from fleetdaq.edge.spool import StreamSpool
from fleetdaq.edge.stream_loop import StreamLoop
from fleetdaq.edge.time_sync import NoTimeSyncMonitor, TimeSyncMonitor, make_time_sync_monitor
from fleetdaq.runtime.certificate_dates import check_dates, warn_days
from fleetdaq.runtime.host_metrics import HostMetricsReader
from fleetdaq.runtime.paths import default_spool_dir
from fleetdaq.runtime.security import SecretFileError, TlsFiles, node_tls, read_certificate
from fleetdaq.runtime.systemd import Systemd
from fleetdaq.runtime.threads import NamedThread
from fleetdaq.runtime.zenoh_session import Declared, client_config

log = logging.getLogger("fleetdaq.edge")

EVENTS_SEGMENT_BYTES = 1024 * 1024
"""Event spool segments: events are small, and acked segments are freed whole."""


class EdgeAgent:
    """Runs every stream of one node. A context manager: streams start on enter, stop on exit."""

    def __init__(
        self,
        site: SiteConfig,
        node: str,
        endpoints: list[str] | None = None,
        spool_dir: Path | None = None,
    ) -> None:
        if node not in site.nodes:
            raise DriverError(f"node {node!r} is not in the site config")
        self.site = site
        self.node = node
        self.endpoints = endpoints or site.endpoints_for(node)
        self.systemd = Systemd()
        """systemd's READY, STATUS and watchdog (each acquisition loop must keep moving)."""
        self.systemd.status_of = self.status_line
        self.tls: TlsFiles | None = None
        if site.security.tls:
            try:
                self.tls = node_tls(Path(site.security.pki_dir), node)
            except SecretFileError as err:
                raise DriverError(f"security.tls is on, but {err}") from None
        configured = site.nodes[node].spool.dir
        self.spool_dir = (
            spool_dir or (Path(configured) if configured else default_spool_dir())
        ) / node
        self.keys = SiteKeys(site.site)
        self._session: zenoh.Session | None = None
        self.events: EventPublisher | None = None
        self._ack_sub: zenoh.Subscriber[None] | None = None
        self._health_pub: zenoh.Publisher | None = None
        self._token: zenoh.LivelinessToken | None = None
        self.loops: list[StreamLoop] = []
        self.displays: list[DisplayLoop] = []
        self.shared = SharedDevices()
        """Devices several drivers reach (a T8 that streams and has outputs, a weld cell)."""
        self.outputs: OutputService | None = None
        self.time_sync: TimeSyncMonitor = NoTimeSyncMonitor()
        self._stop = threading.Event()
        self._health_thread = NamedThread(target=self._health, name="health", daemon=True)
        self._sync_thread = NamedThread(target=self._sync_spools, name="spool-sync", daemon=True)
        self._connector = NamedThread(target=self._connect, name="connect", daemon=True)
        self._session_lock = threading.Lock()
        self._started = False
        self._closed = False
        self.started_ns = 0
        self._host = HostMetricsReader({"spool": self.spool_dir})
        self.certificate_not_after_ns = 0
        """With TLS: when the first of its certificate and the site CA expires (UTC ns)."""

    def __enter__(self) -> EdgeAgent:
        self.start()
        return self

    def __exit__(
        self, t: type[BaseException] | None, e: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    def start(self) -> None:
        """Open the spools and start acquiring at once; connect to the hub in the background.

        Acquisition never waits for the network: a buoy that boots while its link is down
        spools from the first scan and delivers once the hub is reachable. If anything fails
        (or a Ctrl-C lands) part-way, everything opened so far is closed again.
        """
        try:
            self._start()
        except BaseException:
            self.close()
            raise

    def _start(self) -> None:
        sid, node = self.site.site, self.node
        self._started = True
        node_cfg = self.site.nodes[node]
        events = self.events = EventPublisher(
            None,
            self.keys.events(node),
            node,
            spool=StreamSpool(
                self.spool_dir / EVENTS_STREAM,
                node_cfg.spool.max_bytes,
                node_cfg.spool.max_age_s,
                EVENTS_SEGMENT_BYTES,
            ),
            replay_after_s=node_cfg.spool.replay_after_s,
        )
        self.time_sync = make_time_sync_monitor(
            node_cfg, lambda level, tag, msg, **kv: events.emit(level, "clock", tag, msg, **kv)
        )
        self.time_sync.start()
        for name, cfg in node_cfg.streams.items():
            spool = StreamSpool(
                self.spool_dir / name,
                node_cfg.spool.max_bytes,
                node_cfg.spool.max_age_s,
                node_cfg.spool.segment_bytes,
            )
            driver = create_driver(cfg, shared=self.shared)
            loop = StreamLoop(sid, node, name, cfg, None, events, spool, node_cfg.spool, driver)
            loop.time_sync = self.time_sync
            self.loops.append(loop)
        outputs = self.outputs = OutputService(
            sid, node, node_cfg, events, self.shared,
            command_age_limit_s=self.site.command_age_limit_s(node),
        )  # fmt: skip
        for loop in self.loops:
            hook = outputs.interlocks.hook(loop.name, loop.channel_index)
            if hook is not None:
                loop.batch_hooks.append(hook)
        self.displays = create_displays(
            node_cfg,
            self.latest_value,
            lambda level, tag, msg: events.emit(level, "display", tag, msg),
        )
        self.started_ns = time.time_ns()
        self._check_certificates(events)
        for loop in self.loops:
            self.systemd.beats.append(loop.beat)
        outputs.start()
        for loop in self.loops:
            loop.start()
        for display in self.displays:
            display.start()
        self._sync_thread.start()
        events.emit(
            logging.INFO,
            "agent",
            "started",
            f"started fleetdaq {__version__} with {len(self.loops)} stream(s), "
            f"connecting to {self.endpoints}",
        )
        self._connector.start()
        # Acquiring (into the spool, whether or not the hub is reachable yet): ready.
        self.systemd.ready(self.status_line())

    def status_line(self) -> str:
        """What `systemctl status` shows: streams, the hub link, what the spool holds."""
        spool = sum(loop.spool.bytes for loop in self.loops) / 1e6
        linked = "hub connected" if self._session is not None else "hub not reachable"
        streams = ", ".join(f"{loop.name} {loop.counters.batches} batches" for loop in self.loops)
        return f"node {self.node}: {streams}; {linked}; spool {spool:.1f} MB"

    def latest_value(self, stream: str, channel: str) -> float | None:
        """The newest value of `stream`/`channel` on this node, None before the first batch."""
        loop = next((lp for lp in self.loops if lp.name == stream), None)
        if loop is None or loop.latest is None or channel not in loop.channel_index:
            return None
        return float(loop.latest[loop.channel_index[channel]])

    def _connect(self) -> None:
        """Open the Zenoh session, retrying until the hub's router answers or we stop."""
        node = self.node
        by_stream = {loop.name: loop for loop in self.loops}

        def on_ack(sample: zenoh.Sample) -> None:
            key = self.keys.parse(str(sample.key_expr))
            mark = decode_mark(sample.payload.to_bytes())
            if key is not None and key.name == EVENTS_STREAM and mark is not None:
                assert self.events is not None
                self.events.ack(*mark)
                return
            loop = by_stream.get(key.name) if key is not None else None
            if loop is None or mark is None:
                return
            seq, epoch = mark
            if not loop.spool.ack(seq, epoch):
                why = (
                    f"it is for another spool's numbering (epoch {epoch}, this spool's is "
                    f"{loop.spool.epoch}: one this spool replaced)"
                    if epoch is not None and epoch != loop.spool.epoch
                    else f"only {loop.spool.next_sequence - 1} was sent"
                )
                loop.events.emit(
                    logging.ERROR,
                    loop.name,
                    "ack_refused",
                    f"ignored an ack for sequence {seq}: {why} (a confused or forged ack must "
                    "not delete unsent data)",
                    sequence=seq,
                    sent=loop.spool.next_sequence - 1,
                )

        backoff, warned = 0.5, False
        while not self._stop.is_set():
            try:
                # A short first attempt: the streams wait for it before they start.
                timeout_ms = 2000 if warned else 500
                session = zenoh.open(
                    client_config(self.endpoints, timeout_ms=timeout_ms, tls=self.tls)
                )
            except zenoh.ZError as err:
                for loop in self.loops:
                    loop.hub_unreachable.set()
                if not warned:
                    warned = True
                    log.warning(
                        "hub not reachable at %s (%s); acquiring into the spool and retrying",
                        self.endpoints,
                        err,
                    )
                if self._stop.wait(backoff):
                    return
                backoff = min(backoff * 2, 10.0)
                continue
            with self._session_lock:
                if self._stop.is_set():
                    session.close()
                    return
                self._session = session
                self._token = session.liveliness().declare_token(self.keys.alive(node))
                self._health_pub = session.declare_publisher(self.keys.health(node))
                self._ack_sub = session.declare_subscriber(self.keys.acks_of(node), on_ack)
                for loop in self.loops:
                    loop.attach(session)
                assert self.events is not None
                self.events.attach(session)
                if self.outputs is not None:
                    self.outputs.attach(session)
            log.info("connected to the hub at %s", self.endpoints)
            self._health_thread.start()
            return

    def health(self) -> NodeHealth:
        """This node's health now (what goes out on its health key about once a second)."""
        now = time.time_ns()
        return NodeHealth(
            time_ns=now,
            node=self.node,
            version=__version__,
            uptime_s=(now - self.started_ns) / 1e9,
            host=self._host.read(),
            streams=tuple(self._stream_health(loop, now) for loop in self.loops),
            clock=self.time_sync.message(),
            outputs=self.outputs.states() if self.outputs is not None else (),
            certificate_not_after_ns=self.certificate_not_after_ns,
        )

    def _check_certificates(self, events: EventPublisher) -> None:
        """With TLS: when its pair or the CA ends into its health; what is wrong with their
        dates as events (`fleetdaq.runtime.certificate_dates`)."""
        if self.tls is None:
            return
        mine, ca = read_certificate(self.tls.cert), read_certificate(self.tls.ca)
        self.certificate_not_after_ns, notes = check_dates(
            self.node, mine, ca, time.time_ns(), warn_days(self.site)
        )
        for n in notes:
            events.emit(n.level, "certificates", n.tag, n.message, **n.fields)

    @staticmethod
    def _stream_health(loop: StreamLoop, now_ns: int) -> StreamHealth:
        c, spool = loop.counters, loop.spool
        oldest = spool.oldest_unacked_time_ns()
        device = loop.driver.health() if isinstance(loop.driver, DriverHealth) else {}
        return StreamHealth(
            name=loop.name,
            batches=c.batches,
            scans=c.scans,
            invalid_samples=c.invalid_samples,
            read_errors=c.read_errors,
            next_sequence=c.next_sequence,
            replayed=c.replayed,
            sample_period_ns=loop.time_fit.period_ns,
            spool_bytes=spool.bytes,
            spool_acked=spool.acked,
            spool_floor=spool.floor,
            spool_dropped_batches=spool.dropped_batches,
            oldest_unacked_age_s=max(0.0, (now_ns - oldest) / 1e9) if oldest is not None else 0.0,
            acks_refused=spool.acks_refused,
            late_polls=c.late_polls,
            device=tuple(KeyValue(str(k), str(v)) for k, v in device.items()),
        )

    def _health(self) -> None:
        events, pub = self.events, self._health_pub
        assert events is not None
        assert pub is not None  # this thread starts once connected
        while not self._stop.wait(1.0):
            try:
                pub.put(encode(self.health()))
            except Exception:  # one bad reading must not end the node's health for good
                log.exception("publishing node health failed")
            events.flush()

    def _sync_spools(self) -> None:
        interval = self.site.nodes[self.node].spool.fsync_interval_s
        while not self._stop.wait(interval or 0.05):
            for loop in self.loops:
                loop.sync_spool()
            if self.events is not None:
                try:
                    self.events.sync()
                except OSError as err:
                    log.error("event spool fsync failed: %s", err)

    def close(self) -> None:
        """Stop every stream and close the session. Idempotent; safe after a partial start."""
        if not self._started or self._closed:
            return
        self._closed = True
        self.systemd.stopping(f"node {self.node}: stopping, outputs to their safe values")
        self._stop.set()
        try:
            for display in self.displays:
                display.close()
            for loop in self.loops:
                loop.stop()
            for loop in self.loops:
                loop.join(5.0)
            if self.outputs is not None:
                self.outputs.close()  # every output to its safe value, devices closed
            for thread in (self._connector, self._health_thread, self._sync_thread):
                if thread.is_alive():
                    thread.join(5.0)
            self.time_sync.close()
            if self.events is not None:
                self.events.emit(logging.INFO, "agent", "stopped", "stopped")
                self.events.close()
        finally:
            with self._session_lock:
                entities: tuple[Declared | None, ...] = (
                    self._ack_sub,
                    self._health_pub,
                    self._token,
                )
                for entity in entities:
                    if entity is not None:
                        entity.undeclare()
                if self._session is not None:
                    self._session.close()
                    self._session = None
            for loop in self.loops:
                loop.join_replayer(5.0)
