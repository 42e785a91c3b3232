"""The supervisor service: evaluates every alarm, keeps their ISA-18.2 states, and tells.

- Channel alarms are evaluated on the batches themselves (`fleetdaq.hub.recording.batch_feed`), in
  numpy, in acquisition time, on this service's own thread (never the recorder's).
- Stream, node and hub alarms are evaluated twice a second from the read model (stream
  accounting, typed node health, the recorder, the notifier), with their delays in wall time.
- Every transition is journaled (`fleetdaq.hub.supervision.alarms.journal`), recorded in the MCAP as
  an `AlarmState` on ``/alarms``, raised as an event (so it is in events.log), put in the read model
  and handed to the notifier. Restarting the hub restores every alarm from the journal.
- Operators ack, shelve, unshelve, disable and enable alarms through a request with a reply on
  ``fleetdaq/<site>/hub/alarms`` (`fleetdaq.hub.supervision.alarms.requests`).
"""

from __future__ import annotations

import dataclasses
import logging
import math
import threading
import time
from collections import deque
from collections.abc import Callable, Sequence
from pathlib import Path

from fleetdaq.contract.messages import ALARM_STATE_TYPE
from fleetdaq.contract.requester_text import text_problem
from fleetdaq.contract.wire import batch_values
from fleetdaq.hub.bus import EventBus
from fleetdaq.hub.config.site import SiteConfig
from fleetdaq.hub.read_model import (
    ALARM_TOTALS,
    ALARMS,
    AlarmView,
    HubView,
    JsonObject,
    ReadModel,
    number,
)
from fleetdaq.hub.recording.batch_feed import BatchFeed, FedBatch
from fleetdaq.hub.recording.recorder import Recorder
from fleetdaq.hub.requests import MAX_HOST_CHARS, MAX_NOTE_CHARS, MAX_USER_CHARS
from fleetdaq.hub.supervision.alarms.conditions import Delayed, Flip, SampleCondition, StreamScreen
from fleetdaq.hub.supervision.alarms.definitions import AlarmDef, build_definitions
from fleetdaq.hub.supervision.alarms.journal import Journal, as_float, as_int
from fleetdaq.hub.supervision.alarms.kernels import batch_extremes, settle, warm_up
from fleetdaq.hub.supervision.alarms.machines import (
    HEALTH_FRESH_NS,
    machine,
    node_check,
    partition_check,
)
from fleetdaq.hub.supervision.alarms.states import IN_ALARM, AlarmStatus, Change, State
from fleetdaq.hub.supervision.alarms.told import Told, put_back, told
from fleetdaq.hub.supervision.notification import Notifier
from fleetdaq.runtime.threads import NamedThread

log = logging.getLogger("fleetdaq.alarms")

ALARMS_TOPIC = "/alarms"
TICK_S = 0.5


class Alarm:
    """One alarm at run time: its definition, state and condition."""

    def __init__(self, d: AlarmDef) -> None:
        self.d = d
        self.status = AlarmStatus(latch=d.latch)
        on = round((d.delay_s + (d.threshold if d.check in _THRESHOLD_IS_DELAY else 0)) * 1e9)
        off = round(d.off_delay_s * 1e9)
        self.samples: SampleCondition | None = None
        self.delayed = Delayed(on, off)
        if d.kind == "channel":
            self.samples = SampleCondition(d.check, d.threshold, d.deadband, on, off)
        # stream gaps: what was already lost when last looked at, and how long holes wait
        self.lost_seen: int | None = None
        self.missing = Delayed(round(d.threshold * 1e9), 0)
        self.window: deque[tuple[int, int, int]] = deque()

    def view(self) -> AlarmView:
        d, s = self.d, self.status
        return AlarmView(
            d.name, d.kind, d.node, d.stream, d.channel, d.severity, s.state.value, s.active,
            s.since_ns, s.value, d.unit, s.count, d.condition, d.description, s.shelved_until_ns,
        )  # fmt: skip


_THRESHOLD_IS_DELAY = {"down", "clock_unlocked", "partition_down"}
"""Checks whose threshold is how long the raw condition must hold."""


class Supervisor:
    name = "supervisor"

    def __init__(
        self,
        site: SiteConfig,
        bus: EventBus,
        model: ReadModel,
        recorder: Recorder,
        feed: BatchFeed,
        journal_path: Path,
        notifier: Notifier | None = None,
        snapshot: Callable[[], HubView] | None = None,
        also_from: Sequence[BatchFeed] = (),
    ) -> None:
        """`also_from`: feeds of batches the recorder never takes (a partition's watched
        streams: `fleetdaq.hub.partitions.live`), evaluated on the same thread."""
        self.site = site
        self.bus = bus
        self.model = model
        self.recorder = recorder
        self.notifier = notifier
        self.snapshot = snapshot
        """The hub's read model (the runtime's `snapshot`); None: this model's own."""
        self.alarms = {d.name: Alarm(d) for d in build_definitions(site)}
        self.by_stream: dict[tuple[str, str], list[tuple[int, Alarm]]] = {}
        for a in self.alarms.values():
            if a.d.kind == "channel":
                names = [c.name for c in site.nodes[a.d.node].streams[a.d.stream].channels]
                col = names.index(a.d.channel)
                self.by_stream.setdefault((a.d.node, a.d.stream), []).append((col, a))
        self.screens: dict[tuple[str, str], tuple[StreamScreen, dict[int, list[Alarm]]]] = {}
        for (node, stream), pairs in self.by_stream.items():
            by_col: dict[int, list[Alarm]] = {}
            for col, a in pairs:
                by_col.setdefault(col, []).append(a)
            conditions = {c: [a.samples for a in al if a.samples] for c, al in by_col.items()}
            width = len(site.nodes[node].streams[stream].channels)
            self.screens[(node, stream)] = (StreamScreen(width, conditions), by_col)
        self.journal = Journal(journal_path)
        self.lock = threading.Lock()
        self.totals = {"raised": 0, "cleared": 0, "acked": 0, "shelved": 0, "disabled": 0}
        self.batches_seen = 0
        self.late_skipped = 0
        self.missed_batches = 0
        self.started_ns = 0
        self._consumer = feed.subscribe(self.name, self._on_batch, max_bytes=128 << 20)
        for other in also_from:
            other.attach(self._consumer)
        self._stop = threading.Event()
        self._thread = NamedThread(target=self._run, name="supervisor", daemon=True)
        self._died: str | None = None
        self._journal_errors_told = 0
        self._journal_told_at = 0.0

    # --- lifecycle ----------------------------------------------------------------------------

    def start(self) -> None:
        self.started_ns = time.time_ns()
        if self.screens:  # value alarms: their one-pass loop compiled meanwhile (numpy until then)
            warm_up(self.journal.path.parent / "cache")
        self._restore(self.journal.load())
        self.journal.open()
        self._publish()
        self._consumer.start()
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(5.0)
        self._consumer.stop()
        settle(30.0)  # a compile still running is not left inside LLVM at exit
        self.journal.close()
        self._publish()

    def failure(self) -> str | None:
        if self._died:
            return self._died
        if self.started_ns and not self._stop.is_set() and not self._consumer.alive:
            return "the supervisor's batch thread died"
        return None

    def _restore(self, last: dict[str, JsonObject]) -> None:
        restored = 0
        for name, rec in last.items():
            a = self.alarms.get(name)
            if a is None:
                continue  # an alarm the site file no longer defines
            try:
                s = a.status
                s.state = State(str(rec["state"]))
                s.active = bool(rec["active"])
                s.since_ns = as_int(rec["since_ns"])
                s.count = as_int(rec["count"])
                s.shelved_until_ns = as_int(rec.get("shelved_until_ns", 0))
                value = rec.get("value")
                s.value = as_float(value) if value is not None else math.nan
            except (KeyError, TypeError, ValueError):
                log.warning("alarm journal: cannot restore %s from %r", name, rec)
                continue
            # The condition is unknown until it is evaluated again: a restored active alarm
            # stays in its state (acked stays acked) until the live data says otherwise.
            a.delayed.active = a.status.active
            if a.samples is not None:
                a.samples.active = a.samples.raw = a.status.active
            restored += 1
        for screen, by_col in self.screens.values():
            for col in by_col:
                screen.refresh(col)
        if restored:
            states = [a.status.state for a in self.alarms.values()]
            in_alarm = sum(s in IN_ALARM for s in states)
            shelved = sum(s is State.SHELVED for s in states)
            self.bus.emit(
                logging.INFO,
                "alarms",
                "restored",
                f"restored {restored} alarm state(s) from the journal ({in_alarm} in alarm, "
                f"{shelved} shelved)",
                restored=restored,
            )

    # --- channel alarms: on the batches ----------------------------------------------------------

    def _on_batch(self, b: FedBatch) -> None:
        self.batches_seen += 1
        self.missed_batches += b.missed_before
        if b.late:
            self.late_skipped += 1  # history filled in by a replay: alarms are about now
            return
        screened = self.screens.get((b.node, b.stream))
        if screened is None:
            return
        screen, by_col = screened
        h = b.header
        # The data array is the payload's tail (the recorder checked every length): a view.
        # A channel is copied out (contiguous) only when one of its limits may change.
        values = batch_values(h, b.payload)
        lo_a, hi_a, nan_a = batch_extremes(values)
        busy = screen.busy(lo_a, hi_a, nan_a)
        if not busy:
            return  # every sample inside every band: nothing can change
        period = h.sample_period_ns
        for col in busy:
            lo, hi, nan = float(lo_a[col]), float(hi_a[col]), bool(nan_a[col])
            column = values[:, col]  # a view: the compiled loop reads it in place
            try:
                for a in by_col[col]:
                    cond = a.samples
                    assert cond is not None
                    if not cond.could_change(lo, hi, nan):
                        continue
                    flips = cond.evaluate(column, h.first_sample_time_ns, period)
                    if flips:
                        with self.lock:
                            for flip in flips:
                                self._flip(a, flip)
            finally:
                # Even when a transition failed (its error goes to the feed's log): a band
                # left from before a condition changed would screen out the batches that
                # change it back.
                screen.refresh(col)

    # --- stream, node and hub alarms: from the read model ---------------------------------------

    def _run(self) -> None:
        try:
            while not self._stop.wait(TICK_S):
                view = self.snapshot() if self.snapshot else self.model.snapshot(time.time_ns())
                now = time.time_ns()
                with self.lock:
                    for a in self.alarms.values():
                        if a.d.kind != "channel":
                            raw, value = self._check(a, view, now)
                            flip = a.delayed.update(raw, now, value)
                            if flip is not None:
                                self._flip(a, flip)
                        change = a.status.expire(now)
                        if change is not None:
                            self._apply(a, change)
                self.journal.sync()
                self._journal_health()
                self._publish()
        except Exception as err:
            self._died = f"the supervisor's thread died: {err!r}"
            log.critical("%s", self._died, exc_info=True)
            self.bus.emit(logging.CRITICAL, "alarms", "supervisor_died", self._died)

    def _journal_health(self) -> None:
        """The journal cannot be written (a full disk): say so, at most once a minute."""
        errors = self.journal.write_errors
        if errors > self._journal_errors_told:
            now = time.monotonic()
            if now - self._journal_told_at >= 60.0:
                self._journal_told_at = now
                self._journal_errors_told = errors
                self.bus.emit(
                    logging.ERROR,
                    "alarms",
                    "journal_error",
                    f"the alarm journal cannot be written ({self.journal.last_error}; "
                    f"{errors} failed write(s)): alarms work on, but a restart would not "
                    "remember what changed meanwhile",
                    errors=errors,
                )

    def _check(self, a: Alarm, view: HubView, now: int) -> tuple[bool, float]:
        d = a.d
        since_start_s = (now - self.started_ns) / 1e9
        if d.kind == "stream":
            s = view.stream(d.node, d.stream)
            if s is None:
                return False, math.nan
            if d.check == "stale":
                last = s.last_receive_ns or self.started_ns
                age = (now - last) / 1e9
                return age > d.threshold, age
            if d.check == "rate":
                if since_start_s < 10 or not s.rate_hz:
                    return False, s.scan_rate
                return s.scan_rate < d.threshold * s.rate_hz, s.scan_rate
            if d.check == "gaps":
                grew = a.lost_seen is not None and s.lost > a.lost_seen
                a.lost_seen = s.lost
                waiting = a.missing.update(s.missing > 0, now)
                holes = a.missing.active if waiting is None else waiting.active
                return grew or holes, float(s.lost + s.missing)
            node = view.node(d.node)
            health = node.health if node is not None else None
            st = health.stream(d.stream) if health is not None else None
            if st is None or health is None or now - health.time_ns > HEALTH_FRESH_NS:
                return False, math.nan
            if d.check == "invalid":
                window = a.window
                window.append((health.time_ns, st.invalid_samples, st.scans))
                horizon = health.time_ns - round(float(d.options.get("window_s", 10.0)) * 1e9)  # type: ignore[arg-type]
                while len(window) > 2 and window[1][0] <= horizon:
                    window.popleft()
                _, inv0, scans0 = window[0]
                channels = len(self.site.nodes[d.node].streams[d.stream].channels)
                samples = (st.scans - scans0) * channels
                share = (st.invalid_samples - inv0) / samples if samples > 0 else 0.0
                return share > d.threshold, share
            if d.check == "late_polls":
                window = a.window
                window.append((health.time_ns, st.late_polls, st.scans))
                horizon = health.time_ns - round(float(d.options.get("window_s", 10.0)) * 1e9)  # type: ignore[arg-type]
                while len(window) > 2 and window[1][0] <= horizon:
                    window.popleft()
                late = float(st.late_polls - window[0][1])
                return late >= d.threshold, late
            if d.check == "backlog":
                raw_value = st.device_value(str(d.options.get("key", "")))
                try:
                    backlog = float(raw_value) if raw_value is not None else math.nan
                except ValueError:
                    backlog = math.nan
                return backlog > d.threshold, backlog
            return False, math.nan
        if d.kind == "node":
            return node_check(d, machine(view, d.node), now)
        if d.check.startswith("partition_"):  # a partition hub, as the main hub sees it
            return partition_check(d, view.partitions.get(d.node.removeprefix("hub/")) or {})
        # the hub
        rec = view.recorder
        if d.check == "hub_disk":
            hh = view.hub_health
            disk = hh.host.disk("data") if hh is not None else None
            if disk is None or not disk.total_bytes:
                return False, math.nan
            free = 100.0 * disk.free_bytes / disk.total_bytes
            return free < d.threshold, free
        if d.check in ("recorder", "write_errors"):
            return rec.state in ("disk_error", "failed"), float(rec.write_errors)
        if d.check == "recorder_stopped":
            return rec.state == "stopped", math.nan
        if d.check == "notifications_failing":
            notifier = view.notifier
            age = float(notifier.get("oldest_queued_age_s", 0.0)) if notifier else 0.0
            return age > d.threshold, age
        if d.check == "certificate_expiring":
            ends = [
                end
                for c in view.certificates.values()
                if (end := number(c, "not_after_ns")) is not None
            ]
            if not ends:
                return False, math.nan
            days = (min(ends) - now) / 86_400e9
            return days < d.threshold, days
        return False, math.nan

    # --- transitions -------------------------------------------------------------------------

    def _flip(self, a: Alarm, flip: Flip) -> None:
        change = a.status.condition(flip.active, flip.time_ns, flip.value)
        if change is not None:
            self._apply(a, change)

    def _apply(self, a: Alarm, change: Change) -> None:
        """Journal, record, raise, publish, notify one transition the hub made (lock held)."""
        self._tell(change, told(a.d, a.status, change), sync=False)

    def _tell(self, change: Change, t: Told, sync: bool) -> bool:
        """Write `t` everywhere, the journal first; False, with nothing else written, when
        the journal refused it (a full disk) and `sync` (an operator's action, to be undone).
        The hub's own transitions go on in memory then (the journal counts the failure)."""
        journaled = self.journal.append(t.journal, sync=sync)
        if sync and not journaled:
            return False
        if change.transition in self.totals:
            self.totals[change.transition] += 1
        now = time.time_ns()
        self.recorder.record(ALARMS_TOPIC, t.record, change.time_ns, now, ALARM_STATE_TYPE)
        self.bus.emit(t.level, "alarms", t.tag, t.message, **t.fields)
        if self.notifier is not None:
            self.notifier.submit(t.notification)
        return True

    def _publish(self) -> None:
        with self.lock:
            views = tuple(a.view() for a in self.alarms.values())
            totals = dict(self.totals)
        self.model.put(ALARMS, views)
        self.model.put(ALARM_TOTALS, totals)

    # --- operators (fleetdaq.hub.supervision.alarms.requests calls these) --------------------

    def operate(
        self,
        action: str,
        names: list[str],
        user: str,
        host: str,
        note: str = "",
        for_s: float = 0.0,
    ) -> list[tuple[str, bool, str]]:
        """Apply an operator action to each named alarm: (name, done, new state or reason).

        Each is done whole or not at all: its state, the journal (fsynced), the `/alarms`
        record, the event (events.log) and the notification, or none of them and the reason.
        `user`, `host` and `note` follow the rule for requester text
        (`fleetdaq.contract.requester_text`);
        text that breaks it refuses the action for every name before anything changes.
        """
        from fleetdaq.hub.supervision.alarms.states import Refused

        for what, value, limit in (
            ("user", user, MAX_USER_CHARS),
            ("host", host, MAX_HOST_CHARS),
            ("note", note, MAX_NOTE_CHARS),
        ):
            problem = text_problem(value, limit)
            if problem is not None:
                return [(name, False, f"{what} {problem}") for name in names]
        out: list[tuple[str, bool, str]] = []
        now = time.time_ns()
        with self.lock:
            for name in names:
                a = self.alarms.get(name)
                if a is None:
                    out.append((name, False, "no alarm of that name"))
                    continue
                s = a.status
                before = dataclasses.replace(s)
                try:
                    if action == "ack":
                        change = s.ack(now, user, host, note)
                    elif action == "shelve":
                        change = s.shelve(now, now + round(for_s * 1e9), user, host, note)
                    elif action == "unshelve":
                        change = s.unshelve(now, user, host, note)
                    elif action == "disable":
                        change = s.disable(now, user, host, note)
                    elif action == "enable":
                        change = s.enable(now, user, host, note)
                    else:
                        raise Refused(f"unknown action {action!r}")
                except Refused as why:
                    out.append((name, False, str(why)))
                    continue
                try:
                    t = told(a.d, s, change)
                except Exception as err:  # nothing was written: the action is undone
                    put_back(s, before)
                    log.exception("alarm %s: %s cannot be recorded", name, action)
                    out.append((name, False, f"it cannot be recorded ({err}); nothing changed"))
                    continue
                if not self._tell(change, t, sync=True):
                    put_back(s, before)
                    journal = f"the alarm journal cannot be written ({self.journal.last_error})"
                    out.append((name, False, f"{journal}; nothing changed"))
                    continue
                out.append((name, True, s.state.value))
        self._publish()
        return out
