"""The snapshot buffer, like rosbag2's snapshot mode: the last `hub.snapshot.seconds` of every
stream, every event, health report, alarm state and command, held in bounded memory and
written to a file on request (`fleetdaq rec snapshot`, the dashboard, a rule's
``record: snapshot``) or when an alarm of a configured severity is raised. The minute before
an event is kept even when nobody was recording.

What is held is what the recorder takes (checked, new messages), by reference: a batch's
payload is the same bytes object the recorder wrote, never a copy. Batches come from the batch
feed; everything else from the recorder's tap (`offer`, which the composition root hands the
recorder; called on its writer thread: an append). The memory bound (`max_bytes`) is counted
on payload bytes plus a per-message overhead; when it binds before `seconds` does, the view
says how many seconds the buffer really covers.

A snapshot is a folder ``<data_dir>/snapshots/<UTC time>/`` written like a recording session
(one MCAP file and a rosbag2 ``metadata.yaml``), so `fleetdaq.read`, `fleetdaq verify`,
rosbags and ``ros2 bag`` open it like any recording. Files are written on the buffer's own
thread; an alarm-triggered snapshot waits `GRACE_S` so the batches in flight at the alarm are in
it, and alarms closer together than `min_interval_s` share one snapshot. While the recorder is
writing, an alarm takes no snapshot: its seconds are in the recording already.
"""

from __future__ import annotations

import collections
import contextlib
import logging
import shutil
import threading
import time
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from concurrent.futures import TimeoutError as FutureTimeout
from pathlib import Path
from typing import Any

from fleetdaq.contract.config.site import effective_yaml
from fleetdaq.contract.messages import Event
from fleetdaq.contract.wire import plausible_time
from fleetdaq.hub.bus import EventBus
from fleetdaq.hub.config.hub import SnapshotConfig
from fleetdaq.hub.config.site import SiteConfig
from fleetdaq.hub.read_model import SNAPSHOTS, ReadModel
from fleetdaq.hub.recording.batch_feed import BatchFeed, FedBatch
from fleetdaq.hub.recording.session import RecordingSession, topic_of
from fleetdaq.runtime.threads import name_os_thread

log = logging.getLogger("fleetdaq.snapshots")

OVERHEAD_BYTES = 200
"""Counted per held message on top of its payload (the tuple, the deque slot, the ints)."""
GRACE_S = 2.0
"""An alarm-triggered snapshot is written this long after the alarm (batches in flight)."""
WAIT_S = 120.0
"""How long a request waits for its file."""

Held = tuple[int, str, bytes, int, str]
"""(receive time, topic, payload, publish time, message type)."""


class SnapshotBuffer:
    name = "snapshots"

    def __init__(
        self,
        site: SiteConfig,
        data_dir: Path,
        bus: EventBus,
        model: ReadModel,
        feed: BatchFeed,
        recording: Callable[[], bool] = lambda: False,
        cfg: SnapshotConfig | None = None,
        on_trigger: Callable[[dict[str, str]], None] | None = None,
    ) -> None:
        self.cfg = cfg or site.hub.snapshot
        """`hub.snapshot`, or a partition hub's own (`hub.partitions.<name>.snapshot`)."""
        self.recording = recording
        """Whether the recorder is writing: then an alarm's seconds are in the recording and
        it takes no snapshot (a request always does)."""
        self.site = site
        self.root = data_dir / "snapshots"
        self.bus = bus
        self.model = model
        self.window_ns = round(self.cfg.seconds * 1e9)
        self._held: collections.deque[Held] = collections.deque()
        self._bytes = 0
        self._lock = threading.Lock()
        self.evicted_for_memory = 0
        self.written: list[str] = []
        self.failed = 0
        self.merged = 0
        self.skipped_recording = 0
        self._last_alarm_ns = 0
        self._pending_alarm: Future[tuple[bool, str]] | None = None
        self._pool: ThreadPoolExecutor | None = None
        self._consumer = feed.subscribe(self.name, self._on_batch, max_bytes=64 << 20)
        self._events = bus.subscribe(self.name, self._on_event)
        self.on_trigger = on_trigger
        """Told of every request and every alarm that may take a snapshot (the main hub of a
        partitioned site passes them on: each partition hub keeps a buffer of its own slice)."""
        self._recorder_cfg = site.hub.recorder.model_copy(
            update={"file_duration_s": None, "max_file_bytes": 1 << 50}
        )
        self._config_yaml = effective_yaml(site)
        self._publish()

    # --- service ---------------------------------------------------------------------------------

    def start(self) -> None:
        self._pool = ThreadPoolExecutor(
            1, thread_name_prefix="snapshots", initializer=name_os_thread
        )
        self._consumer.start()

    def stop(self) -> None:
        self._consumer.stop()
        pool, self._pool = self._pool, None
        if pool is not None:
            pool.shutdown(wait=True)  # a pending alarm snapshot is still written

    def failure(self) -> str | None:
        if self._pool is not None and not self._consumer.alive:
            return "the snapshot buffer's feed thread died"
        return None

    # --- holding ---------------------------------------------------------------------------------

    def offer(
        self, topic: str, payload: bytes, publish_ns: int, recv_ns: int, msgtype: str
    ) -> None:
        """Hold one message (the recorder's tap; any thread). An append and some evictions."""
        size = len(payload) + OVERHEAD_BYTES
        limit = self.cfg.max_bytes
        with self._lock:
            held = self._held
            held.append((recv_ns, topic, payload, publish_ns, msgtype))
            self._bytes += size
            oldest = recv_ns - self.window_ns
            while held and (held[0][0] < oldest or self._bytes > limit):
                old = held.popleft()
                self._bytes -= len(old[2]) + OVERHEAD_BYTES
                if old[0] >= oldest:
                    self.evicted_for_memory += 1

    def _on_batch(self, b: FedBatch) -> None:
        first = b.header.first_sample_time_ns
        publish = first if plausible_time(first, b.recv_ns) else b.recv_ns
        self.offer(topic_of(b.node, b.stream), b.payload, publish, b.recv_ns, b.header.msgtype)

    def _on_event(self, e: Event) -> None:
        if e.tag != "alarm_raised" or e.get("severity") not in self.cfg.on_alarm:
            return
        alarm = str(e.get("alarm") or "?")
        self._tell({"kind": "alarm", "alarm": alarm})
        self._alarm(alarm)

    def _tell(self, trigger: dict[str, str]) -> None:
        callback = self.on_trigger
        if callback is None:
            return
        try:
            callback(trigger)
        except Exception:  # the partitions miss this one; the main hub's snapshot goes on
            log.exception("snapshots: passing a trigger on failed")

    def remote(self, trigger: dict[str, str]) -> None:
        """A trigger the main hub passed on (a partition hub): a request is written now (not
        waited for; the snapshot event says where), an alarm as this hub's own alarms are
        (not while its recorder writes; merged within `min_interval_s`)."""
        if trigger["kind"] == "alarm":
            self._alarm(trigger["alarm"])
            return
        pool = self._pool
        if pool is not None:
            who, note = trigger["who"], trigger.get("note", "")
            with contextlib.suppress(RuntimeError):  # stopping meanwhile: no new snapshots
                pool.submit(self._write, f"requested by {who} on the main hub", who, note)

    def _alarm(self, alarm: str) -> None:
        if self.recording():
            self.skipped_recording += 1
            return
        pool = self._pool
        if pool is None:
            return
        now = time.time_ns()
        pending = self._pending_alarm
        if now - self._last_alarm_ns < self.cfg.min_interval_s * 1e9 or (
            pending is not None and not pending.done()
        ):
            self.merged += 1
            return
        self._last_alarm_ns = now

        def later() -> tuple[bool, str]:
            time.sleep(GRACE_S)
            return self._write(f"alarm {alarm} raised", f"alarm:{alarm}", "")

        with contextlib.suppress(RuntimeError):  # stopping meanwhile: no new snapshots
            self._pending_alarm = pool.submit(later)

    # --- writing ---------------------------------------------------------------------------------

    def snapshot(self, who: str, note: str = "", tell: bool = True) -> tuple[bool, str]:
        """Write what is held now (a request: waits for the file). (written, path or why not).
        `tell`: pass it on to `on_trigger` (off when the caller asks the partitions itself)."""
        pool = self._pool
        if pool is None:
            return False, "the hub is not running"
        if tell:
            self._tell({"kind": "request", "who": who, "note": note})
        try:
            return pool.submit(self._write, f"requested by {who}", who, note).result(WAIT_S)
        except FutureTimeout:
            return False, f"the snapshot is still being written after {WAIT_S:g} s"

    def _write(self, why: str, who: str, note: str) -> tuple[bool, str]:
        with self._lock:
            held = sorted(self._held, key=lambda m: m[0])
        if not held:
            return False, "nothing held yet"
        now = time.time_ns()
        session: RecordingSession | None = None
        try:
            session = RecordingSession(
                self.root,
                self.site.site,
                list(self.site.nodes),
                self._recorder_cfg,
                self._config_yaml,
                now,
                extra_metadata={
                    "fleetdaq.snapshot": {"why": why, "who": who, "note": note, "time_ns": str(now)}
                },
            )
            for recv_ns, topic, payload, publish_ns, msgtype in held:
                session.write(topic, payload, publish_ns, recv_ns, msgtype)
            session.close()
        except Exception as err:  # a full disk, or text no encoder writes: no snapshot at all
            if not isinstance(err, OSError):
                log.exception("snapshot (%s) failed", why)
            left = _discard(session)
            self.failed += 1
            self.bus.emit(
                logging.ERROR,
                "recorder",
                "snapshot_failed",
                f"snapshot ({why}) could not be written: {err}{left}",
                why=why,
                by=who,
            )
            self._publish()
            return False, f"could not write the snapshot: {err}{left}"
        span_s = (held[-1][0] - held[0][0]) / 1e9
        path = str(session.dir)
        self.written.append(path)
        self.bus.emit(
            logging.INFO,
            "recorder",
            "snapshot",
            f"snapshot of the last {span_s:.0f} s written to {path} ({why})"
            + (f": {note}" if note else ""),
            path=path,
            why=why,
            by=who,
            messages=len(held),
            span_s=round(span_s, 3),
        )
        self._publish()
        return True, path

    # --- view ------------------------------------------------------------------------------------

    def counters(self) -> dict[str, Any]:
        with self._lock:
            held = len(self._held)
            span = (self._held[-1][0] - self._held[0][0]) / 1e9 if held > 1 else 0.0
            nbytes = self._bytes
        return {
            "enabled": True,
            "seconds": self.cfg.seconds,
            "max_bytes": self.cfg.max_bytes,
            "held_messages": held,
            "held_bytes": nbytes,
            "covers_s": round(span, 3),
            "evicted_for_memory": self.evicted_for_memory,
            "written": len(self.written),
            "last": self.written[-1] if self.written else "",
            "failed": self.failed,
            "merged_alarms": self.merged,
            "skipped_recording": self.skipped_recording,
            "on_alarm": list(self.cfg.on_alarm),
        }

    def _publish(self) -> None:
        self.model.put(SNAPSHOTS, self.counters())


def _discard(session: RecordingSession | None) -> str:
    """Remove a snapshot that failed half way (its folder holds nothing else): no ``.active``
    file is left for `fleetdaq verify` to find. What is said when part of it stays."""
    if session is None:
        return ""
    session.abandon()
    shutil.rmtree(session.dir, ignore_errors=True)
    return f"; {session.dir} could not be removed" if session.dir.exists() else ""
