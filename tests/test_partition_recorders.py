"""The main hub's side of recorder requests on a partitioned site
(`fleetdaq.hub.partitions.recorders`):
a partition's answer crosses the mesh, so it is checked in full before the operator is told
what that hub did. The real round trip (two hubs, `fleetdaq rec`) is in test_partitions.py."""

from __future__ import annotations

import json
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

from fleetdaq.contract.keys import SiteKeys
from fleetdaq.contract.messages import Event
from fleetdaq.hub.bus import EventBus
from fleetdaq.hub.partitions.recorders import PartitionRecorders, parse_answer
from tests.zenoh_shapes import Payload, Reply, Sample


@pytest.mark.parametrize(
    ("raw", "why"),
    [
        (b"x" * (4 * 1024 * 1024 + 1), "bytes (at most"),
        (b"{not json", "not JSON"),
        (b"[1, 2]", "not a JSON object"),
        (b"{}", "ok is not true or false"),
        (b'{"ok": 1, "result": "closed a.mcap"}', "ok is not true or false"),
        (b'{"ok": true, "result": 5}', "result is not text"),
        (b'{"ok": true, "result": "' + b"r" * 2001 + b'"}', "result is not text"),
        (b'{"ok": true, "error": ["x"]}', "error is not text"),
        (b"[" * 100_000, "not JSON"),
    ],
)
def test_an_answer_that_is_not_one_is_refused_with_why(raw: bytes, why: str) -> None:
    with pytest.raises(ValueError, match=re.escape(why)):
        parse_answer(raw)


def test_an_answer_keeps_only_ok_result_and_error_and_an_error_is_never_ok() -> None:
    full = {"ok": True, "result": "closed x.mcap", "error": "", "recorder": {"state": "recording"}}
    assert parse_answer(json.dumps(full).encode()) == {
        "ok": True,
        "result": "closed x.mcap",
        "error": "",
    }
    wrong = parse_answer(b'{"ok": true, "error": "unknown action"}')
    assert wrong["ok"] is False


class _Session:
    def __init__(self, replies: dict[str, list[Reply]]) -> None:
        self.replies = replies
        self.asked: list[tuple[str, bytes]] = []

    def get(self, key: str, payload: bytes, timeout: float) -> list[Reply]:
        self.asked.append((key, payload))
        return self.replies.get(key.split("/")[-2], [])


@dataclass
class _Router:
    session: _Session


def test_each_partition_is_asked_and_a_bad_or_missing_answer_is_that_partitions_failure() -> None:
    good = Reply(Sample(Payload(b'{"ok": true, "result": "stopped; session s closed"}')))
    session = _Session(
        {
            "bay2": [good],
            "bay3": [Reply(Sample(Payload(b"junk")))],
            "bay4": [Reply(None, Sample(Payload(b"queryable failed")))],
            # bay5: no queryable answered (its hub is down)
        }
    )
    seen: list[Event] = []
    bus = EventBus()
    bus.subscribe("test", seen.append)
    bus.start()
    try:
        asked = PartitionRecorders(
            _Router(session),  # type: ignore[arg-type]
            SiteKeys("parts"),
            ["bay2", "bay3", "bay4", "bay5"],
            bus,
            timeout_s=3,
        )
        request = {"action": "stop", "user": "ana", "host": "shore", "note": ""}
        answers: dict[str, Any] = asked.ask(request)()
    finally:
        bus.stop()
    assert [k for k, _ in session.asked] == [
        f"fleetdaq/parts/hub/partition/{n}/recorder" for n in ("bay2", "bay3", "bay4", "bay5")
    ]
    assert {json.loads(p)["user"] for _, p in session.asked} == {"ana"}
    assert answers["bay2"] == {"ok": True, "result": "stopped; session s closed", "error": ""}
    assert answers["bay3"]["ok"] is False
    assert "its answer is not valid (not JSON)" in answers["bay3"]["error"]
    assert answers["bay4"] == {
        "ok": False,
        "result": "",
        "error": "its hub refused: queryable failed",
    }
    assert answers["bay5"]["error"] == (
        "no answer (is its hub running and linked? waited at most 3 s)"
    )
    assert asked.malformed == 1
    assert [(e.tag, e.get("partition")) for e in seen] == [("malformed", "bay3")]


def test_passed_on_without_waiting_a_partition_that_did_not_do_it_is_a_warning() -> None:
    """A rule's `record:` action: the answers are collected on a thread of their own."""
    import threading

    ok = Reply(Sample(Payload(b'{"ok": true, "result": "closed f.mcap"}')))
    session = _Session({"bay2": [ok], "bay3": [Reply(Sample(Payload(b'{"ok": false}')))]})
    seen: list[Event] = []
    got = threading.Event()
    bus = EventBus()

    def on_event(e: Event) -> None:
        seen.append(e)
        got.set()

    bus.subscribe("test", on_event)
    bus.start()
    try:
        parts = PartitionRecorders(
            _Router(session),  # type: ignore[arg-type]
            SiteKeys("parts"),
            ["bay2", "bay3"],
            bus,
        )
        parts.pass_on({"action": "split", "user": "rule:layers", "host": "hub", "note": ""})
        assert got.wait(10), "no event for bay3"
    finally:
        bus.stop()
    assert len(session.asked) == 2
    assert [(e.tag, e.get("partition"), e.get("action")) for e in seen] == [
        ("partition_not_done", "bay3", "split")
    ]
    assert "record split for rule:layers not done" in seen[0].message


def test_a_snapshot_is_not_asked_of_a_partition_that_keeps_no_buffer_and_that_is_no_failure():
    """`hub.partitions.bay3.snapshot: {enabled: false}`: a site's snapshot is bay2's and the
    main hub's; bay3's answer says why it has none, and `rec snapshot` is not a failure for it.
    Every other action still goes to bay3."""
    ok = Reply(Sample(Payload(b'{"ok": true, "result": "wrote snapshots/x"}')))
    session = _Session({"bay2": [ok], "bay3": [ok]})
    bus = EventBus()
    bus.start()
    try:
        parts = PartitionRecorders(
            _Router(session),  # type: ignore[arg-type]
            SiteKeys("parts"),
            ["bay2", "bay3"],
            bus,
            snapshots_off=frozenset({"bay3"}),
        )
        request = {"action": "snapshot", "user": "ana", "host": "shore", "note": ""}
        answers: dict[str, Any] = parts.ask(request)()
        assert [k.split("/")[-2] for k, _ in session.asked] == ["bay2"]
        assert answers["bay2"]["ok"] is True
        assert answers["bay3"] == {
            "ok": True,
            "result": "no snapshot: this hub keeps no snapshot buffer "
            "(hub.partitions.bay3.snapshot.enabled is false)",
            "error": "",
        }
        parts.ask({**request, "action": "split"})()
        assert [k.split("/")[-2] for k, _ in session.asked[1:]] == ["bay2", "bay3"]
    finally:
        bus.stop()


def test_the_main_hub_asks_no_snapshot_of_the_partitions_its_site_file_switches_off(
    tmp_path: Path,
) -> None:
    from fleetdaq.hub.config.load import parse_config
    from fleetdaq.hub.runtime import HubRuntime

    site = parse_config(
        """
site: p
hub:
  listen: [tcp/127.0.0.1:7999]
  dashboard: {enabled: false}
  partitions:
    bay2: {listen: [tcp/127.0.0.1:7998], nodes: [cell], snapshot: {enabled: false}}
    bay3: {listen: [tcp/127.0.0.1:7997], nodes: [env], snapshot: {seconds: 10}}
    bay4: {listen: [tcp/127.0.0.1:7996], nodes: [aux]}
nodes:
  wec: {streams: {t8: {driver: wave_sim, rate_hz: 100, channels: [{name: a}]}}}
  cell: {streams: {t8: {driver: wave_sim, rate_hz: 100, channels: [{name: a}]}}}
  env: {streams: {t8: {driver: wave_sim, rate_hz: 100, channels: [{name: a}]}}}
  aux: {streams: {t8: {driver: wave_sim, rate_hz: 100, channels: [{name: a}]}}}
""",
        "p.yaml",
    )
    parts = HubRuntime(site, tmp_path).partition_recorders  # built, not started
    assert parts is not None
    assert parts.snapshots_off == {"bay2"}
