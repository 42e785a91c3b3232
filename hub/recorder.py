"""The recorder service: data keys -> accounting -> MCAP session -> acks.

Zenoh delivers samples on its own threads; the callback only copies the payload (and the
edge's `floor` attachment) and stamps the hub receive time into a queue. One writer thread
validates each batch header (bounds-checked, no array decode), drops duplicates, writes the
received bytes untouched into the session, and at least every `flush_interval_s` closes the
chunk in progress, fsyncs, and acks per stream the highest contiguous sequence now durable.

Delivery bookkeeping per stream: `contiguous` is the highest sequence such that every
sequence from the stream's base up to it is written; `pending` holds sequences written above
a hole (waiting for the edge to replay the hole). The edge's `floor` says it no longer holds
anything below it: holes below the floor can never be filled and are counted as `lost`,
with an event. A write error (a full disk) abandons the file, rolls every stream back to its
last durable (acked) sequence, raises an event and retries; the edges keep their spools
until acks resume, then replay.

Stopping undeclares the subscribers first, then drains the queue, then closes files, so every
received batch is on disk when `close()` returns.
"""

from __future__ import annotations

import errno
import logging
import queue
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from edge.config import SiteConfig, effective_yaml
from edge.errors import WireError
from edge.wire import (
    EVENT_TYPE,
    Event,
    ack_key,
    data_selector,
    decode_event,
    decode_u64,
    encode_event,
    encode_u64,
    events_selector,
    read_header,
    split_data_key,
)
from hub.events import EventLog
from hub.session import EVENTS_TOPIC, RecordingSession, StreamSelector, topic_of

log = logging.getLogger("fleetdaq.recorder")

_STOP = object()
_DATA, _EVENT = 0, 1
_RETRY_AFTER_ERROR_S = 2.0
_MAX_HELD_EVENTS = 10_000


@dataclass(slots=True)
class StreamStats:
    """Per-stream delivery accounting from sequence numbers."""

    node: str
    stream: str
    recorded: bool
    rate_hz: float | None = None
    batches: int = 0
    scans: int = 0
    samples: int = 0
    duplicates: int = 0
    late: int = 0
    """Batches that arrived after a higher sequence (replayed from the edge's spool)."""
    lost: int = 0
    """Sequences the edge no longer holds and this hub never received: gone for good."""
    deferred: int = 0
    """Batches received while the disk refused writes (not acked: the edge sends them again)."""
    first_sequence: int | None = None
    last_sequence: int | None = None
    contiguous: int | None = None
    durable: int | None = None
    """Highest sequence acked (written, flushed, fsynced)."""
    acked_sent: int | None = None
    pending: set[int] = field(default_factory=set)
    acq_gaps: int = 0
    """Breaks in acquisition time between consecutive batches (e.g. an edge restart)."""
    acq_gap_s: float = 0.0
    last_receive_ns: int = 0
    _next_t: float | None = None
    _in_order: bool = False
    _recent: deque[tuple[int, int]] = field(default_factory=lambda: deque(maxlen=64))

    @property
    def missing(self) -> int:
        """Holes below the highest sequence received, still waiting for a replay."""
        if self.contiguous is None or self.last_sequence is None:
            return 0
        return self.last_sequence - self.contiguous - len(self.pending)

    @property
    def gaps(self) -> int:
        """Sequences not recorded: lost for good plus holes not (yet) filled."""
        return self.lost + self.missing

    def offer(self, seq: int, floor: int | None) -> tuple[bool, int]:
        """Account for a batch. Returns (is new, newly lost sequences)."""
        newly_lost = 0
        if self.contiguous is None:
            # First batch this hub sees: below the edge's floor everything was acked before
            # (by an earlier hub run) or dropped and reported by the edge.
            base = floor if floor is not None and floor <= seq else seq
            self.contiguous = self.durable = base - 1
            self.first_sequence = base
        elif floor is not None and floor > self.contiguous + 1:
            below = sum(1 for p in self.pending if p < floor)
            newly_lost = floor - 1 - self.contiguous - below
            self.lost += newly_lost
            self.contiguous = floor - 1
            self._absorb()
        if seq <= self.contiguous or seq in self.pending:
            self.duplicates += 1
            return False, newly_lost
        if self.last_sequence is not None and seq < self.last_sequence:
            self.late += 1
        self._in_order = self.last_sequence is not None and seq == self.last_sequence + 1
        self.pending.add(seq)
        self._absorb()
        if self.last_sequence is None or seq > self.last_sequence:
            self.last_sequence = seq
        return True, newly_lost

    def _absorb(self) -> None:
        assert self.contiguous is not None
        while self.contiguous + 1 in self.pending:
            self.pending.remove(self.contiguous + 1)
            self.contiguous += 1
        if self.pending:  # a floor jump can leave pending entries below the new mark
            self.pending = {p for p in self.pending if p > self.contiguous}

    def count(
        self, seq: int, scans: int, samples: int, recv_ns: int, t0: int, period_ns: float
    ) -> float | None:
        """Count an accepted batch; return the acquisition gap (s) before it, if any."""
        self.batches += 1
        self.scans += scans
        self.samples += samples
        self.last_receive_ns = recv_ns
        self._recent.append((recv_ns, self.scans))
        gap = None
        if self._next_t is not None and self._in_order:
            missing_s = (t0 - self._next_t) / 1e9
            if missing_s > max(2 * period_ns / 1e9, 0.02):
                gap = missing_s
                self.acq_gaps += 1
                self.acq_gap_s += missing_s
        if seq == self.last_sequence:
            self._next_t = t0 + scans * period_ns
        return gap

    def rollback(self) -> None:
        """What was written since the last durable flush may be lost: expect it again."""
        self.contiguous = self.durable
        self.pending.clear()

    def scan_rate(self) -> float:
        """Scans per second over the recent batches."""
        if len(self._recent) < 2:
            return 0.0
        (t0, n0), (t1, n1) = self._recent[0], self._recent[-1]
        return (n1 - n0) / ((t1 - t0) / 1e9) if t1 > t0 else 0.0

    def summary(self) -> dict[str, Any]:
        return {
            "node": self.node,
            "stream": self.stream,
            "recorded": self.recorded,
            "batches": self.batches,
            "scans": self.scans,
            "samples": self.samples,
            "gaps": self.gaps,
            "lost": self.lost,
            "missing": self.missing,
            "duplicates": self.duplicates,
            "late": self.late,
            "deferred": self.deferred,
            "acquisition_gaps": self.acq_gaps,
            "acquisition_gap_s": round(self.acq_gap_s, 3),
            "first_sequence": self.first_sequence,
            "last_sequence": self.last_sequence,
            "acked": self.durable,
        }


class Recorder:
    """Subscribes to every data and event key of the site and records them."""

    def __init__(self, session: Any, site: SiteConfig, data_dir: Path) -> None:
        self.site = site
        self.cfg = site.hub.recorder
        self.data_dir = data_dir
        self.select = StreamSelector(self.cfg.include, self.cfg.exclude)
        self.streams: dict[tuple[str, str], StreamStats] = {}
        self.malformed = 0
        self.malformed_by_key: dict[str, int] = {}
        self.write_errors = 0
        self.events_not_recorded = 0
        self.max_queued_bytes = 512 * 1024 * 1024
        self.queued_bytes = 0
        """Payload bytes received and not yet written (approximate: two threads update it)."""
        self.overflow = 0
        """Batches dropped on arrival because the queue was over `max_queued_bytes`."""
        self.lock = threading.Lock()
        self._queue: queue.SimpleQueue[Any] = queue.SimpleQueue()
        self._zsession = session
        self.session = RecordingSession(
            data_dir, site.site, list(site.nodes), self.cfg, effective_yaml(site), time.time_ns()
        )
        self.events = EventLog(data_dir / "events.log")
        self._thread = threading.Thread(target=self._writer, name="recorder", daemon=True)
        self._subs: list[Any] = []
        self._closed = False
        self._broken_until = 0.0
        self._held_events: list[tuple[bytes, int, int]] = []
        self._last_flush = time.monotonic()

    def start(self) -> None:
        self._thread.start()
        put = self._queue.put

        limit = self.max_queued_bytes

        def on_data(sample: Any) -> None:
            # Bounded: past the limit a batch is dropped here, counted, and not acked, so the
            # edge replays it. Memory stays bounded when the disk is slower than the network.
            if self.queued_bytes > limit:
                self.overflow += 1
                return
            att = sample.attachment
            floor = decode_u64(att.to_bytes()) if att is not None else None
            payload = sample.payload.to_bytes()
            self.queued_bytes += len(payload)
            put((_DATA, str(sample.key_expr), payload, time.time_ns(), floor))

        def on_event(sample: Any) -> None:
            put((_EVENT, str(sample.key_expr), sample.payload.to_bytes(), time.time_ns(), None))

        site = self.site.site
        self._subs = [
            self._zsession.declare_subscriber(data_selector(site), on_data),
            self._zsession.declare_subscriber(events_selector(site), on_event),
        ]

    def emit(self, level: int, source: str, tag: str, message: str) -> None:
        """Raise a hub event: recorded in the session, logged, shown, alerted on."""
        now = time.time_ns()
        e = Event(now, "hub", level, source, tag, message)
        self._queue.put((_EVENT, "", encode_event(e), now, None))

    # --- the writer thread ------------------------------------------------------------------

    def _writer(self) -> None:
        get = self._queue.get
        interval = self.cfg.flush_interval_s
        while True:
            try:
                item = get(timeout=min(0.2, interval))
            except queue.Empty:
                item = None
            if item is _STOP:
                return
            with self.lock:
                if item is not None:
                    kind, key, payload, recv_ns, floor = item
                    if kind == _DATA:
                        self.queued_bytes -= len(payload)
                        self._record(key, payload, recv_ns, floor)
                    else:
                        self._record_event(key, payload, recv_ns)
                if time.monotonic() - self._last_flush >= interval:
                    self._flush_and_ack()

    def _writable(self) -> bool:
        return time.monotonic() >= self._broken_until

    def _guarded(self, what: str, fn: Any, *args: Any) -> bool:
        """Run a session write; on OSError abandon the file and retry later. False if failed."""
        try:
            fn(*args)
            return True
        except OSError as err:
            self._write_failed(what, err)
            return False

    def _write_failed(self, what: str, err: OSError) -> None:
        self.write_errors += 1
        first = self._broken_until == 0.0
        self._broken_until = time.monotonic() + _RETRY_AFTER_ERROR_S
        abandoned = self.session.abandon()
        for st in self.streams.values():
            st.rollback()
        if first:
            kept = f"abandoned {abandoned.name} (fleetdaq verify --recover); " if abandoned else ""
            full = err.errno in (errno.ENOSPC, errno.EDQUOT)
            self._event_now(
                logging.CRITICAL if full else logging.ERROR,
                "recorder",
                "disk_full" if full else "write_error",
                f"{what} failed: {err}; {kept}not acking, so edges keep spooling; "
                f"retrying every {_RETRY_AFTER_ERROR_S:g} s",
            )

    def _resumed(self) -> None:
        if self._broken_until != 0.0:
            self._broken_until = 0.0
            held, self._held_events = self._held_events, []
            for payload, time_ns, recv_ns in held:
                self._write_event(payload, time_ns, recv_ns)
            self._event_now(
                logging.WARNING,
                "recorder",
                "write_resumed",
                "writing again; edges replay what was not acked",
            )

    def _record_event(self, key: str, payload: bytes, recv_ns: int) -> None:
        try:
            e = decode_event(payload)
        except WireError as err:
            self._malformed(key or "hub/events", err)
            return
        self.events.add(e)
        if self._writable() and self._write_event(payload, e.time_ns, recv_ns):
            return
        # Kept until writing resumes, so the recording still tells what happened. Past the
        # bound they are still in events.log and counted here.
        if len(self._held_events) < _MAX_HELD_EVENTS:
            self._held_events.append((payload, e.time_ns, recv_ns))
        else:
            self.events_not_recorded += 1

    def _write_event(self, payload: bytes, time_ns: int, recv_ns: int) -> bool:
        if not self._guarded(
            "writing an event",
            self.session.write,
            EVENTS_TOPIC,
            payload,
            time_ns,
            recv_ns,
            EVENT_TYPE,
        ):
            return False
        self._resumed()
        return True

    def _malformed(self, key: str, err: WireError) -> None:
        self.malformed += 1
        self.malformed_by_key[key] = self.malformed_by_key.get(key, 0) + 1
        if self.malformed_by_key[key] == 1:
            log.warning("malformed payload on %s: %s", key, err)

    def _record(self, key: str, payload: bytes, recv_ns: int, floor: int | None) -> None:
        try:
            _, node, stream = split_data_key(key)
            h = read_header(payload)
            if (h.node, h.stream) != (node, stream):
                raise WireError(f"payload says {h.node}/{h.stream}, key says {node}/{stream}")
        except WireError as err:
            self._malformed(key, err)
            return
        stats = self.streams.get((node, stream))
        if stats is None:
            cfg = self.site.nodes.get(node)
            rate = cfg.streams[stream].rate_hz if cfg and stream in cfg.streams else None
            stats = StreamStats(node, stream, self.select(node, stream), rate)
            self.streams[(node, stream)] = stats
            if floor is None and h.sequence != 0:
                self._event_now(
                    logging.WARNING,
                    "recorder",
                    "late_start",
                    f"{node}/{stream} first seen at sequence {h.sequence} with no spool floor: "
                    "batches before it were not received by this hub",
                )
        if not self._writable():
            stats.deferred += 1
            return
        is_new, newly_lost = stats.offer(h.sequence, floor)
        if newly_lost:
            self._event_now(
                logging.ERROR,
                "recorder",
                "lost",
                f"{node}/{stream}: {newly_lost} batch(es) below sequence {floor} were never "
                "received and the edge no longer holds them",
            )
        if not is_new:
            return
        if stats.recorded and not self._guarded(
            "writing",
            self.session.write,
            topic_of(node, stream),
            payload,
            h.first_sample_time_ns,
            recv_ns,
        ):
            stats.deferred += 1
            return
        self._resumed()
        gap = stats.count(
            h.sequence, h.scan_count, h.samples, recv_ns, h.first_sample_time_ns, h.sample_period_ns
        )
        if gap is not None:
            self._event_now(
                logging.WARNING,
                "recorder",
                "acquisition_gap",
                f"{node}/{stream}: {gap:.3f} s without scans before sequence {h.sequence} "
                "(the edge was not acquiring)",
            )

    def _flush_and_ack(self) -> None:
        self._last_flush = time.monotonic()
        if not self._writable():
            return
        if self.session.due_split(time.time_ns()):
            if not self._guarded("closing a file", self.session.split):
                return
        elif not self._guarded("flushing", self.session.flush):
            return
        for st in self.streams.values():
            st.durable = st.contiguous
            if st.durable is not None and st.durable >= 0 and st.durable != st.acked_sent:
                self._zsession.put(
                    ack_key(self.site.site, st.node, st.stream), encode_u64(st.durable)
                )
                st.acked_sent = st.durable

    def _event_now(self, level: int, source: str, tag: str, message: str) -> None:
        """A hub event raised on the writer thread itself (lock held): record it directly."""
        now = time.time_ns()
        payload = encode_event(Event(now, "hub", level, source, tag, message))
        self._record_event("", payload, now)

    # --- control --------------------------------------------------------------------------------

    def split(self) -> None:
        with self.lock:
            self._guarded("closing a file", self.session.split)

    def close(self) -> None:
        """Stop receiving, write everything received, close the files. Idempotent."""
        if self._closed:
            return
        self._closed = True
        for sub in self._subs:
            sub.undeclare()
        self._subs = []
        if self._thread.is_alive():
            self._queue.put(_STOP)
            self._thread.join()
        with self.lock:
            self._flush_and_ack()
            self._guarded("closing the session", self.session.close)
        self.events.close()

    def summary(self) -> dict[str, Any]:
        with self.lock:
            return {
                "session": str(self.session.dir),
                "files": [str(p) for p in self.session.files()],
                "abandoned_files": [str(p) for p in self.session.abandoned],
                "streams": {f"{k[0]}/{k[1]}": s.summary() for k, s in sorted(self.streams.items())},
                "malformed": self.malformed,
                "write_errors": self.write_errors,
                "overflow": self.overflow,
                "events_not_recorded": self.events_not_recorded,
                "events": {
                    logging.getLevelName(level).lower(): n
                    for level, n in sorted(self.events.counts.items())
                },
            }
