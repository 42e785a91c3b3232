"""Outputs end to end: a real edge agent in its own process, a test double of the hub in
another (tests/hub_double.py: a Zenoh router on loopback, the hub heartbeat, OutputCommand
queries), real Zenoh between them. Every refusal reason through the real queryable, readback
from the simulated devices, a retried command applied once, a pulse that returns, the node's
health, and the dead-man: heartbeat stopped, and the hub killed with SIGKILL."""

from __future__ import annotations

import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

from tests.hub_double import HubDouble
from tests.procs import Proc, free_port, wait_until

SITE = """\
site: ctl
hub: {{listen: [tcp/127.0.0.1:{port}]}}
nodes:
  cell:
    spool: {{dir: {spool}}}
    control: {{safe_after_s: {safe_after_s}, max_command_age_s: 5}}
    streams:
      t8: {{driver: labjack_t8, rate_hz: 200, sim: {{seed: 1}}, channels: [{{name: a}}]}}
      wave: {{driver: wave_sim, rate_hz: 20, channels: [{{name: level}}]}}
    outputs:
      valve: {{driver: labjack_t8_dac, dac: 0, min: 0, max: 5, safe: 0.5, max_rate: 2, sim: {{}}}}
      pump: {{driver: labjack_t8_dio, line: FIO2, safe: 0, arm_required: true, sim: {{}}}}
      relay: {{driver: pcf8574, address: 0x20, pin: 3, invert: true, safe: 0, sim: {{}}}}
      heater: {{driver: mcp4725, address: 0x60, min: 0, max: 3, safe: 0.25, sim: {{}}}}
      lamp: {{driver: pcf8574, address: 0x21, pin: 0, safe: 0, readback: last_written,
             sim: {{}}}}
      broken: {{driver: pcf8574, address: 0x22, pin: 0, safe: 0,
               sim: {{faults: [{{kind: nack, at_s: 0}}]}}}}
      locked: {{driver: mcp4725, address: 0x61, min: 0, max: 3, safe: 0, sim: {{}}}}
    interlocks:
      always: {{channel: wave/level, above: -1000, outputs: [locked]}}
"""
SAFE = {"valve": 0.5, "pump": 0.0, "relay": 0.0, "heater": 0.25}


@dataclass
class Rig:
    double: HubDouble
    edge: Proc
    tmp: Path
    port: int
    before_first_beat: dict[str, Any]


def _site(tmp: Path, port: int, safe_after_s: float) -> Path:
    cfg = tmp / "site.yaml"
    cfg.write_text(SITE.format(port=port, spool=tmp / "spool", safe_after_s=safe_after_s))
    return cfg


def _edge(cfg: Path, tmp: Path) -> Proc:
    return Proc(["edge", "--config", str(cfg), "--node", "cell"], tmp / "edge.log")


def _answers(double: HubDouble) -> dict[str, Any] | None:
    got = double.ask("cmd", output="valve", action="read", timeout=1.0)
    return got["replies"][0] if got["replies"] else None


def _arm(double: HubDouble, *outputs: str) -> None:
    for out in outputs:
        reply = double.command(out, "arm")
        assert reply["applied"], reply


@pytest.fixture(scope="module")
def rig(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Rig]:
    tmp = tmp_path_factory.mktemp("outputs")
    port = free_port()
    cfg = _site(tmp, port, 3.0)
    double = HubDouble(port, "ctl", "cell", beat=False)
    edge = _edge(cfg, tmp)
    try:
        first = wait_until(lambda: _answers(double), 30, "the edge to answer")
        before = double.command("valve", "set", value=1.0)
        double.ask("beat", on=True)
        wait_until(lambda: not (_answers(double) or {"safe_state": True})["safe_state"], 10,
                   "the edge to hear the heartbeat")  # fmt: skip
        assert first["safe_state"]
        yield Rig(double, edge, tmp, port, before)
    finally:
        double.close()
        code = edge.terminate()
        assert code == 0, edge.output()[-3000:]


def test_before_the_first_heartbeat_commands_are_refused_with_safe_state(rig: Rig) -> None:
    reply = rig.before_first_beat
    assert (reply["applied"], reply["refusal"], reply["safe_state"]) == (False, "safe_state", True)
    assert "no hub heartbeat heard yet" in reply["message"]


def test_outputs_start_at_their_safe_values_read_back_from_the_devices(rig: Rig) -> None:
    for name, safe in SAFE.items():
        reply = rig.double.command(name, "read")
        assert reply["applied"], reply
        assert reply["readback"] == pytest.approx(safe, abs=1e-3), name
        assert reply["readback_source"] == "device"
    lamp = rig.double.command("lamp", "read")
    assert lamp["readback_source"] == "last_written"


def test_after_the_hub_is_heard_only_arm_required_outputs_need_arming(rig: Rig) -> None:
    reply = rig.double.command("pump", "set", value=1.0)
    assert reply["refusal"] == "not_armed", reply
    assert reply["safe_state"] is False
    for name in ("relay", "heater"):
        reply = rig.double.command(name, "read")
        assert reply["armed"] is True, reply


def test_every_refusal_reason_comes_back_through_the_real_queryable(rig: Rig) -> None:
    d = rig.double
    _arm(d, "valve", "heater", "relay", "locked", "broken")
    cases: list[tuple[str, dict[str, Any], str, str]] = [
        ("nope", {"action": "set", "value": 1}, "unknown_output", "no output 'nope'"),
        ("heater", {"value": 3.5}, "out_of_limits", "outside the limits 0..3 V"),
        ("relay", {"value": 0.5}, "not_allowed", "digital: 0 or 1"),
        ("relay", {"action": "pulse", "value": 1, "pulse_s": 0}, "not_allowed", "pulse_s"),
        ("heater", {"issued_ns": time.time_ns() - 10_000_000_000}, "too_old", "s ago"),
        ("heater", {"issued_ns": time.time_ns() + 60_000_000_000}, "too_old", "in the future"),
        (
            "heater",
            {"value": 1, "max_age_s": 0.001, "issued_ns": time.time_ns() - 10**8},
            "too_old",
            "older than 0.001 s",
        ),
        ("locked", {"value": 1}, "interlock", "interlock always active"),
        ("pump", {"value": 1}, "not_armed", "not armed"),
        ("broken", {"value": 1}, "device_error", "Remote I/O error"),
    ]
    for output, fields, reason, text in cases:
        reply = d.command(output, fields.pop("action", "set"), **fields)
        assert (reply["applied"], reply["refusal"]) == (False, reason), (output, reply)
        assert text in reply["message"], reply
    # too_fast: a step within max_rate x the time since the last change, then one beyond it.
    # (0.05 V at 2 V/s needs 25 ms since the valve's safe value was written at start: a fast
    # host reaches this line ~0.2 s after that, too soon for a 0.5 V step.)
    step = d.command("valve", value=0.55)
    assert step["applied"], step
    fast = d.command("valve", value=5.0)
    assert fast["refusal"] == "too_fast", fast
    assert "exceeds max_rate 2 V/s" in fast["message"]
    assert fast["interlocks"] == []
    locked = d.command("locked", "read")
    assert locked["interlocks"] == ["always"]


def test_hostile_payloads_are_refused_not_allowed_and_the_queryable_keeps_answering(
    rig: Rig,
) -> None:
    d = rig.double
    for raw in ("", "00", "00010000" + "ff" * 40, "deadbeef" * 300):
        got = d.ask("cmd", output="heater", raw=raw)
        (reply,) = got["replies"]
        assert (reply["refusal"], reply["command_id"]) == ("not_allowed", ""), reply
    mismatch = d.command("heater", key="relay", value=1)
    assert mismatch["refusal"] == "not_allowed"
    assert "came on the key of 'relay'" in mismatch["message"]
    assert d.ask("cmd", output="heater", key="*", timeout=1.0)["replies"] == []
    assert d.command("heater", "read")["applied"]  # still answering
    assert d.events("malformed_command")
    d.ask("junk_beat")  # junk on the heartbeat key: refused, counted, the hub still counts
    wait_until(lambda: d.events("heartbeat_refused"), 10, "the refused heartbeat")
    assert not d.command("heater", "read")["safe_state"]


def test_applied_commands_read_back_from_the_device_and_a_retry_is_applied_once(
    rig: Rig,
) -> None:
    d = rig.double
    _arm(d, "heater", "relay")
    first = d.command("heater", value=1.2, command_id="retry-1")
    assert first["applied"]
    assert first["readback"] == pytest.approx(1.2, abs=3.3 / 4096)
    assert first["readback_source"] == "device"
    assert first["requested"] == 1.2
    assert d.command("heater", value=2.0, command_id="retry-2")["applied"]
    again = d.command("heater", value=1.2, command_id="retry-1")
    assert first["replay"] is False
    assert again == first | {"replay": True}  # the stored reply (same readback, replied_ns)
    now = d.command("heater", "read")
    assert now["readback"] == pytest.approx(2.0, abs=3.3 / 4096)  # not applied a second time
    restamped = d.command("heater", value=1.2, command_id="retry-1", issued_ns=time.time_ns())
    assert restamped == again, "a retry stamped anew is a replay all the same"
    reused = d.command("heater", value=0.3, command_id="retry-1")
    assert reused["refusal"] == "not_allowed"
    assert "another command" in reused["message"]
    on = d.command("relay", value=1)
    assert (on["applied"], on["readback"]) == (True, 1.0)  # active-low pin read back, inverted
    assert d.events("command_retried")


def test_a_replayed_refusal_is_its_original_refusal_and_reads_are_never_replays(rig: Rig) -> None:
    d = rig.double
    refused = d.command("heater", value=9, command_id="replay-refused")
    assert refused["refusal"] == "out_of_limits"
    again = d.command("heater", value=9, command_id="replay-refused")
    assert again == refused | {"replay": True}
    reads = [d.command("heater", "read", command_id="read-1") for _ in range(2)]
    assert [r["replay"] for r in reads] == [False, False]


def test_a_command_from_1970_that_allows_itself_1e300_s_is_too_old(rig: Rig) -> None:
    d = rig.double
    _arm(d, "heater")
    before = d.command("heater", "read")["readback"]
    for issued_ns in (1, time.time_ns() - 6 * 10**9, time.time_ns() + 6 * 10**9):
        reply = d.command("heater", value=2.9, issued_ns=issued_ns, max_age_s=1e300)
        assert (reply["applied"], reply["refusal"]) == (False, "too_old"), reply
        assert "its own max_age_s 1e+300 cannot raise this node's limit" in reply["message"]
    assert d.command("heater", "read")["readback"] == before


def test_requester_text_an_edge_cannot_record_is_refused_before_anything_is_done(
    rig: Rig,
) -> None:
    d = rig.double
    _arm(d, "heater")
    before = d.command("heater", "read")["readback"]
    for field, text in (("reason", "on\x1b[2J"), ("who", "eve\nroot"), ("reason", "r" * 501),
                        ("command_id", "bad\u202etext")):  # fmt: skip
        fields = {"command_id": "bad-text", field: text}
        reply = d.command("heater", value=2.9, **fields)
        assert reply["refusal"] == "not_allowed", reply
        assert reply["command_id"] == ("" if field == "command_id" else "bad-text")
        assert reply["message"].startswith(f"{field} holds a ") or "at most" in reply["message"]
    assert d.command("heater", "read")["readback"] == before
    # (not `"bad" in id`: a random hex id of another test's command holds "bad" now and then)
    mine = ("bad-text", "bad\u202etext")
    assert not [e for e in d.events() if e["fields"].get("command_id") in mine]
    assert d.events("malformed_command")
    kindly = d.command("heater", value=1.0, who="jürgen@prüfstand", reason="Aufheizen 温度 ✓")
    assert kindly["applied"], kindly


def test_a_pulse_returns_to_the_previous_value_without_blocking_other_commands(
    rig: Rig,
) -> None:
    d = rig.double
    _arm(d, "pump")
    assert d.command("pump", value=0)["applied"]
    pulse = d.command("pump", "pulse", value=1, pulse_s=1.0)
    assert pulse["applied"]
    assert pulse["readback"] == 1.0
    assert d.command("heater", "read")["applied"]  # answered while the pulse runs
    wait_until(lambda: d.command("pump", "read")["readback"] == 0.0, 10, "the pulse to end")
    assert d.events("pulse_ended")


def test_every_command_and_result_is_an_event_with_structured_fields(rig: Rig) -> None:
    d = rig.double
    _arm(d, "heater")
    d.command("heater", value=0.7, command_id="ev-1", who="alice@bench", reason="warm up")
    d.command("heater", value=9, command_id="ev-2")

    def mine() -> list[dict[str, Any]]:
        return [e for e in d.events() if e["fields"].get("command_id") in ("ev-1", "ev-2")]

    evs = wait_until(lambda: len(mine()) == 2 and mine(), 10, "the command events")
    applied, refused = sorted(evs, key=lambda e: e["fields"]["command_id"])
    assert applied["tag"] == "command_applied"
    assert applied["source"] == "heater"
    assert applied["fields"]["who"] == "alice@bench"
    assert applied["fields"]["action"] == "set"
    assert applied["fields"]["value"] == "0.7"
    assert refused["tag"] == "command_refused"
    assert refused["fields"]["refusal"] == "out_of_limits"


def test_node_health_carries_every_output(rig: Rig) -> None:
    outputs = wait_until(lambda: rig.double.ask("health").get("outputs"), 10, "node health")
    by_name = {o["name"]: o for o in outputs}
    assert set(by_name) == {"valve", "pump", "relay", "heater", "lamp", "broken", "locked"}
    assert by_name["heater"]["kind"] == "analog"
    assert by_name["heater"]["unit"] == "V"
    assert by_name["locked"]["interlocks"] == ["always"]
    assert by_name["lamp"]["readback_source"] == "last_written"


# --- the dead-man ---------------------------------------------------------------------------


def _safe_event(double: HubDouble) -> dict[str, Any] | None:
    evs = double.events("safe_state")
    return evs[-1] if evs else None


def test_dead_man_heartbeat_stopped_and_hub_killed(tmp_path: Path) -> None:
    safe_after = 1.5
    port = free_port()
    cfg = _site(tmp_path, port, safe_after)
    beats = tmp_path / "last_beat_ns"
    double = HubDouble(port, "ctl", "cell", beat=True, beat_file=beats)
    edge = _edge(cfg, tmp_path)
    try:
        wait_until(lambda: (_answers(double) or {}).get("safe_state") is False, 30, "the hub")
        _arm(double, "heater", "relay", "valve")
        assert double.command("heater", value=2.5)["applied"]
        assert double.command("relay", value=1)["applied"]

        # 1. The heartbeat stops, the hub stays up: safe within safe_after_s + 1 s.
        double.ask("beat", on=False)
        event = wait_until(lambda: _safe_event(double), 10, "the safe_state event")
        last_beat = int(beats.read_text())
        assert event["time_ns"] - last_beat <= (safe_after + 1.0) * 1e9
        assert event["level"] == 40
        for name, safe in SAFE.items():
            reply = double.command(name, "read")
            assert reply["readback"] == pytest.approx(safe, abs=1e-3), name
            assert reply["safe_state"]
            assert not reply["armed"]
        assert double.command("heater", value=1)["refusal"] == "safe_state"
        assert double.command("heater", "arm")["refusal"] == "safe_state"
        cleared = len(double.events("safe_state_cleared"))
        double.ask("beat", on=True)
        wait_until(lambda: len(double.events("safe_state_cleared")) > cleared, 10, "the hub back")
        assert double.command("heater", value=1)["refusal"] == "not_armed"
        _arm(double, "heater")
        assert double.command("heater", value=2.5)["applied"]

        # 2. The hub is killed (SIGKILL): nobody to tell the edge anything.
        double.kill()
        last_beat = int(beats.read_text())
        double = HubDouble(port, "ctl", "cell", beat=False)  # a hub restarting, not beating yet
        wait_until(lambda: _answers(double), 30, "the edge to reconnect")
        event = wait_until(lambda: _safe_event(double), 10, "the safe_state event")
        assert len(double.events("safe_state")) == 1  # held by the edge until a hub listened
        assert 0 < event["time_ns"] - last_beat <= (safe_after + 1.0) * 1e9
        assert double.command("heater", "read")["readback"] == pytest.approx(0.25, abs=1e-3)
        assert double.command("heater", value=1)["refusal"] == "safe_state"
        double.ask("beat", on=True)
        wait_until(lambda: not _answers(double)["safe_state"], 10, "the hub back")
        assert double.command("heater", value=1)["refusal"] == "not_armed"
        _arm(double, "heater")
        assert double.command("heater", value=1)["applied"]
    finally:
        double.close()
        code = edge.terminate()
    assert code == 0, edge.output()[-3000:]
