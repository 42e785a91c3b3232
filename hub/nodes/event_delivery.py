"""Events an edge spooled: taken in sequence order, once, and acked when written for good.

An edge sends each event with its sequence in the node's event spool, the spool's floor and
epoch (`fleetdaq.contract.wire.encode_event_mark`). Per node, the hub takes only the next sequence
it expects (the floor, for the first one it sees from a spool): a duplicate (a replay of what it
has) and an event ahead of a hole (a live event while older ones still wait for their replay) are
ignored, and the edge's replay brings them in order. A floor above the next expected sequence means
the edge's full spool dropped what lay between: counted, and raised as an event.

An accepted event goes onto the event bus. events.log and the recorder each say when they have
written it (`logged`, `recorded`); the recorder's flush makes what it wrote durable
(`flushed`), and its ack round (`acks`) fsyncs events.log and acks per node the highest
sequence that is in both for good. Only the hub that records a node acks its events.

If an accepted event never reaches both (a subscriber's queue overflowed, events.log refused
the write), the ack would wait forever: when a replay of an event that one of them has not
written comes and nothing was acked for `stall_s`, the node's accepted sequence goes back to
what both wrote and the replays are taken again (the one that had it may write it twice; an
event is never lost). Events both wrote but the recorder has not flushed (a full disk) just wait for
the flush."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from enum import Enum

from fleetdaq.contract.messages import Event

STALL_S = 30.0


class Verdict(Enum):
    ACCEPTED = "accepted"
    DUPLICATE = "duplicate"
    AHEAD = "ahead"
    """After a hole: the missing ones come first, by replay."""


@dataclass(frozen=True, slots=True)
class Offer:
    """What became of an offered event, and how many the edge's spool had dropped before it."""

    verdict: Verdict
    lost: int = 0


@dataclass(slots=True)
class _NodeEvents:
    epoch: int | None = None
    accepted: int | None = None
    """Highest sequence handed to the bus, every one below it too."""
    logged: int = -1
    recorded: int = -1
    durable: int = -1
    acked: int = -1
    lost: int = 0
    progress: float = 0.0
    """When an ack last moved (or the node's numbering began)."""
    pending: dict[int, tuple[Event, int, int]] = field(default_factory=dict)
    """Bus events not acked yet, by id: (the event, its sequence, its epoch)."""


class EventDelivery:
    """Order, dedup and acks of the events nodes spooled. Thread-safe."""

    def __init__(
        self,
        acking: frozenset[str] | set[str],
        stall_s: float = STALL_S,
        clock: Callable[[], float] = time.monotonic,
        log_sync: Callable[[], bool] | None = None,
    ) -> None:
        """`acking`: the nodes this hub records, and so acks. `clock`: monotonic seconds.
        `log_sync`: the event log's fsync (`fleetdaq.hub.supervision.event_log.EventLog.sync`)."""
        self.acking = frozenset(acking)
        self.stall_s = stall_s
        self._clock = clock
        self.duplicates = 0
        self.rewinds = 0
        self.log_sync = log_sync
        """Makes what events.log wrote durable (its fsync; False if that failed)."""
        self._nodes: dict[str, _NodeEvents] = {}
        self._lock = threading.Lock()

    def offer(
        self,
        node: str,
        seq: int,
        floor: int,
        epoch: int,
        event: Event,
        publish: Callable[[Event], None],
    ) -> Offer:
        """Take `event` (sequence `seq` of `node`'s spool) if it is the next one: `publish`
        is called with it then, under this object's lock, so events go out in order."""
        with self._lock:
            n = self._nodes.get(node)
            if n is None or n.epoch != epoch:  # first seen, or a new (wiped) spool
                n = self._nodes[node] = _NodeEvents(epoch=epoch, progress=self._clock())
            lost = 0
            expected = floor if n.accepted is None else n.accepted + 1
            if floor > expected:  # the edge dropped these unacked (its spool was full)
                lost = floor - expected
                n.lost += lost
                expected = floor
            handled = min(n.logged, n.recorded)
            if (
                seq < expected
                and n.accepted is not None
                and seq > max(n.acked, handled)
                and self._clock() - n.progress > self.stall_s
            ):
                # Accepted long ago and still not written by both (not merely waiting for a
                # flush, as while the hub's disk is full): take the replays again.
                self.rewinds += 1
                n.accepted = max(n.acked, handled, floor - 1)
                n.pending.clear()
                n.progress = self._clock()
                expected = n.accepted + 1
            if seq < expected:
                self.duplicates += 1
                return Offer(Verdict.DUPLICATE, lost)
            if seq > expected:
                n.accepted = expected - 1 if lost else n.accepted
                return Offer(Verdict.AHEAD, lost)
            n.accepted = seq
            if node in self.acking:
                n.pending[id(event)] = (event, seq, epoch)
            publish(event)
            return Offer(Verdict.ACCEPTED, lost)

    def _mark(self, e: Event, what: str) -> None:
        with self._lock:
            n = self._nodes.get(e.node)
            got = n.pending.get(id(e)) if n is not None else None
            if n is None or got is None or got[0] is not e or got[2] != n.epoch:
                return  # not a spooled event (the hub's own, or a peer without a spool)
            seq = got[1]
            if what == "logged":
                n.logged = seq
            else:
                n.recorded = seq

    def logged(self, e: Event) -> None:
        """events.log has written `e` (the event log's thread, in bus order)."""
        self._mark(e, "logged")

    def recorded(self, e: Event) -> None:
        """The recorder has written `e` into its session, or owes nothing for it (recording
        stopped). Durable at the next clean flush."""
        self._mark(e, "recorded")

    def flushed(self) -> None:
        """The recorder's flush succeeded with no write error pending: all it wrote is durable."""
        with self._lock:
            for n in self._nodes.values():
                n.durable = n.recorded

    def acks(self) -> list[tuple[str, int, int]]:
        """(node, sequence, epoch) to ack now: the highest sequence durable in the recording
        and in events.log (fsynced here, only when there is something to ack)."""
        with self._lock:
            logged = {node: n.logged for node, n in self._nodes.items()}
            due = any(
                min(n.durable, logged[node]) > n.acked
                for node, n in self._nodes.items()
                if node in self.acking
            )
        if not due:
            return []
        if self.log_sync is not None and not self.log_sync():
            return []
        out: list[tuple[str, int, int]] = []
        with self._lock:
            for node, n in self._nodes.items():
                upto = min(n.durable, n.logged, logged.get(node, -1))
                if node not in self.acking or upto <= n.acked or n.epoch is None:
                    continue
                n.acked = upto
                n.progress = self._clock()
                n.pending = {k: v for k, v in n.pending.items() if v[1] > upto}
                out.append((node, upto, n.epoch))
        return out

    def lost(self, node: str) -> int:
        """Events of `node` its spool dropped unacked, as seen from the floors it sent."""
        with self._lock:
            n = self._nodes.get(node)
            return n.lost if n is not None else 0

    def summary(self) -> dict[str, object]:
        """Per node: the last sequence taken and acked, events lost; and the duplicates and
        rewinds in all (the hub's ``--summary``)."""
        with self._lock:
            nodes = {
                node: {"accepted": n.accepted, "acked": n.acked, "lost": n.lost}
                for node, n in sorted(self._nodes.items())
            }
        return {"nodes": nodes, "duplicates": self.duplicates, "rewinds": self.rewinds}
