"""The output service in-process, with Zenoh's Query replaced by a stand-in that records the
reply (the transport, not the unit under test): a full queue refused at once as busy, a reply
that cannot be sent does not stop the worker, and a device that fails at start gets its initial
value and its hardware watchdog once it answers again."""

from __future__ import annotations

import dataclasses
import logging
import time
from typing import Any

import pytest

from fleetdaq.contract.cdr import decode, encode
from fleetdaq.contract.messages import OutputCommand, OutputReply
from fleetdaq.edge.drivers.pacing import VirtualTime
from fleetdaq.edge.event_publisher import EventPublisher
from fleetdaq.edge.output_commands import CommandDesk
from fleetdaq.edge.outputs import QUEUE_LIMIT, OutputService
from fleetdaq.hub.config.load import parse_config
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


def test_command_ids_are_remembered_while_their_command_could_be_applied_and_no_longer() -> None:
    clock = VirtualTime()
    t0 = clock.time_ns()
    service = _service()  # never started: in its safe state, every set is refused safe_state
    desk = CommandDesk("n", service.channels, service.interlocks, service.events, clock, service,
                       max_command_age_s=5.0, memory=3)  # fmt: skip

    def send(
        i: int, action: str = "set", max_age_s: float = 0.0, issued_ns: int = 0
    ) -> OutputReply:
        cmd = OutputCommand(f"c{i}", "heater", action, 1.0, 0.0, "operator", "t", "r",
                            issued_ns or clock.time_ns(), max_age_s)  # fmt: skip
        return decode(desk.decide("heater", encode(cmd)), OutputReply)

    first = send(1)
    assert (first.refusal, first.replay) == ("safe_state", False)
    clock.advance(4 * 10**9)
    again = send(1, issued_ns=t0)  # the same bytes 4 s later: still young enough
    assert encode(again) == encode(dataclasses.replace(first, replay=True))  # NaN readback
    send(2, max_age_s=1.0)  # its own limit: remembered for 1 s only
    send(3)
    busy = send(4)
    assert (busy.refusal, busy.replay) == ("not_allowed", False)
    assert busy.message.startswith("busy: 3 commands young enough to be replayed are remembered")
    assert busy.message.endswith("try again in 1.0 s")
    assert send(4, "read").refusal == "", "a read moves nothing: never refused for the memory"
    clock.advance(int(1.5e9))  # c1 (5 s) and c2 (1 s) are too old now: forgotten
    assert send(4).refusal == "safe_state"
    late = send(1, issued_ns=t0)
    assert (late.refusal, late.replay) == ("too_old", False), "forgotten, and too old by then"
    clock.advance(3 * 10**9)  # c3 was sent 4.5 s ago: a retry stamped anew keeps it longer
    assert send(3).replay
    clock.advance(4 * 10**9)
    assert send(3, issued_ns=t0 + 4 * 10**9).replay, "remembered as long as the retry lives"
