"""An edge's system messages: `fleetdaq_msgs/msg/Event` on ``.../<node>/events``, and its log.

With a spool (the agent's), events are delivered like batches: each is appended to the node's
event spool (`fleetdaq.edge.spool.StreamSpool`, folder ``events``) with the next sequence number
before it is published, and stays there until the hub acks it (``.../ack/events``) as written to
events.log and the recording. A replay thread sends the unacked ones again, oldest first, as soon as
the hub starts to listen (a connection, the hub back after an outage), and again while the oldest is
older than `replay_after_s`; the hub takes them in sequence order and ignores duplicates
(`fleetdaq.hub.nodes.event_delivery`). So an event raised during a hub outage, or before an edge
restart during one, reaches the hub with its original time. What a full spool drops is counted and
raised as an ``events_dropped`` event.

Without a spool (tools, tests) events wait in a bounded memory queue until the hub listens.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque

import zenoh

from fleetdaq.contract.cdr import encode
from fleetdaq.contract.messages import make_event
from fleetdaq.contract.wire import encode_event_mark
from fleetdaq.edge.spool import StreamSpool
from fleetdaq.runtime.threads import NamedThread
from fleetdaq.runtime.zenoh_session import has_subscribers

log = logging.getLogger("fleetdaq.edge")

LISTEN_POLL_S = 0.2
"""How often the replay thread looks whether the hub listens (its subscription matches)."""
REPLAY_BATCH = 500
"""Events re-sent in one replay pass: below the hub's per-node burst (`fleetdaq.hub.nodes.watch`),
so a backlog is never taken for a flood; the next pass follows the ack."""


class EventPublisher:
    """Publishes a node's events and logs them; with `spool`, keeps each until the hub acks it.

    Without a spool, until the hub's subscription reaches this publisher events wait in a
    bounded queue and go out in order once it matches; any dropped from a full queue are
    counted and reported in an event of their own.
    """

    def __init__(
        self,
        session: zenoh.Session | None,
        key: str,
        node: str,
        backlog: int = 1000,
        spool: StreamSpool | None = None,
        replay_after_s: float = 3.0,
    ) -> None:
        self._key = key
        self._pub: zenoh.Publisher | None = None
        self._node = node
        self._pending: deque[bytes] = deque()
        self._backlog = backlog
        self.dropped = 0
        """Events lost: from the memory queue, or dropped unacked by a full spool."""
        self.spool = spool
        self.replay_after_s = replay_after_s
        self.replayed = 0
        self.acks_refused = 0
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._replayer = NamedThread(target=self._replay, name="replay-events", daemon=True)
        if session is not None:
            self.attach(session)

    def attach(self, session: zenoh.Session) -> None:
        """Start publishing on `session` (events raised before are in the spool or the queue)."""
        self._pub = session.declare_publisher(
            self._key,
            # With a spool nothing waits on a congested link (an acquisition thread may be
            # the one raising the event): what a put drops is replayed from the spool.
            congestion_control=(
                zenoh.CongestionControl.DROP
                if self.spool is not None
                else zenoh.CongestionControl.BLOCK
            ),
            reliability=zenoh.Reliability.RELIABLE,
        )
        if self.spool is not None and not self._replayer.is_alive():
            self._replayer.start()
        self.flush()

    def emit(self, level: int, source: str, tag: str, message: str, /, **fields: object) -> None:
        """Raise an event; `fields` are what code reading it may react to (old/new values...)."""
        log.log(level, "%s [%s]: %s", source, tag, message)
        event = make_event(time.time_ns(), self._node, level, source, tag, message, **fields)
        payload = encode(event)
        if self.spool is not None:
            self._spool_and_send(event.time_ns, payload)
            return
        with self._lock:
            if len(self._pending) >= self._backlog:
                self._pending.popleft()
                self.dropped += 1
            self._pending.append(payload)
        self.flush()

    def _spool_and_send(self, time_ns: int, payload: bytes) -> None:
        spool = self.spool
        assert spool is not None
        with self._lock:  # one order: the spool's, which is the order the hub takes them in
            seq = spool.next_sequence
            dropped = spool.append(seq, time_ns, payload)
            self._put(seq, payload)
        for d in dropped:
            self.dropped += d.batches
            self.emit(
                logging.ERROR,
                "agent",
                "events_dropped",
                f"{d.reason}: dropped {d.batches} unacked event(s), sequences "
                f"{d.first_seq}..{d.last_seq}; the hub had not acked them",
                first=d.first_seq,
                last=d.last_seq,
                dropped=d.batches,
            )

    def _put(self, seq: int, payload: bytes) -> bool:
        """Publish one spooled event if the hub listens; False otherwise (it waits in the spool)."""
        pub, spool = self._pub, self.spool
        if pub is None or spool is None or not has_subscribers(pub):
            return False
        pub.put(payload, attachment=encode_event_mark(seq, spool.floor, spool.epoch))
        return True

    def flush(self) -> None:
        """Publish what waits in the memory queue, if the hub listens (the spool replays)."""
        pub = self._pub
        if self.spool is not None or pub is None or not has_subscribers(pub):
            return
        with self._lock:
            pending, self._pending = self._pending, deque()
            dropped, self.dropped = self.dropped, 0
        if dropped:
            note = make_event(
                time.time_ns(),
                self._node,
                logging.WARNING,
                "agent",
                "events_dropped",
                f"{dropped} event(s) dropped while no hub was listening",
                dropped=dropped,
            )
            pending.appendleft(encode(note))
        for payload in pending:
            pub.put(payload)

    # --- acks and replay -------------------------------------------------------------------------

    def ack(self, seq: int, epoch: int | None) -> None:
        """The hub has every event up to `seq` in events.log and the recording: free them.
        An ack for events not spooled yet, or of another spool's numbering, is refused and
        raised as an event (it must not delete what the hub cannot have)."""
        spool = self.spool
        if spool is None or spool.ack(seq, epoch):
            return
        self.acks_refused += 1
        self.emit(
            logging.ERROR,
            "agent",
            "ack_refused",
            f"ignored an event ack for sequence {seq}: only {spool.next_sequence - 1} was "
            "spooled, or it is for another spool's numbering (a confused or forged ack must not "
            "delete unsent events)",
            sequence=seq,
            sent=spool.next_sequence - 1,
        )

    def _hub_listens(self) -> bool:
        pub = self._pub
        return pub is not None and has_subscribers(pub)

    def _replay(self) -> None:
        listened, last_pass = False, 0.0
        while not self._stop.wait(LISTEN_POLL_S):
            try:
                if not self._hub_listens():
                    listened = False
                    continue
                now = time.monotonic()
                if not listened or now - last_pass >= self.replay_after_s:
                    # The hub has just come: what waited for it goes now, whatever its age.
                    self._replay_pass(every_unacked=not listened)
                    last_pass = now
                listened = True
            except Exception:  # a failed pass is tried again; the events stay in the spool
                if self._stop.is_set():
                    return
                log.exception("replaying events from the spool failed; trying again")

    def _replay_pass(self, every_unacked: bool) -> None:
        spool = self.spool
        assert spool is not None
        oldest = spool.oldest_unacked_time_ns()
        if oldest is None:
            return
        if not every_unacked and time.time_ns() - oldest < self.replay_after_s * 1e9:
            return  # the newest went out live and their ack is still due
        first = spool.acked + 1
        until = min(spool.next_sequence - 1, first + REPLAY_BATCH - 1)
        for seq, _, payload in spool.read_from(first, until):
            if self._stop.is_set():
                return
            with self._lock:  # never between a live event's append and its put
                if not self._put(seq, payload):
                    return
            self.replayed += 1

    def sync(self) -> None:
        """fsync the event spool (the agent's spool-sync thread): power loss loses nothing
        older than the fsync interval."""
        if self.spool is not None:
            self.spool.sync()

    def close(self) -> None:
        """Publish what waits (without a spool), stop replaying, close the spool. Idempotent."""
        self.flush()
        self._stop.set()
        if self._replayer.is_alive():
            self._replayer.join(5.0)
        if self._pub is not None:
            self._pub.undeclare()
            self._pub = None
        if self.spool is not None:
            self.spool.close()
