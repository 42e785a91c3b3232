"""A replay pass that fails (here: the put raises, as Zenoh does on a broken session) is
reported as an event and tried again; the replay thread does not end before its stream."""

from __future__ import annotations

import threading
import time
from pathlib import Path
from typing import Any

import zenoh

from fleetdaq.edge.event_publisher import EventPublisher
from fleetdaq.edge.spool import StreamSpool
from fleetdaq.edge.stream_loop import StreamLoop
from fleetdaq.hub.config.load import parse_config

SITE = """\
site: replay
nodes:
  env:
    spool: {replay_after_s: 0.2}
    streams:
      air: {driver: environment_sim, rate_hz: 20, scans_per_batch: 2,
            channels: [{name: t, unit: degC}]}
"""


class _Matched:
    matching = True


class FlakyPublisher:
    """Live puts go nowhere (so every batch stays unacked); the first replay put raises."""

    def __init__(self, replay: bool, log: list[str]) -> None:
        self.matching_status = _Matched()
        self.replay, self.log = replay, log

    def put(self, payload: Any, **_: Any) -> None:
        if self.replay:
            self.log.append("replay")
            if self.log.count("replay") == 1:
                raise zenoh.ZError("session closed (the test's)")

    def undeclare(self) -> None:
        pass


class Session:
    def __init__(self) -> None:
        self.puts: list[str] = []

    def declare_publisher(self, key: str, **kw: Any) -> FlakyPublisher:
        return FlakyPublisher(kw.get("priority") == zenoh.Priority.DATA_LOW, self.puts)


class Events(EventPublisher):
    def __init__(self) -> None:
        super().__init__(None, "fleetdaq/replay/env/events", "env")
        self.tags: list[str] = []

    def emit(self, level: int, source: str, tag: str, message: str, /, **fields: object) -> None:
        self.tags.append(tag)


def _wait(cond: Any, timeout: float, what: str) -> None:
    done = threading.Event()
    deadline = time.monotonic() + timeout
    while not cond():
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        done.wait(0.05)


def test_a_failed_replay_is_reported_and_tried_again(tmp_path: Path) -> None:
    site = parse_config(SITE, "<test>")
    node = site.nodes["env"]
    spool = StreamSpool(tmp_path / "spool", node.spool.max_bytes, node.spool.max_age_s)
    events, session = Events(), Session()
    loop = StreamLoop(
        "replay", "env", "air", node.streams["air"], session, events, spool, node.spool
    )
    loop.start()
    try:
        _wait(lambda: "replay_error" in events.tags, 30, "the failed replay's event")
        _wait(lambda: loop.counters.replayed > 0, 30, "a replay after the failure")
    finally:
        loop.stop()
        loop.join(5.0)
    assert session.puts.count("replay") >= 2
