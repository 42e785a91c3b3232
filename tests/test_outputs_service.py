"""The output service in-process, with Zenoh's Query replaced by a stand-in that records the
reply (the transport, not the unit under test): a full queue refused at once as busy, a reply
that cannot be sent does not stop the worker, and a device that fails at start gets its initial
value and its hardware watchdog once it answers again."""

from __future__ import annotations

import logging
import time
from typing import Any

import pytest

from edge.cdr import decode, encode
from edge.config.load import parse_config
from edge.event_publisher import EventPublisher
from edge.messages import OutputCommand, OutputReply
from edge.outputs import QUEUE_LIMIT, OutputService
from tests.procs import wait_until

SITE = """\
site: s
nodes:
  n:
    control: {readback_s: 0.05}
    streams: {w: {driver: wave_sim, rate_hz: 10, channels: [{name: x}]}}
    outputs:
      heater: {driver: mcp4725, min: 0, max: 3, safe: 0, initial: 1.5, sim: {}}
      relay: {driver: pcf8574, address: 0x20, pin: 0, safe: 0, initial: 1,
              sim: {faults: [{kind: nack, at_s: 0, for_s: 0.5}]}}
"""


class Payload:
    def __init__(self, data: bytes) -> None:
        self.data = data

    def to_bytes(self) -> bytes:
        return self.data


class Query:
    """What the service uses of a zenoh.Query."""

    def __init__(self, output: str, data: bytes, fail: bool = False) -> None:
        self.key_expr = f"fleetdaq/s/n/out/{output}"
        self.payload = Payload(data)
        self.replies: list[OutputReply] = []
        self.dropped = False
        self.fail = fail

    def reply(self, key: str, payload: bytes) -> None:
        if self.fail:
            raise RuntimeError("the asker went away")
        assert key == self.key_expr
        self.replies.append(decode(payload, OutputReply))

    def drop(self) -> None:
        self.dropped = True


def _cmd(output: str, action: str = "read", i: int = 0) -> bytes:
    return encode(
        OutputCommand(f"c{i}", output, action, 0.0, 0.0, "operator", "t", "r", time.time_ns(), 0)
    )


def _service() -> OutputService:
    cfg = parse_config(SITE, "t").nodes["n"]
    return OutputService("s", "n", cfg, EventPublisher(None, "fleetdaq/s/n/events", "n"))


def test_a_full_queue_is_refused_at_once_and_every_queued_command_is_answered() -> None:
    service = _service()
    queued = [Query("heater", _cmd("heater", i=i)) for i in range(QUEUE_LIMIT)]
    for q in queued:
        service._on_query(q)  # the worker is not running yet: they wait
    extra = Query("heater", _cmd("heater", i=999))
    service._on_query(extra)
    (busy,) = extra.replies
    assert (busy.refusal, busy.command_id) == ("not_allowed", "c999")
    assert "busy" in busy.message
    assert extra.dropped
    try:
        service.start()
        wait_until(lambda: all(q.replies for q in queued), 10, "every queued reply")
    finally:
        service.close()
    assert all(q.dropped for q in queued)
    assert [q.replies[0].command_id for q in queued] == [f"c{i}" for i in range(QUEUE_LIMIT)]


def test_a_reply_that_cannot_be_sent_does_not_stop_the_worker() -> None:
    service = _service()
    service.start()
    try:
        broken = Query("heater", _cmd("heater", i=1), fail=True)
        service._on_query(broken)
        after = Query("heater", _cmd("heater", i=2))
        service._on_query(after)
        wait_until(lambda: after.replies, 10, "the next reply")
        assert broken.dropped
        assert service.counts["replies_failed"] == 1
    finally:
        service.close()


def test_a_device_that_fails_at_start_gets_its_initial_value_once_it_answers(
    caplog: pytest.LogCaptureFixture,
) -> None:
    caplog.set_level(logging.INFO, logger="fleetdaq.edge")
    service = _service()
    relay = service.channels["relay"]
    service.start()
    try:
        assert service.started.wait(10)
        assert relay.fault is not None  # the chip NACKed the initial write
        assert service.channels["heater"].readback == pytest.approx(1.5, abs=0.001)
        wait_until(lambda: relay.readback == 1.0, 10, "the relay's initial value")
        tags: list[Any] = [r.getMessage() for r in caplog.records]
        assert any("[output_recovered]" in t for t in tags)
    finally:
        service.close()
    assert relay.readback == 0.0  # safe at stop
