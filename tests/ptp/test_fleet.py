"""The hub's fleet view of time, fed by node health and the nodes' clock events."""

from __future__ import annotations

import logging
from dataclasses import replace

from fleetdaq.contract.messages import Event, KeyValue, NodeHealth, TimeSyncStatus
from fleetdaq.hub.nodes.fleet_time import FleetTime
from fleetdaq.ptp.time_status import Check, Level, SyncState, TimeStatus

GM_A, GM_B = "aaaaaa.fffe.000001", "bbbbbb.fffe.000002"


def health(state: SyncState, gm: str, at: int, offset: int = 1_000, level=Level.OK) -> NodeHealth:
    status = TimeStatus(
        source="ptp4l",
        state=state,
        checks=(Check("offset", level, "x"),),
        time_ns=at,
        offset_ns=offset,
        grandmaster_id=gm,
        port_state="SLAVE" if state is SyncState.LOCKED else "LISTENING",
    )
    return NodeHealth(at, "x", "0", 0.0, None, (), TimeSyncStatus.of(status))  # type: ignore[arg-type]


class Emitted(list):
    def __call__(self, level: int, source: str, tag: str, message: str) -> None:
        self.append((level, source, tag, message))

    def tags(self) -> list[str]:
        return [e[2] for e in self]


def test_two_nodes_locked_on_one_grandmaster_make_a_good_fleet():
    events = Emitted()
    fleet = FleetTime(events)
    fleet.update("wec", health(SyncState.LOCKED, GM_A, 10, offset=-3_000))
    fleet.update("shore", health(SyncState.LOCKED, GM_A, 10, offset=12_000))
    view = fleet.view()
    assert view.same_grandmaster
    assert view.grandmasters == (GM_A,)
    assert view.max_abs_offset_ns == 12_000
    assert view.locked == 2
    assert view.verdict == 0
    assert events.tags() == ["node_clock_state", "node_clock_state"]
    assert all(e[0] == logging.INFO and e[1] == "fleet" for e in events)


def test_a_node_losing_lock_is_a_warning_and_a_worse_verdict():
    events = Emitted()
    fleet = FleetTime(events)
    fleet.update("wec", health(SyncState.LOCKED, GM_A, 10))
    fleet.update("wec", health(SyncState.HOLDOVER, GM_A, 20))
    assert events[-1][:3] == (logging.WARNING, "fleet", "node_holdover")
    assert "wec: lost lock" in events[-1][3]
    assert fleet.view().verdict == 1
    fleet.update("wec", health(SyncState.FREERUN, "", 30))
    assert events[-1][:3] == (logging.ERROR, "fleet", "node_freerun")
    assert fleet.view().verdict == 2


def test_a_clock_event_acts_at_once_and_older_health_cannot_undo_it():
    events = Emitted()
    fleet = FleetTime(events)
    fleet.update("wec", health(SyncState.LOCKED, GM_A, 10))
    fleet.on_event(Event(50, "wec", logging.WARNING, "clock", "clock_holdover", "lost lock"))
    assert fleet.view().nodes[0].state is SyncState.HOLDOVER
    assert events.tags()[-1] == "node_holdover"
    fleet.update("wec", health(SyncState.LOCKED, GM_A, 40))  # read before the event, late
    assert fleet.view().nodes[0].state is SyncState.HOLDOVER
    assert events.tags().count("node_locked") == 0
    fleet.update("wec", health(SyncState.HOLDOVER, GM_A, 60))  # same state: no new event
    assert events.tags().count("node_holdover") == 1


def test_events_of_other_sources_and_of_the_hub_are_not_clock_news():
    fleet = FleetTime(Emitted())
    fleet.on_event(Event(5, "wec", logging.WARNING, "t8", "clock_holdover", "not a clock"))
    fleet.on_event(Event(5, "hub", logging.WARNING, "clock", "clock_holdover", "hub"))
    assert fleet.view().nodes == ()


def test_a_grandmaster_change_and_a_split_fleet_are_raised():
    events = Emitted()
    fleet = FleetTime(events, split_grace_s=0)
    fleet.update("wec", health(SyncState.LOCKED, GM_A, 10))
    fleet.update("shore", health(SyncState.LOCKED, GM_A, 10))
    # The hub reacts to the event's structured fields, never to its text.
    fields = (KeyValue("old", GM_A), KeyValue("new", GM_B))
    fleet.on_event(Event(20, "wec", logging.WARNING, "clock", "grandmaster_changed", "?", fields))
    assert "node_grandmaster_changed" in events.tags()
    assert events.tags()[-1] == "grandmasters_differ"
    assert events[-1][0] == logging.ERROR
    view = fleet.view()
    assert not view.same_grandmaster
    assert view.verdict == 2
    fleet.update("shore", health(SyncState.LOCKED, GM_B, 30))
    assert events.tags()[-1] == "grandmasters_agree"
    assert fleet.view().grandmasters == (GM_B,)


def test_a_node_that_leaves_is_dropped_from_the_view():
    fleet = FleetTime(Emitted())
    fleet.update("wec", health(SyncState.LOCKED, GM_A, 10))
    fleet.on_alive("wec", False)
    assert fleet.view().nodes == ()
    assert fleet.view().verdict == 2  # nobody reports: nothing to trust


def test_health_without_a_clock_reading_is_ignored():
    fleet = FleetTime(Emitted())
    nothing = NodeHealth(1, "wec", "0", 0.0, None, (), TimeSyncStatus.unknown())  # type: ignore[arg-type]
    not_yet = NodeHealth(1, "wec", "0", 0.0, None, (), TimeSyncStatus.unknown("ptp4l"))  # type: ignore[arg-type]
    nonsense = replace(health(SyncState.LOCKED, GM_A, 10), clock=replace(TimeSyncStatus.of(
        TimeStatus("ptp4l", SyncState.LOCKED, (), 5)), state="unsynced"))  # fmt: skip
    for h in (nothing, not_yet, nonsense):
        fleet.update("wec", h)
    assert fleet.view().nodes == ()


def test_a_split_only_while_nodes_switch_one_after_the_other_is_not_news():
    events = Emitted()
    now = [100.0]
    fleet = FleetTime(events, split_grace_s=2.0, monotonic=lambda: now[0])
    fleet.update("wec", health(SyncState.LOCKED, GM_A, 10))
    fleet.update("shore", health(SyncState.LOCKED, GM_A, 10))
    fleet.update("wec", health(SyncState.LOCKED, GM_B, 20))
    now[0] += 0.5
    fleet.update("shore", health(SyncState.LOCKED, GM_B, 21))
    assert "grandmasters_differ" not in events.tags()
    assert "grandmasters_agree" not in events.tags()
    fleet.update("wec", health(SyncState.LOCKED, GM_A, 30))
    now[0] += 2.5
    fleet.update("wec", health(SyncState.LOCKED, GM_A, 40))  # still split 2.5 s later
    assert events.tags()[-1] == "grandmasters_differ"


def test_clock_events_of_a_node_not_yet_seen_wait_for_its_health():
    fleet = FleetTime(Emitted())
    fleet.on_event(Event(5, "wec", logging.INFO, "clock", "clock_locked", "locked"))
    assert fleet.view().nodes == ()
