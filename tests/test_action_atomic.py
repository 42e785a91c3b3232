"""An operator's action is done whole or not at all, even past the request's checks: an alarm
action the journal cannot take (a full disk) or whose text cannot be recorded is undone, a
snapshot that fails half way leaves no ``.active`` file, and text no encoder writes (a lone
UTF-16 surrogate) never stops a line of events.log or a hub event half way."""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from fleetdaq.contract.cdr import encode
from fleetdaq.contract.messages import EVENT_TYPE, Event, make_event
from fleetdaq.hub.bus import EventBus
from fleetdaq.hub.config.load import parse_config
from fleetdaq.hub.read_model import ReadModel
from fleetdaq.hub.recording.batch_feed import BatchFeed
from fleetdaq.hub.recording.snapshots import SnapshotBuffer
from fleetdaq.hub.runtime import HubRuntime
from fleetdaq.hub.supervision.alarms.definitions import build_definitions
from fleetdaq.hub.supervision.alarms.journal import Journal
from fleetdaq.hub.supervision.alarms.states import AlarmStatus, Change, State
from fleetdaq.hub.supervision.alarms.told import told
from fleetdaq.hub.supervision.event_log import EventLog
from tests.procs import free_port, wait_until

SITE = """\
site: atomic
hub:
  listen: [tcp/127.0.0.1:{port}]
  dashboard: {{enabled: false}}
  universal_alarms: {{node_down: false, stream_stale: false, stream_gaps: false,
                      clock_unsynced: false}}
nodes:
  wec:
    streams:
      t8: {{driver: wave_sim, rate_hz: 100, channels: [{{name: heave, unit: m}}]}}
alarms:
  hub_memory: {{node: hub, memory_percent_above: 0.01, severity: info}}
"""
ALARM = "hub_memory"


@pytest.fixture
def hub(tmp_path: Path) -> Iterator[HubRuntime]:
    site = parse_config(SITE.format(port=free_port()), "<test>")
    runtime = HubRuntime(site, tmp_path / "data")
    try:
        runtime.start()
        sup = runtime.supervisor
        wait_until(
            lambda: sup.alarms[ALARM].status.state is State.ACTIVE_UNACKED, 30, f"{ALARM} raised"
        )
        yield runtime
    finally:
        runtime.close()


def logged_before_a_marker(runtime: HubRuntime) -> list[Event]:
    """Every event events.log took up to now (a marker raised now has reached it)."""
    runtime.bus.emit(logging.INFO, "test", "marker", "marker")
    recent = runtime.event_log.recent
    wait_until(lambda: any(e.tag == "marker" for e in recent), 10, "the marker in events.log")
    return list(recent)


def test_an_alarm_action_the_journal_cannot_take_is_undone_and_says_why(hub: HubRuntime):
    sup = hub.supervisor
    journal = sup.journal
    with journal._lock:  # the disk fills up under the open journal
        journal._fh.close()
        journal._fh = open("/dev/full", "a", encoding="utf-8")  # noqa: SIM115
    results = sup.operate("ack", [ALARM], "ann", "desk", "layer 12 looked fine")
    assert results == [
        (
            ALARM,
            False,
            "the alarm journal cannot be written ([Errno 28] No space left on device); "
            "nothing changed",
        )
    ]
    assert sup.alarms[ALARM].status.state is State.ACTIVE_UNACKED
    assert sup.totals["acked"] == 0
    assert not [e for e in logged_before_a_marker(hub) if e.tag == "alarm_acked"]


def test_an_alarm_action_whose_note_cannot_be_recorded_changes_nothing(hub: HubRuntime):
    sup = hub.supervisor
    journal = (hub.data_dir / "alarms.journal").read_bytes()
    status = dataclasses.replace(sup.alarms[ALARM].status)
    for action in ("ack", "shelve", "disable"):
        results = sup.operate(action, [ALARM], "ann", "desk", "layer \ud800", for_s=60.0)
        assert results == [
            (ALARM, False, "note holds a lone UTF-16 surrogate (U+D800) at character 6")
        ]
    assert sup.alarms[ALARM].status == status
    assert (hub.data_dir / "alarms.journal").read_bytes() == journal
    assert not [e for e in logged_before_a_marker(hub) if e.tag.startswith("alarm_") and
                e.tag != "alarm_raised"]  # fmt: skip


def test_a_snapshot_that_fails_half_way_leaves_no_active_file_and_says_why(tmp_path: Path):
    site = parse_config(SITE.format(port=1), "<test>")
    bus = EventBus()
    snap = SnapshotBuffer(site, tmp_path, bus, ReadModel("atomic"), BatchFeed())
    seen: list[Event] = []
    bus.subscribe("test", seen.append)
    bus.start()
    snap.start()
    try:
        now = time.time_ns()
        snap.offer(
            "/events", encode(make_event(now, "hub", 20, "t", "t", "held")), now, now, EVENT_TYPE
        )
        # Text the request's checks would refuse, reaching the snapshot's metadata anyway.
        written, why = snap.snapshot("ann@desk", "layer \ud800")
        assert written is False
        assert why.startswith("could not write the snapshot: 'utf-8' codec can't encode"), why
        assert not list(tmp_path.rglob("*.active"))
        assert list((tmp_path / "snapshots").iterdir()) == []
        assert snap.failed == 1
        assert snap.snapshot("ann@desk", "Zoë's layer 🌊")[0] is True
    finally:
        snap.stop()
        bus.stop()
    failed = [e for e in seen if e.tag == "snapshot_failed"]
    assert len(failed) == 1
    assert encode(failed[0])  # the event itself is recordable


def test_events_log_keeps_a_line_that_holds_a_lone_surrogate_escaped(tmp_path: Path):
    bus = EventBus()
    log = EventLog(tmp_path / "events.log", bus, ReadModel("atomic"))
    log.start()
    bus.start()
    try:
        bus.publish(make_event(time.time_ns(), "hub", 20, "test", "odd", "note \ud800 kept"))
        bus.publish(make_event(time.time_ns(), "hub", 20, "test", "next", "the next one"))
    finally:
        bus.stop()
        log.stop()
    lines = (tmp_path / "events.log").read_text(encoding="utf-8").splitlines()
    assert [line.split(": ", 1)[1] for line in lines] == ["note \\ud800 kept", "the next one"]


def test_a_hub_event_is_made_writable_before_any_subscriber_sees_it():
    bus = EventBus()
    seen: list[Event] = []
    bus.subscribe("test", seen.append)
    bus.start()
    try:
        bus.emit(logging.INFO, "recorder", "split", "closed by \udcff@desk", by="\udcff@desk")
    finally:
        bus.stop()
    (e,) = seen
    assert e.message == "closed by \\udcff@desk"
    assert e.get("by") == "\\udcff@desk"
    assert encode(e)  # the recorder writes it


def test_an_infinite_value_is_journaled_as_no_value_and_a_record_that_is_not_json_is_refused(
    tmp_path: Path,
):
    site = parse_config(SITE.format(port=1), "<test>")
    (d,) = [d for d in build_definitions(site) if d.name == ALARM]
    status = AlarmStatus(latch=False, state=State.ACTIVE_UNACKED, active=True, value=math.inf)
    t = told(d, status, Change("raised", State.ACTIVE_UNACKED, 1, math.inf))
    journal = Journal(tmp_path / "alarms.journal")
    journal.open()
    try:
        assert journal.append(t.journal, sync=True) is True
        assert journal.append({"name": ALARM, "value": math.nan}) is False
        assert journal.write_errors == 1
    finally:
        journal.close()
    (line,) = (tmp_path / "alarms.journal").read_text().splitlines()
    assert json.loads(line)["value"] is None


def test_a_request_whose_handler_fails_is_still_answered_saying_so():
    import zenoh

    from fleetdaq.hub.requests import FAILED, Caller, OperatorQueryable
    from fleetdaq.hub.routing.router import Router
    from fleetdaq.runtime.zenoh_session import client_config

    def handler(raw: bytes, caller: Caller | None) -> dict[str, object]:
        if raw == b"fail":
            raise RuntimeError("a bug past the checks")
        return {"ok": True, "error": ""}

    port = free_port()
    router = Router([f"tcp/127.0.0.1:{port}"])
    router.start()
    queryable = OperatorQueryable(router, "fleetdaq/atomic/hub/test", handler, None, "test")
    queryable.start()
    session = zenoh.open(client_config([f"tcp/127.0.0.1:{port}"]))
    try:

        def ask(payload: bytes) -> object:
            for reply in session.get("fleetdaq/atomic/hub/test", payload=payload, timeout=10.0):
                if reply.ok is not None:
                    return json.loads(reply.ok.payload.to_bytes())
            return None

        assert ask(b"fail") == {"ok": False, "error": FAILED}
        assert ask(b"{}") == {"ok": True, "error": ""}, "the service goes on"
    finally:
        session.close()
        queryable.stop()
        router.stop()
