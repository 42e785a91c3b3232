"""Events an edge spooled: the hub takes them once and in order, and acks only what is written
for good (`fleetdaq.hub.nodes.event_delivery`); the edge keeps them on disk until then
(`fleetdaq.edge.event_publisher`).

The outage itself, with real hub and edge processes, is in tests/test_events_outage.py.
"""

from __future__ import annotations

import logging
from pathlib import Path

from fleetdaq.contract.cdr import decode
from fleetdaq.contract.messages import Event, make_event
from fleetdaq.edge.event_publisher import EventPublisher
from fleetdaq.edge.spool import StreamSpool
from fleetdaq.hub.nodes.event_delivery import EventDelivery, Verdict

EPOCH = 77


class Clock:
    def __init__(self) -> None:
        self.now = 1000.0

    def __call__(self) -> float:
        return self.now


def event(tag: str, node: str = "buoy") -> Event:
    return make_event(1_700_000_000_000_000_000, node, logging.WARNING, "tc", tag, tag)


class Hub:
    """An `EventDelivery` with what it put on the bus."""

    def __init__(self, clock: Clock | None = None) -> None:
        self.delivery = EventDelivery({"buoy"}, stall_s=30.0, clock=clock or Clock())
        self.bus: list[Event] = []

    def offer(self, seq: int, floor: int = 0, epoch: int = EPOCH, tag: str = "") -> Verdict:
        e = event(tag or f"e{seq}")
        return self.delivery.offer("buoy", seq, floor, epoch, e, self.bus.append).verdict

    def write(self) -> None:
        """events.log and the recorder write everything on the bus; the recorder flushes."""
        for e in self.bus:
            self.delivery.logged(e)
            self.delivery.recorded(e)
        self.delivery.flushed()

    def tags(self) -> list[str]:
        return [e.tag for e in self.bus]


def test_events_go_on_the_bus_in_sequence_order_once_whatever_order_they_come_in() -> None:
    hub = Hub()
    # Live events 3 and 4 come while 1 and 2 wait for their replay; then the replay 0..4.
    assert hub.offer(0) is Verdict.ACCEPTED
    assert hub.offer(3) is Verdict.AHEAD
    assert hub.offer(4) is Verdict.AHEAD
    assert [hub.offer(s) for s in range(5)] == [Verdict.DUPLICATE] + [Verdict.ACCEPTED] * 4
    assert [hub.offer(s) for s in range(5)] == [Verdict.DUPLICATE] * 5
    assert hub.tags() == ["e0", "e1", "e2", "e3", "e4"]
    assert hub.delivery.duplicates == 6


def test_a_hub_that_starts_late_takes_the_first_event_at_the_edges_floor() -> None:
    hub = Hub()
    assert hub.offer(12, floor=10) is Verdict.AHEAD
    assert [hub.offer(s, floor=10) for s in (10, 11, 12)] == [Verdict.ACCEPTED] * 3
    assert hub.delivery.lost("buoy") == 0


def test_events_the_edges_full_spool_dropped_are_counted_as_lost_and_the_rest_flows() -> None:
    hub = Hub()
    for s in range(3):
        hub.offer(s)
    d = hub.delivery.offer("buoy", 9, 7, EPOCH, event("e9"), hub.bus.append)
    assert (d.verdict, d.lost) == (Verdict.AHEAD, 4)  # 3..6 are gone; 7 and 8 still come
    assert [hub.offer(s, floor=7) for s in (7, 8, 9)] == [Verdict.ACCEPTED] * 3
    assert hub.delivery.lost("buoy") == 4


def test_a_new_spool_numbering_from_0_is_taken_afresh() -> None:
    hub = Hub()
    for s in range(3):
        hub.offer(s)
    assert hub.offer(0, epoch=EPOCH + 1, tag="again") is Verdict.ACCEPTED
    assert hub.tags()[-1] == "again"


def test_the_ack_is_what_both_events_log_and_the_flushed_recording_have() -> None:
    hub = Hub()
    for s in range(3):
        hub.offer(s)
    synced: list[bool] = []
    hub.delivery.log_sync = lambda: synced.append(True) or True
    for e in hub.bus:
        hub.delivery.logged(e)
    assert hub.delivery.acks() == []  # not recorded yet
    hub.delivery.recorded(hub.bus[0])
    hub.delivery.recorded(hub.bus[1])
    assert hub.delivery.acks() == []  # recorded, not flushed
    hub.delivery.flushed()
    assert hub.delivery.acks() == [("buoy", 1, EPOCH)]
    assert synced == [True]  # events.log fsynced before the ack
    assert hub.delivery.acks() == []  # said once
    hub.write()
    assert hub.delivery.acks() == [("buoy", 2, EPOCH)]


def test_no_ack_while_events_log_cannot_be_fsynced() -> None:
    hub = Hub()
    hub.offer(0)
    hub.delivery.log_sync = lambda: False
    hub.write()
    assert hub.delivery.acks() == []


def test_a_node_another_hub_records_is_deduplicated_but_never_acked() -> None:
    delivery = EventDelivery({"buoy"})
    bus: list[Event] = []
    for s in (0, 0, 1):
        delivery.offer("cell", s, 0, EPOCH, event(f"e{s}", "cell"), bus.append)
    for e in bus:
        delivery.logged(e)
        delivery.recorded(e)
    delivery.flushed()
    assert [e.tag for e in bus] == ["e0", "e1"]
    assert delivery.acks() == []


def test_the_hubs_own_events_are_not_tracked() -> None:
    hub = Hub()
    hub.offer(0)
    own = event("hub_thing")  # same node name, same content: not the object on the bus
    hub.delivery.logged(own)
    hub.delivery.recorded(own)
    hub.delivery.flushed()
    assert hub.delivery.acks() == []


def test_an_event_never_written_is_taken_again_from_its_replay_after_the_stall_time() -> None:
    clock = Clock()
    hub = Hub(clock)
    hub.offer(0)
    hub.offer(1)
    hub.delivery.logged(hub.bus[0])  # event 1 lost for events.log (its queue overflowed)
    for e in hub.bus:
        hub.delivery.recorded(e)
    hub.delivery.flushed()
    assert hub.delivery.acks() == [("buoy", 0, EPOCH)]
    assert hub.offer(1) is Verdict.DUPLICATE  # a replay soon after: still in hand
    clock.now += 31.0
    assert hub.offer(1) is Verdict.ACCEPTED  # nothing moved for 30 s: taken again
    assert hub.delivery.rewinds == 1
    hub.write()
    assert hub.delivery.acks() == [("buoy", 1, EPOCH)]


# --- the edge ------------------------------------------------------------------------------------


def spool(tmp_path: Path) -> StreamSpool:
    return StreamSpool(tmp_path / "events", 10_000_000, 3600.0, 65536)


def test_events_raised_without_a_hub_are_on_disk_with_their_time_after_a_restart(
    tmp_path: Path,
) -> None:
    first = EventPublisher(None, "fleetdaq/s/buoy/events", "buoy", spool=spool(tmp_path))
    first.emit(logging.WARNING, "tc", "thermocouple_fault", "open circuit")
    first.emit(logging.INFO, "agent", "stopped", "stopped")
    first.close()  # the edge stops during the outage

    again = EventPublisher(None, "fleetdaq/s/buoy/events", "buoy", spool=spool(tmp_path))
    assert again.spool is not None
    kept = list(again.spool.read_from(0, 10))
    assert [s for s, _, _ in kept] == [0, 1]
    fault = decode(kept[0][2], Event)
    assert (fault.tag, fault.node) == ("thermocouple_fault", "buoy")
    assert kept[0][1] == fault.time_ns  # the spool keeps the event's own time
    again.emit(logging.INFO, "agent", "started", "started")
    assert again.spool.next_sequence == 3  # numbering goes on after the restart
    again.close()


def test_an_event_ack_for_what_was_never_spooled_is_refused_and_said(tmp_path: Path) -> None:
    events = EventPublisher(None, "fleetdaq/s/buoy/events", "buoy", spool=spool(tmp_path))
    assert events.spool is not None
    events.emit(logging.INFO, "agent", "started", "started")
    events.ack(5, events.spool.epoch)
    events.ack(0, events.spool.epoch + 1)
    assert events.acks_refused == 2
    assert events.spool.acked == -1
    tags = [decode(p, Event).tag for _, _, p in events.spool.read_from(0, 10)]
    assert tags == ["started", "ack_refused", "ack_refused"]
    events.ack(0, events.spool.epoch)
    assert events.spool.acked == 0
    events.close()


def test_events_a_full_spool_drops_unacked_are_counted_and_raised_as_an_event(
    tmp_path: Path,
) -> None:
    small = StreamSpool(tmp_path / "events", 1_000_000, 3600.0, 65536)
    events = EventPublisher(None, "fleetdaq/s/buoy/events", "buoy", spool=small)
    for i in range(4000):  # ~1.3 MB of events, none acked: past the spool's 1 MB
        events.emit(logging.INFO, "tc", "reading", f"reading {i:05d} " + "x" * 200)
    assert events.dropped > 0
    assert small.bytes <= 1_000_000 + 65536
    kept = [decode(p, Event) for _, _, p in small.read_from(0, 10**6)]
    notes = [e for e in kept if e.tag == "events_dropped"]
    assert notes
    assert notes[0].level == logging.ERROR
    assert sum(int(e.get("dropped") or 0) for e in notes) <= events.dropped
    assert [e for e in kept if e.tag == "reading"][-1].message.startswith("reading 03999")
    events.close()


def test_events_written_but_waiting_for_a_flush_are_never_taken_twice() -> None:
    clock = Clock()
    hub = Hub(clock)
    hub.offer(0)
    for e in hub.bus:  # written by both; the recorder's disk is full, so no clean flush
        hub.delivery.logged(e)
        hub.delivery.recorded(e)
    clock.now += 600.0
    assert hub.offer(0) is Verdict.DUPLICATE
    assert hub.delivery.rewinds == 0
    hub.delivery.flushed()
    assert hub.delivery.acks() == [("buoy", 0, EPOCH)]


def test_the_summary_says_per_node_what_was_taken_acked_and_lost() -> None:
    hub = Hub()
    hub.offer(0)
    hub.offer(0)
    hub.delivery.offer("buoy", 5, 5, EPOCH, event("e5"), hub.bus.append)
    hub.write()
    hub.delivery.acks()
    assert hub.delivery.summary() == {
        "nodes": {"buoy": {"accepted": 5, "acked": 5, "lost": 4}},
        "duplicates": 1,
        "rewinds": 0,
    }
