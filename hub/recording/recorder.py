"""The recorder service: data keys -> checks -> accounting -> MCAP session -> acks.

Zenoh delivers samples on its own threads. The data callback looks the key up among the
streams the site file defines (anything else is refused there, counted per key, and never
queued), checks that stream's share of the receive queue, copies the payload and stamps the
hub receive time. One writer thread checks each batch completely (every length, the
node/stream it claims, a plausible acquisition time), drops duplicates, writes the received
bytes untouched into the session, and at least every `flush_interval_s` closes the chunk in
progress, fsyncs, and acks per stream the highest contiguous sequence now durable
(`fleetdaq.hub.recording.stream_stats`; the events its accounting raises are
`fleetdaq.hub.recording.stream_reports`). Events
come from the event bus (this service is one of its subscribers) and node health from the
node watch; both are written on the same thread.

No single message can stop the writer: anything unexpected while handling one abandons the
open file (so what is closed stays readable), rolls the streams back to their last ack,
raises an event, and goes on. If the writer thread dies anyway, `failure()` says so and the
hub exits non-zero. A write error (a full disk) abandons the file, rolls every stream back,
raises an event and retries; the edges keep their spools until acks resume, then replay
(`fleetdaq.hub.recording.write_recovery`).

Stopping undeclares the subscribers first, then drains the queue, then closes files, so every
received batch is on disk when `stop()` returns.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, assert_never

from fleetdaq.contract.cdr import encode
from fleetdaq.contract.config.site import effective_yaml
from fleetdaq.contract.errors import WireError
from fleetdaq.contract.keys import EVENTS_STREAM, SiteKeys
from fleetdaq.contract.messages import EVENT_TYPE, Event
from fleetdaq.contract.wire import (
    BatchDecoder,
    decode_mark,
    encode_mark,
    encode_u64,
    plausible_time,
)
from fleetdaq.hub.bus import EventBus
from fleetdaq.hub.config.site import SiteConfig
from fleetdaq.hub.read_model import RECORDER, STREAMS, ReadModel, RecorderView
from fleetdaq.hub.recording.batch_feed import BatchFeed, FedBatch
from fleetdaq.hub.recording.seams import EventAcks, Refusals
from fleetdaq.hub.recording.session import EVENTS_TOPIC, RecordingSession, StreamSelector, topic_of
from fleetdaq.hub.recording.stream_reports import StreamReports
from fleetdaq.hub.recording.stream_stats import StreamStats
from fleetdaq.hub.recording.write_recovery import Held, WriteRecovery
from fleetdaq.hub.recording.writer_queue import (
    STOP,
    Batch,
    EdgeDrops,
    EventRecord,
    Mark,
    Message,
    Stop,
    WriterItem,
)
from fleetdaq.hub.routing.router import Router
from fleetdaq.runtime.systemd import Beat
from fleetdaq.runtime.threads import NamedThread

log = logging.getLogger("fleetdaq.recorder")

Tap = Callable[[str, bytes, int, int, str], None]
"""tap(topic, payload, publish time, receive time, message type)."""

_MAX_SEQUENCE = 2**63 - 1
_VIEW_INTERVAL_S = 0.25


class Recorder:
    name = "recorder"

    def __init__(
        self,
        router: Router,
        site: SiteConfig,
        data_dir: Path,
        bus: EventBus,
        model: ReadModel,
        refused: Refusals,
        events: EventAcks,
        feed: BatchFeed | None = None,
        max_queued_bytes: int = 512 * 1024 * 1024,
        partition: str | None = None,
        tap: Tap | None = None,
    ) -> None:
        """`partition`: the hub this is (None: the main hub). With `hub.partitions` in the site
        file, a hub records and acks only the streams of its own nodes (`SiteConfig.nodes_of`)
        and subscribes to those alone, so no other hub's batches cross the router mesh to it.
        `events`: the events the nodes it records spooled (`SiteConfig.nodes_of` of the same
        `partition`), acked once recorded and logged."""
        self.router = router
        self.site = site
        self.cfg = site.hub.recorder
        self.data_dir = data_dir
        self.bus = bus
        self.model = model
        self.keys = SiteKeys(site.site)
        select = StreamSelector(self.cfg.include, self.cfg.exclude)
        self.nodes = site.nodes_of(partition)
        self.partitioned = bool(site.hub.partitions)
        names = [(n, s) for n in self.nodes for s in site.nodes[n].streams]
        budget = max(4 * 1024 * 1024, max_queued_bytes // max(1, len(names)))
        self.routes: dict[str, StreamStats] = {}
        for node, stream in names:
            st = StreamStats(
                node, stream, select(node, stream), site.nodes[node].streams[stream].rate_hz
            )
            st.budget_bytes = budget
            st.sample_format = site.nodes[node].streams[stream].sample_format
            self.routes[self.keys.data(node, stream)] = st
        self.streams = {(st.node, st.stream): st for st in self.routes.values()}
        self.refused = refused
        self.feed = feed or BatchFeed()
        """Accepted batches go on to the services that look at the data (alarms, ...)."""
        self._bytes_before = 0
        """Bytes of the sessions before the current one (stop and start make a new one)."""
        self.beat = Beat("recorder writer")
        """Shows the writer loop moves (at least every 0.2 s): systemd's watchdog watches it."""
        self.tap = tap
        """Also handed every message recorded besides batches (the snapshot buffer), on the
        writer thread, whether or not the recorder is recording. Must be quick."""
        self.writer_errors = 0
        self.recovery = WriteRecovery(bus, self._abandon)
        self.lock = threading.Lock()
        """Held by the writer thread while it handles an item; `summary()` takes it."""
        self._queue: queue.SimpleQueue[WriterItem] = queue.SimpleQueue()
        self._decoders: dict[tuple[str, str], BatchDecoder] = {}
        self.session: RecordingSession | None = None
        self._thread = NamedThread(target=self._writer, name="recorder", daemon=True)
        self._subs: list[Any] = []
        self._stopped = False
        self.recording = True
        """False while stopped by an operator or a rule (`stop_recording`)."""
        self._died: str | None = None
        self._last_flush = time.monotonic()
        self._last_view = 0.0
        self.reports = StreamReports(bus)
        self.event_delivery = events
        """The events the nodes it records spooled: acked here once recorded and logged."""
        self._bus_sub = bus.subscribe(self.name, self._on_event, maxsize=100_000)

    # --- lifecycle ----------------------------------------------------------------------------

    def _new_session(self) -> RecordingSession:
        return RecordingSession(
            self.data_dir,
            self.site.site,
            list(self.nodes),
            self.cfg,
            effective_yaml(self.site),
            time.time_ns(),
        )

    def start(self) -> None:
        self.session = self._new_session()
        if self.cfg.recover_on_start:
            self._recover_crashed_files()
        self._publish_view(force=True)
        self._thread.start()
        routes, refused, put = self.routes, self.refused, self._queue.put

        def on_data(sample: Any) -> None:
            key = str(sample.key_expr)
            st = routes.get(key)
            if st is None:
                refused.refuse(key, "data")
                return
            # Bounded per stream: past its share a batch is dropped here, counted, and not
            # acked, so the edge replays it; one stream flooding cannot starve the others.
            if st.queued_bytes > st.budget_bytes:
                st.overflow += 1
                return
            att = sample.attachment
            mark = decode_mark(att.to_bytes()) if att is not None else None
            payload = sample.payload.to_bytes()
            st.queued_bytes += len(payload)
            put(Batch(st, payload, time.time_ns(), mark))

        # One hub: every node's data (keys of unknown nodes refused and counted). Partitioned:
        # each of its own nodes', or the other hubs' batches would cross the mesh to it.
        selectors = (
            [self.keys.data(node, "*") for node in self.nodes]
            if self.partitioned
            else [self.keys.all_data]
        )
        declare = self.router.session.declare_subscriber
        self._subs = [declare(key, on_data) for key in selectors]

    def _recover_crashed_files(self) -> None:
        """Turn ``*.mcap.active`` files left by a crash into valid files, with an event each."""
        from fleetdaq.hub.recording.data_lock import FileInUse
        from fleetdaq.hub.recording.verify import recover_file, refresh_metadata

        assert self.session is not None
        own = self.session.dir
        crashed = [
            *self.data_dir.glob("*/*.mcap.active"),
            *self.data_dir.glob("snapshots/*/*.active"),
        ]
        for f in sorted(crashed):
            if f.parent == own:
                continue
            try:
                report = recover_file(f)
            except FileInUse as err:  # a `fleetdaq verify --recover` on it right now
                self.bus.emit(logging.WARNING, "recorder", "recover_skipped", str(err))
                continue
            except OSError as err:
                self.bus.emit(
                    logging.ERROR, "recorder", "recover_failed", f"could not recover {f}: {err}"
                )
                continue
            refresh_metadata(f.parent)
            self.bus.emit(
                logging.WARNING,
                "recorder",
                "recovered",
                f"recovered a file left by a crash: {f.parent.name}/{report.line()}",
                file=str(f),
            )

    def record(
        self, topic: str, payload: bytes, publish_ns: int, recv_ns: int, msgtype: str
    ) -> None:
        """Record a message other than a batch (node health...) whose payload was checked."""
        self._queue.put(Message(topic, payload, publish_ns, recv_ns, msgtype))

    def _on_event(self, e: Event) -> None:
        """A bus subscriber: the event goes to the writer thread's queue (and an edge's report
        of the batches its full spool dropped goes to the stream's accounting)."""
        self._queue.put(EventRecord(e, encode(e), e.time_ns, time.time_ns()))
        if e.tag == "spool_full":
            st = self.streams.get((e.node, e.source))
            try:
                first, last = int(e.get("first") or ""), int(e.get("last") or "")
            except ValueError:
                return
            if st is not None and 0 <= first <= last <= _MAX_SEQUENCE:
                self._queue.put(EdgeDrops(st, first, last))

    def stop(self) -> None:
        """Stop receiving, write everything received, close the files. Idempotent."""
        if self._stopped or self.session is None:
            return
        self._stopped = True
        for sub in self._subs:
            sub.undeclare()
        self._subs = []
        self.bus.emit(logging.INFO, "hub", "stopped", "hub stopping: closing files")
        self._bus_sub.flush()
        if self._thread.is_alive():
            self._queue.put(STOP)
            self._thread.join()
        with self.lock:
            self._drain()
            self._flush_and_ack()
            self._guarded("closing the session", self.session.close)
            self._publish_view(force=True, state="stopped")

    def failure(self) -> str | None:
        return self._died

    # --- the writer thread ----------------------------------------------------------------------

    def _writer(self) -> None:
        try:
            self._writer_loop()
        except BaseException as err:
            self._died = f"the recorder's writer thread died: {err!r}"
            log.critical("%s", self._died, exc_info=True)
            self._publish_view(force=True, state="failed")
            self.bus.emit(
                logging.CRITICAL,
                "recorder",
                "writer_died",
                f"{self._died}; nothing more is recorded or acked (edges keep spooling); the "
                "hub exits so that its supervisor restarts it",
            )

    def _writer_loop(self) -> None:
        get = self._queue.get
        interval = self.cfg.flush_interval_s
        beat = self.beat.beat
        while True:
            beat()
            try:
                item = get(timeout=min(0.2, interval))
            except queue.Empty:
                item = None
            if isinstance(item, Stop):
                return
            with self.lock:
                if item is not None:
                    self._handle(item)
                if time.monotonic() - self._last_flush >= interval:
                    self._flush_and_ack()
                self._publish_view()

    def _drain(self) -> None:
        while True:
            try:
                item = self._queue.get_nowait()
            except queue.Empty:
                return
            self._handle(item)

    def _handle(self, item: WriterItem) -> None:
        try:
            match item:
                case Batch(st, payload, recv_ns, mark):
                    st.queued_bytes -= len(payload)
                    self._record(st, payload, recv_ns, mark)
                case EventRecord(event, payload, time_ns, recv_ns):
                    self._record_event(payload, time_ns, recv_ns)
                    self.event_delivery.recorded(event)
                case EdgeDrops(st, first, last):
                    self.reports.dropped_by_edge(st, first, last)
                case Message(topic, payload, publish_ns, recv_ns, msgtype):
                    self._record_message(topic, payload, publish_ns, recv_ns, msgtype)
                case Stop():
                    pass  # only ends the loop; drained after it, there is nothing to do
                case _:
                    assert_never(item)
        except Exception as err:  # no single message may stop the writer
            self._unexpected(err)

    def _unexpected(self, err: Exception) -> None:
        """Something a message did that was not foreseen: the open file may hold half a
        record now, so it is abandoned (as after a write error) and the streams roll back to
        their last ack; the edges send the rest again. Events and messages written since the
        last flush wait for the next one."""
        self.writer_errors += 1
        log.error("recorder: unexpected error handling a message", exc_info=True)
        abandoned = self.recovery.abandon_after_unexpected()
        if self.writer_errors <= 10 or self.writer_errors % 100 == 0:
            kept = f"; abandoned {abandoned.name} (fleetdaq verify --recover)" if abandoned else ""
            self.bus.emit(
                logging.ERROR,
                "recorder",
                "writer_error",
                f"unexpected error handling a message: {err!r}{kept}; recording goes on "
                f"({self.writer_errors} so far)",
                errors=self.writer_errors,
            )

    def _guarded(self, what: str, fn: Any, *args: Any) -> bool:
        """Run a session write; on OSError abandon the file and retry later. False if failed."""
        try:
            fn(*args)
            return True
        except OSError as err:
            self.recovery.failed(what, err)
            return False

    def _abandon(self) -> Path | None:
        assert self.session is not None
        abandoned = self.session.abandon()
        for st in self.streams.values():
            st.rollback()
        return abandoned

    def _write_held(self, item: Held) -> None:
        assert self.session is not None
        if self._guarded("writing", self.session.write, *item):
            self.recovery.unflushed.append(item)
        else:
            self.recovery.hold(item)

    def _record_event(self, payload: bytes, time_ns: int, recv_ns: int) -> None:
        publish = time_ns if plausible_time(time_ns, recv_ns) else recv_ns
        self._record_message(EVENTS_TOPIC, payload, publish, recv_ns, EVENT_TYPE)

    def _record_message(
        self, topic: str, payload: bytes, publish_ns: int, recv_ns: int, msgtype: str
    ) -> None:
        assert self.session is not None
        publish = publish_ns if plausible_time(publish_ns, recv_ns) else recv_ns
        item = (topic, payload, publish, recv_ns, msgtype)
        if self.tap is not None:
            self.tap(topic, payload, publish, recv_ns, msgtype)
        if not self.recording:
            return  # stopped by an operator or a rule: nothing is written (nothing is owed)
        if self.recovery.recovering():
            self.recovery.hold(item)
            return
        self._write_held(item)

    def _decoder(self, st: StreamStats) -> BatchDecoder:
        """The stream's decoder (writer thread only): its strings are parsed once, not per
        batch (a tenth of the hub's CPU with a hundred small edges)."""
        d = self._decoders.get((st.node, st.stream))
        if d is None:
            d = self._decoders[(st.node, st.stream)] = BatchDecoder()
        return d

    def _record(self, st: StreamStats, payload: bytes, recv_ns: int, mark: Mark | None) -> None:
        assert self.session is not None
        node, stream = st.node, st.stream
        floor, epoch = mark if mark is not None else (None, None)
        try:
            h = self._decoder(st).read_header(payload, st.sample_format)
            if (h.node, h.stream) != (node, stream):
                raise WireError(f"payload says {h.node}/{h.stream}, key says {node}/{stream}")
            if floor is not None and floor > h.sequence:
                # An edge's floor is the lowest sequence its spool holds: never above a batch
                # it sends. Believing it would write off every batch below it as lost.
                raise WireError(f"floor {floor} above the batch's own sequence {h.sequence}")
        except WireError as err:
            self.reports.malformed(st, err)
            return
        if epoch is not None and epoch != st.epoch:
            self.reports.spool_restarted(st, epoch, h.sequence)
        if st.contiguous is None and floor is None and h.sequence != 0:
            self.reports.late_start(st, h.sequence)
        if not self.recovery.writable():
            st.deferred += 1
            return
        is_new, newly_lost = st.offer(h.sequence, floor)
        if newly_lost:
            self.reports.lost_below_floor(st, newly_lost, floor)
        if not is_new:
            return
        publish = h.first_sample_time_ns
        if not plausible_time(publish, recv_ns):
            publish = recv_ns
            self.reports.implausible(st, h.first_sample_time_ns)
        if (
            st.recorded
            and self.recording
            and not self._guarded(
                "writing",
                self.session.write,
                topic_of(node, stream),
                payload,
                publish,
                recv_ns,
                h.msgtype,
            )
        ):
            st.deferred += 1
            return
        late = st.last_sequence is not None and h.sequence < st.last_sequence
        self.feed.publish(FedBatch(node, stream, h, payload, recv_ns, late))
        for gap_s, before in st.count(
            h.sequence, h.scan_count, h.samples, recv_ns, h.first_sample_time_ns, h.sample_period_ns
        ):
            self.reports.acquisition_gap(st, gap_s, before)

    def _flush_and_ack(self) -> None:
        assert self.session is not None
        self._last_flush = time.monotonic()
        recovery = self.recovery
        if not recovery.writable():
            return
        # Events written while a write error was pending may go down with the next abandoned
        # file: only a flush that starts clean makes the recorded ones durable.
        clean = not recovery.recovering()
        if recovery.recovering() and self.session.current_file is None and recovery.held:
            # No batch has come to open a file since the error (every edge may be down): the
            # oldest held event opens one, so this flush tells whether writing works again
            # and the events raised meanwhile are not kept in memory until a batch comes.
            item = recovery.held[0]
            if self.recording:
                if not self._guarded("writing", self.session.write, *item):
                    return  # refused again: still held, retried in 2 s
                recovery.unflushed.append(recovery.held.pop(0))
        if self.session.due_split(time.time_ns()):
            if not self._guarded("closing a file", self.session.split):
                return
        elif not self._guarded("flushing", self.session.flush):
            return
        recovery.flushed()  # durable now
        if clean:
            self.event_delivery.flushed()
        if recovery.recovering() and self.session.current_file is not None:
            # The flush of a file went through: writing works again. The held events go in
            # now and are made durable by the next flush (held again if that fails). With no
            # file open (abandoned, nothing written since) the flush wrote nothing and proves
            # nothing: the next batch opens a file, and its flush tells.
            recovery.resume(self._write_held)
        put = self.router.session.put
        for st in self.streams.values():
            st.durable = st.contiguous
            if st.durable is not None and st.durable >= 0 and st.durable != st.acked_sent:
                ack = (
                    encode_mark(st.durable, st.epoch)
                    if st.epoch is not None
                    else encode_u64(st.durable)
                )
                put(self.keys.ack(st.node, st.stream), ack)
                st.acked_sent = st.durable
        for node, seq, epoch in self.event_delivery.acks():
            put(self.keys.ack(node, EVENTS_STREAM), encode_mark(seq, epoch))

    def _publish_view(self, force: bool = False, state: str | None = None) -> None:
        now = time.monotonic()
        if not force and now - self._last_view < _VIEW_INTERVAL_S:
            return
        self._last_view = now
        s = self.session
        if state is None:
            state = (
                "stopped"
                if not self.recording
                else "recording"
                if self.recovery.writable()
                else "disk_error"
            )
        current = s.current_file if s is not None else None
        size = s.current_size() if s is not None else 0
        self.model.put(STREAMS, tuple(st.view() for st in self.streams.values()))
        self.model.put(
            RECORDER,
            RecorderView(
                state=state,
                session=s.name if s is not None else "",
                session_dir=str(s.dir) if s is not None else "",
                current_file=str(current) if current is not None else "",
                current_file_bytes=size,
                bytes_written=self._bytes_before + (s.closed_bytes if s is not None else 0) + size,
                files=tuple(str(p) for p in s.files()) if s is not None else (),
                abandoned_files=tuple(str(p) for p in s.abandoned) if s is not None else (),
                write_errors=self.recovery.write_errors,
                writer_errors=self.writer_errors,
                malformed=sum(st.malformed for st in self.streams.values()),
                overflow=sum(st.overflow for st in self.streams.values()),
                queued_bytes=sum(st.queued_bytes for st in self.streams.values()),
                events_not_recorded=self.recovery.events_not_recorded,
            ),
        )

    # --- control ---------------------------------------------------------------------------------

    def split(self, who: str = "", note: str = "") -> str:
        """Close the current file now; the next message opens the next one. `note`: why (the
        requester's, in the event)."""
        with self.lock:
            assert self.session is not None
            if not self.recording:
                return "not recording: nothing to split"
            current = self.session.current_file
            if current is None:
                return "no file open yet"
            if not self._guarded("closing a file", self.session.split):
                return "the file could not be closed (see the write error)"
        self.bus.emit(
            logging.INFO,
            "recorder",
            "split",
            f"file {current.name.removesuffix('.active')} closed on request"
            + (f" by {who}" if who else "")
            + (f": {note}" if note else ""),
            by=who,
        )
        return f"closed {current.name.removesuffix('.active')}"

    def stop_recording(self, who: str, note: str = "") -> str:
        """Stop writing (files closed). Batches are still checked, counted and acked: the
        edges owe nothing while the recorder is stopped. `note`: why (in the event)."""
        with self.lock:
            if not self.recording:
                return "already stopped"
            assert self.session is not None
            self._flush_and_ack()
            self._guarded("closing the session", self.session.close)
            self.recording = False
            name = self.session.name
            self._publish_view(force=True)
        self.bus.emit(
            logging.WARNING,
            "recorder",
            "recording_stopped",
            f"recording stopped by {who or 'someone'} (session {name} closed); batches are still "
            "counted and acked but not recorded" + (f": {note}" if note else ""),
            by=who,
            session=name,
        )
        return f"stopped; session {name} closed"

    def start_recording(self, who: str, note: str = "") -> str:
        """Start writing again, into a new session folder. `note`: why (in the event)."""
        with self.lock:
            if self.recording:
                return "already recording"
            if self.session is not None:
                self._bytes_before += self.session.closed_bytes
            self.session = self._new_session()
            self.recording = True
            name = self.session.name
            self._publish_view(force=True)
        self.bus.emit(
            logging.INFO,
            "recorder",
            "recording_started",
            f"recording started by {who or 'someone'} into session {name}"
            + (f": {note}" if note else ""),
            by=who,
            session=name,
        )
        return f"recording into {name}"

    def summary(self) -> dict[str, Any]:
        with self.lock:
            s = self.session
            assert s is not None
            return {
                "session": str(s.dir),
                "files": [str(p) for p in s.files()],
                "abandoned_files": [str(p) for p in s.abandoned],
                "streams": {
                    f"{k[0]}/{k[1]}": st.summary() for k, st in sorted(self.streams.items())
                },
                "malformed": sum(st.malformed for st in self.streams.values()),
                "write_errors": self.recovery.write_errors,
                "writer_errors": self.writer_errors,
                "overflow": sum(st.overflow for st in self.streams.values()),
                "refused": self.refused.total,
                "refused_keys": dict(self.refused.counts),
                "events_not_recorded": self.recovery.events_not_recorded,
                "messages_not_recorded": self.recovery.messages_not_recorded,
                "spooled_events": self.event_delivery.summary(),
            }
