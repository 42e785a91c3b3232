"""The recorder service: data keys -> accounting -> MCAP session.

Zenoh delivers samples on its own threads; the callback only copies the payload and stamps
the hub receive time into a queue. One writer thread validates each batch header (bounds-
checked, no array decode), counts it, and writes the received bytes untouched into the
session. Stopping undeclares the subscriber first, then drains the queue, then closes files,
so every received batch is on disk when `close()` returns.
"""

from __future__ import annotations

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
    data_selector,
    decode_event,
    encode_event,
    events_selector,
    read_header,
    split_data_key,
)
from hub.events import EventLog
from hub.session import EVENTS_TOPIC, RecordingSession, StreamSelector, topic_of

log = logging.getLogger("fleetdaq.recorder")

_STOP = object()
_DATA, _EVENT = 0, 1


@dataclass(slots=True)
class StreamStats:
    """Per-stream accounting from sequence numbers."""

    node: str
    stream: str
    recorded: bool
    rate_hz: float | None = None
    batches: int = 0
    scans: int = 0
    samples: int = 0
    gaps: int = 0
    """Sequence numbers skipped (batches never received)."""
    duplicates: int = 0
    first_sequence: int | None = None
    last_sequence: int | None = None
    last_receive_ns: int = 0
    _recent: deque[tuple[int, int]] = field(default_factory=lambda: deque(maxlen=64))

    def add(self, sequence: int, scans: int, samples: int, recv_ns: int) -> bool:
        """Count a batch; False if it is a duplicate (or older than one already counted)."""
        if self.last_sequence is not None and sequence <= self.last_sequence:
            self.duplicates += 1
            return False
        if self.last_sequence is None:
            self.first_sequence = sequence
        else:
            self.gaps += sequence - self.last_sequence - 1
        self.last_sequence = sequence
        self.batches += 1
        self.scans += scans
        self.samples += samples
        self.last_receive_ns = recv_ns
        self._recent.append((recv_ns, self.scans))
        return True

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
            "duplicates": self.duplicates,
            "first_sequence": self.first_sequence,
            "last_sequence": self.last_sequence,
        }


class Recorder:
    """Subscribes to every data key of the site and records the selected streams."""

    def __init__(self, session: Any, site: SiteConfig, data_dir: Path) -> None:
        self.site = site
        self.cfg = site.hub.recorder
        self.data_dir = data_dir
        self.select = StreamSelector(self.cfg.include, self.cfg.exclude)
        self.streams: dict[tuple[str, str], StreamStats] = {}
        self.malformed = 0
        self.malformed_by_key: dict[str, int] = {}
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

    def start(self) -> None:
        self._thread.start()
        put = self._queue.put

        def on_data(sample: Any) -> None:
            put((_DATA, str(sample.key_expr), sample.payload.to_bytes(), time.time_ns()))

        def on_event(sample: Any) -> None:
            put((_EVENT, str(sample.key_expr), sample.payload.to_bytes(), time.time_ns()))

        site = self.site.site
        self._subs = [
            self._zsession.declare_subscriber(data_selector(site), on_data),
            self._zsession.declare_subscriber(events_selector(site), on_event),
        ]

    def emit(self, level: int, source: str, tag: str, message: str) -> None:
        """Raise a hub event: recorded in the session, logged, shown, alerted on."""
        now = time.time_ns()
        e = Event(now, "hub", level, source, tag, message)
        self._queue.put((_EVENT, "", encode_event(e), now))

    def _writer(self) -> None:
        get = self._queue.get
        while True:
            try:
                item = get(timeout=0.2)
            except queue.Empty:
                with self.lock:
                    if self.session.due_split(time.time_ns()):
                        self.session.split()
                continue
            if item is _STOP:
                return
            kind, key, payload, recv_ns = item
            with self.lock:
                if kind == _DATA:
                    self._record(key, payload, recv_ns)
                else:
                    self._record_event(key, payload, recv_ns)

    def _malformed(self, key: str, err: WireError) -> None:
        self.malformed += 1
        self.malformed_by_key[key] = self.malformed_by_key.get(key, 0) + 1
        if self.malformed_by_key[key] == 1:
            log.warning("malformed payload on %s: %s", key, err)

    def _record_event(self, key: str, payload: bytes, recv_ns: int) -> None:
        try:
            e = decode_event(payload)
        except WireError as err:
            self._malformed(key or "hub/events", err)
            return
        self.session.write(EVENTS_TOPIC, payload, e.time_ns, recv_ns, EVENT_TYPE)
        self.events.add(e)

    def _record(self, key: str, payload: bytes, recv_ns: int) -> None:
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
            if h.sequence != 0:
                self._emit_now(
                    logging.WARNING,
                    "recorder",
                    "late_start",
                    f"{node}/{stream} first seen at sequence {h.sequence}: batches "
                    "before it were not received by this hub",
                )
        if not stats.add(h.sequence, h.scan_count, h.samples, recv_ns):
            return
        if stats.recorded:
            self.session.write(topic_of(node, stream), payload, h.first_sample_time_ns, recv_ns)

    def _emit_now(self, level: int, source: str, tag: str, message: str) -> None:
        """A hub event raised on the writer thread itself (lock held): record it directly."""
        now = time.time_ns()
        e = Event(now, "hub", level, source, tag, message)
        self.session.write(EVENTS_TOPIC, encode_event(e), now, now, EVENT_TYPE)
        self.events.add(e)

    def split(self) -> None:
        with self.lock:
            self.session.split()

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
        self.session.close()
        self.events.close()

    def summary(self) -> dict[str, Any]:
        with self.lock:
            return {
                "session": str(self.session.dir),
                "files": [str(p) for p in self.session.files()],
                "streams": {f"{k[0]}/{k[1]}": s.summary() for k, s in sorted(self.streams.items())},
                "malformed": self.malformed,
                "events": {
                    logging.getLevelName(level).lower(): n
                    for level, n in sorted(self.events.counts.items())
                },
            }
