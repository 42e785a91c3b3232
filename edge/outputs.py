"""The edge's outputs: commands with a reply over Zenoh, the dead-man safe state, interlocks,
readback and the devices' hardware watchdogs.

One queryable on ``fleetdaq/<site>/<node>/out/*`` answers every command with an
`OutputReply` (applied with the readback, or refused with one reason). The Zenoh callback only
parses the key and queues the query (a full queue is refused at once: ``not_allowed``, busy);
one worker thread makes every device call, in order: commands (`fleetdaq.edge.output_commands`), the
end of pulses, safe values (heartbeat lost, interlocks, start and stop) and readback polls
(`fleetdaq.edge.output_upkeep`). Nothing a query carries
can stop the queryable or the worker: every payload is decoded in full (`fleetdaq.contract.cdr`),
checked (`fleetdaq.edge.command_check`), and anything unexpected is refused and counted.

A command id seen before is answered with the reply it got then (the last 1000 ids), so a
retried command is applied at most once; the same id with a different command is refused.
"""

from __future__ import annotations

import logging
import re
import threading
from collections import deque
from dataclasses import dataclass
from typing import TYPE_CHECKING

from fleetdaq.contract.cdr import decode, encode
from fleetdaq.contract.config.node import NodeConfig
from fleetdaq.contract.errors import WireError
from fleetdaq.contract.keys import Kind, SiteKeys
from fleetdaq.contract.messages import HubHeartbeat, OutputCommand, OutputState, RefusalReason
from fleetdaq.contract.schema import NAME
from fleetdaq.edge.command_check import Refusal
from fleetdaq.edge.dead_man import HubWatch
from fleetdaq.edge.drivers.pacing import SYSTEM_TIME, TimeSource
from fleetdaq.edge.drivers.shared import SharedDevices
from fleetdaq.edge.drivers.table import create_output
from fleetdaq.edge.event_publisher import EventPublisher
from fleetdaq.edge.interlocks import Change, Interlocks
from fleetdaq.edge.output_channel import OutputChannel, Pulse
from fleetdaq.edge.output_commands import CommandDesk
from fleetdaq.edge.output_upkeep import Upkeep
from fleetdaq.runtime.threads import NamedThread

if TYPE_CHECKING:
    import zenoh

log = logging.getLogger("fleetdaq.edge")

QUEUE_LIMIT = 64
"""Commands waiting for the worker; past it a command is refused at once (busy)."""
MAX_PAYLOAD = 64 * 1024
_NAME = re.compile(NAME)
_STOP = object()


@dataclass(frozen=True, slots=True)
class _Query:
    query: zenoh.Query
    output: str
    payload: bytes


@dataclass(frozen=True, slots=True)
class _Control:
    kind: str
    """"lost", "back" or "interlock"."""
    missing_s: float = 0.0
    change: Change | None = None
    first: bool = False
    """"back": the first heartbeat since start."""


class OutputService:
    """A node's outputs. `start()` at agent start, `attach(session)` once Zenoh is open,
    `close()` at stop (safe values, devices closed)."""

    def __init__(
        self,
        site: str,
        node: str,
        cfg: NodeConfig,
        events: EventPublisher,
        shared: SharedDevices | None = None,
        clock: TimeSource = SYSTEM_TIME,
        command_age_limit_s: float | None = None,
    ) -> None:
        """`command_age_limit_s`: the site's `command_age_limit_s(node)` (the node's own
        `max_command_age_s` under the site's ceiling); default: the node's own."""
        self.node = node
        self.keys = SiteKeys(site)
        self.control = cfg.control
        self.events = events
        self.clock = clock
        shared = shared if shared is not None else SharedDevices()
        self.channels = {
            name: OutputChannel(name, out, create_output(out, clock, shared), clock)
            for name, out in cfg.outputs.items()
        }
        self.interlocks = Interlocks(cfg.interlocks, self._interlock_changed, events.emit)
        self.hub = HubWatch(
            cfg.control.safe_after_s,
            self._hub_lost,
            self._hub_back,
            monotonic=lambda: clock.monotonic_ns() / 1e9,
        )
        self.safe_state = True
        self.safe_reason = "no hub heartbeat heard yet"
        self.heard = False
        """The hub's heartbeat has been heard since start."""
        self._junk_reported = 0
        self.upkeep = Upkeep(self.channels, events, self.control, clock, self)
        self._cond = threading.Condition()
        self._queries: deque[_Query] = deque()
        self._controls: deque[object] = deque()
        self.desk = CommandDesk(
            node,
            self.channels,
            self.interlocks,
            events,
            clock,
            self,
            command_age_limit_s or self.control.max_command_age_s,
        )
        self._queryable: zenoh.Queryable[None] | None = None
        self._beat_sub: zenoh.Subscriber[None] | None = None
        self._worker = NamedThread(target=self._run, name="outputs", daemon=True)
        self._closing = False
        self.started = threading.Event()
        self.counts = {"queries": 0, "busy": 0, "stray": 0, "replies_failed": 0}

    # -- lifecycle -------------------------------------------------------------------------

    def start(self) -> None:
        """Start the worker (it writes every output's initial value first) and the watch."""
        self._worker.start()
        self.hub.start()

    def attach(self, session: zenoh.Session) -> None:
        """Answer commands and hear the hub's heartbeat on `session`."""
        self._beat_sub = session.declare_subscriber(self.keys.hub("heartbeat"), self._on_beat)
        self._queryable = session.declare_queryable(self.keys.outs_of(self.node), self._on_query)

    def close(self) -> None:
        """Stop answering, put every output to its safe value, close the devices. Idempotent."""
        if self._closing:
            return
        self._closing = True
        if self._queryable is not None:
            self._queryable.undeclare()
        if self._beat_sub is not None:
            self._beat_sub.undeclare()
        self._queryable = self._beat_sub = None
        self.hub.close()
        with self._cond:
            self._controls.append(_STOP)
            self._cond.notify()
        if self._worker.is_alive():
            self._worker.join(10.0)
        with self._cond:
            left = list(self._queries)
            self._queries.clear()
        for job in left:
            job.query.drop()

    def states(self) -> tuple[OutputState, ...]:
        """Every output's state (NodeHealth.outputs)."""
        return tuple(
            ch.state(self.safe_state, self.interlocks.active_for(name))
            for name, ch in self.channels.items()
        )

    # -- Zenoh callbacks (never block, never raise) --------------------------------------------

    def _on_beat(self, sample: zenoh.Sample) -> None:
        try:
            if self.hub.heard(sample.payload.to_bytes()):
                return
            junk = self.hub.junk
            if junk == 1 or junk >= self._junk_reported * 10:
                self._junk_reported = junk
                self.events.emit(
                    logging.WARNING,
                    "outputs",
                    "heartbeat_refused",
                    f"refused a payload on the hub heartbeat key that is not a HubHeartbeat "
                    f"({junk} so far): it does not count as the hub being there",
                    count=junk,
                )
        except Exception:  # a callback must never die; count and go on
            log.exception("hub heartbeat")

    def _on_query(self, query: zenoh.Query) -> None:
        try:
            self._take(query)
        except Exception:
            log.exception("output query")
            self.counts["stray"] += 1
            query.drop()

    def _take(self, query: zenoh.Query) -> None:
        self.counts["queries"] += 1
        key = self.keys.parse(str(query.key_expr))
        if key is None or key.kind is not Kind.OUT or key.node != self.node:
            self.counts["stray"] += 1  # a wildcard query that merely overlaps ours
            query.drop()
            return
        if not _NAME.match(key.name):
            self.counts["stray"] += 1  # out/* or out/**: not one output, nothing to answer
            query.drop()
            return
        payload = query.payload.to_bytes() if query.payload is not None else b""
        if len(payload) > MAX_PAYLOAD or self._closing:
            why = "the edge is stopping" if self._closing else f"payload over {MAX_PAYLOAD} bytes"
            self._reply_now(query, key.name, why)
            return
        with self._cond:
            if len(self._queries) >= QUEUE_LIMIT:
                busy = True
            else:
                busy = False
                self._queries.append(_Query(query, key.name, payload))
                self._cond.notify()
        if busy:
            self.counts["busy"] += 1
            self._reply_now(query, key.name, f"busy: {QUEUE_LIMIT} commands are waiting")

    def _reply_now(self, query: zenoh.Query, output: str, why: str) -> None:
        cmd = _try_decode(query.payload.to_bytes() if query.payload is not None else b"")
        reply = self.desk.reply(cmd, output, Refusal(RefusalReason.NOT_ALLOWED, why))
        self._send(query, output, encode(reply))

    def _send(self, query: zenoh.Query, output: str, payload: bytes) -> None:
        try:
            query.reply(self.keys.out(self.node, output), payload)
        except Exception as err:  # the asker went away
            self.counts["replies_failed"] += 1
            log.debug("reply to %s failed: %s", output, err)
        finally:
            query.drop()

    # -- events from elsewhere (post work, return at once) --------------------------------------

    def _post(self, job: object) -> None:
        with self._cond:
            self._controls.append(job)
            self._cond.notify()

    def _hub_lost(self, missing_s: float) -> None:
        self._post(_Control("lost", missing_s=missing_s))

    def _hub_back(self, beat: HubHeartbeat) -> None:
        first, self.heard = not self.heard, True
        self._post(_Control("back", first=first))

    def _interlock_changed(self, change: Change) -> None:
        if change.tripped and change.interlock.cfg.force_safe:
            self._post(_Control("interlock", change=change))

    # -- the worker ------------------------------------------------------------------------

    def _run(self) -> None:
        try:
            self.upkeep.startup()
        except Exception as err:  # the worker must live on: it answers and keeps things safe
            log.exception("output start-up")
            self.events.emit(
                logging.CRITICAL, "outputs", "output_error", f"output start-up: {err!r}"
            )
        finally:
            self.started.set()
        period = self.control.readback_period_s
        next_poll = self._now() + period
        while True:
            job = self._next_job(next_poll)
            if job is _STOP:
                break
            try:
                if isinstance(job, _Query):
                    self._answer(job)
                elif isinstance(job, _Control):
                    self._apply_control(job)
                self.upkeep.end_pulses()
                if self._now() >= next_poll:
                    self.upkeep.poll()
                    next_poll = max(next_poll + period, self._now())
            except Exception as err:  # keep answering: one failure must not end control
                log.exception("output worker")
                self.events.emit(
                    logging.ERROR, "outputs", "output_error", f"output worker: {err!r}"
                )
        self.upkeep.shutdown()

    def _answer(self, job: _Query) -> None:
        try:
            payload = self.desk.decide(job.output, job.payload)
        except Exception as err:  # a bug must not leave the asker waiting or stop the worker
            log.exception("command on %s", job.output)
            self.events.emit(
                logging.ERROR, "outputs", "output_error", f"command on {job.output}: {err!r}"
            )
            why = Refusal(RefusalReason.NOT_ALLOWED, f"the edge failed on this command: {err!r}")
            payload = encode(self.desk.reply(_try_decode(job.payload), job.output, why))
        self._send(job.query, job.output, payload)

    def _now(self) -> float:
        return self.clock.monotonic_ns() / 1e9

    def _next_job(self, next_poll: float) -> object:
        with self._cond:
            while not self._controls and not self._queries:
                due = min([next_poll, *(p.ends_s for p in self._pulses())])
                wait = due - self._now()
                if wait <= 0:
                    return None
                self._cond.wait(wait)
            if self._controls:
                return self._controls.popleft()
            return self._queries.popleft()

    def _pulses(self) -> list[Pulse]:
        return [ch.pulse for ch in self.channels.values() if ch.pulse is not None]

    def _apply_control(self, job: _Control) -> None:
        if not self.channels:  # nothing to guard: the state is kept, nothing to say
            self.safe_state = job.kind != "back"
            self.safe_reason = "" if job.kind == "back" else "no hub heartbeat"
            return
        if job.kind == "lost":
            self.safe_state = True
            self.safe_reason = f"no hub heartbeat for {job.missing_s:.1f} s"
            done = self.upkeep.to_safe(list(self.channels), disarm=True)
            self.events.emit(
                logging.ERROR,
                "outputs",
                "safe_state",
                f"hub heartbeat missing for {job.missing_s:.1f} s: every output set to its safe "
                "value and disarmed; commands are refused until the hub is back and each output "
                "is armed again",
                missing_s=f"{job.missing_s:.3f}",
                outputs=", ".join(f"{n}={v:g}" for n, v in done.items()),
            )
        elif job.kind == "back":
            first = job.first
            self.safe_state = False
            self.safe_reason = ""
            what = "heard" if first else "back"
            self.events.emit(
                logging.INFO,
                "outputs",
                "safe_state_cleared",
                f"hub heartbeat {what}: commands are accepted (an output must be armed first "
                "when it has arm_required, and every output after a safe state)",
                first=first,
            )
        elif job.kind == "interlock" and job.change is not None:
            lock = job.change.interlock
            if not lock.tripped:
                return  # cleared again before the worker got to it
            names = [n for n in lock.cfg.outputs if n in self.channels]
            disarm = [n for n in names if self.channels[n].cfg.arm_required]
            done = self.upkeep.to_safe(names, disarm=False)
            for name in disarm:
                self.channels[name].armed = False
            self.events.emit(
                logging.ERROR,
                "outputs",
                "forced_safe",
                f"interlock {lock.name} forced {', '.join(names)} safe",
                interlock=lock.name,
                outputs=", ".join(f"{n}={v:g}" for n, v in done.items()),
            )


def _try_decode(payload: bytes) -> OutputCommand | None:
    try:
        return decode(payload, OutputCommand)
    except WireError:
        return None
