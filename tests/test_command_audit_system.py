"""Output commands are recorded, or not done — with real processes: a hub (router, recorder,
dashboard) and an edge with simulated outputs, over Zenoh on loopback; `fleetdaq out` as a
subprocess, the dashboard over real HTTP, raw Zenoh requests from this process.

- hostile requester text (a lone surrogate, control characters, over-long) is refused with the
  reason, through the command line, a raw Zenoh request and the dashboard, and nothing
  happens: no command reaches the edge, nothing is recorded, no event;
- ordinary non-ASCII text is applied and recorded as typed;
- a command from 1970 that allows itself 1e300 s is too old at the edge;
- a replayed command id is answered with its original outcome, marked as a replay, and the
  output keeps what a later command set;
- commands to nodes the site does not have are recorded on ``/hub/commands``, never on a
  channel named by the requester.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
from mcap.reader import make_reader

from fleetdaq.contract.cdr import decode, encode
from fleetdaq.contract.messages import CommandRecord, Event, OutputCommand, OutputReply
from tests.procs import REPO, HubClient, Proc, free_port, sessions, wait_for_port, wait_until
from tests.web.conftest import PASSWORDS, Http, write_cheap_users

SITE = """\
site: audit
hub:
  listen: [tcp/127.0.0.1:{port}]
  recorder: {{file_duration_s: 3600, flush_interval_s: 0.2}}
  dashboard: {{enabled: true, listen: "127.0.0.1:{web}", users_file: {users}}}
  universal_alarms: {{node_down: false, stream_stale: false}}
nodes:
  pier:
    control: {{safe_after_s: 3}}
    streams:
      env: {{driver: environment_sim, rate_hz: 2, channels: [{{name: air, unit: degC}}]}}
    outputs:
      lamp: {{driver: pcf8574, address: 0x20, pin: 1, safe: 0, sim: {{}}}}
      heater: {{driver: mcp4725, address: 0x60, min: 0, max: 3, safe: 0.25, sim: {{}}}}
"""
STEP = 3.3 / 4096
"""The MCP4725's 12-bit step."""
HOSTILE = {
    "a lone surrogate": "\ud800",
    "an escape sequence": "warm up\x1b[2J",
    "a newline": "warm up\nroot: all ok",
    "a bidi override": "warm \u202eup",
    "over-long text": "x" * 501,
}
KIND = {
    "a lone surrogate": "lone UTF-16 surrogate",
    "an escape sequence": "control character (U+001B)",
    "a newline": "control character (U+000A)",
    "a bidi override": "bidirectional control",
    "over-long text": "at most 500 characters",
}
KINDLY = "Prüfung Heizung 温度 ✓"


@dataclass
class Site:
    tmp: Path
    cfg: Path
    data: Path
    port: int
    web: int
    hub: Proc
    edge: Proc
    zenoh: HubClient

    def out(self, *args: str, env: dict[str, str] | None = None) -> tuple[int, str, str]:
        r = subprocess.run(
            [sys.executable, "-m", "fleetdaq", "out", *args, "--config", str(self.cfg)],
            cwd=REPO, capture_output=True, text=True, timeout=60, check=False,
            env={**os.environ, **(env or {})},
        )  # fmt: skip
        return r.returncode, r.stdout, r.stderr

    def ask_hub(self, raw: bytes) -> dict[str, Any]:
        """A raw request on the hub's ``hub/out`` service, as any Zenoh client can send."""
        replies = list(self.zenoh.session.get(self.zenoh.keys.hub("out"), payload=raw, timeout=30))
        (ok,) = [r.ok for r in replies if r.ok is not None]
        answer: dict[str, Any] = json.loads(ok.payload.to_bytes())
        return answer

    def ask_edge(self, cmd: OutputCommand) -> OutputReply:
        """A command straight to the edge's queryable (security off: anyone on the network)."""
        key = self.zenoh.keys.out("pier", cmd.output)
        replies = list(self.zenoh.session.get(key, payload=encode(cmd), timeout=10))
        (ok,) = [r.ok for r in replies if r.ok is not None]
        return decode(ok.payload.to_bytes(), OutputReply)

    def commands_sent(self) -> int:
        status = self.zenoh.status(5.0)
        assert status is not None
        return int(status["commands"].get("sent", 0))

    def heater_now(self) -> float:
        """What the heater holds now: an arm (it already is) answers with a fresh readback."""
        code, stdout, stderr = self.out("arm", "pier/heater")
        assert code == 0, stderr
        return float(stdout.rsplit("readback ", 1)[1].split()[0])


@pytest.fixture(scope="module")
def site(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Site]:
    tmp = tmp_path_factory.mktemp("audit")
    port, web = free_port(), free_port()
    users = tmp / "users"
    write_cheap_users(users, PASSWORDS)
    cfg = tmp / "site.yaml"
    cfg.write_text(SITE.format(port=port, web=web, users=users))
    data = tmp / "data"
    hub = Proc(["hub", "--config", str(cfg), "--data", str(data)], tmp / "hub.log")
    edge: Proc | None = None
    client: HubClient | None = None
    try:
        wait_for_port(port)
        edge = Proc(
            ["edge", "--config", str(cfg), "--node", "pier", "--spool", str(tmp / "spool")],
            tmp / "edge.log",
        )
        client = HubClient(port, "audit")
        client.wait(lambda st: any(n["alive"] for n in st["nodes"]), 60, "the pier alive")
        s = Site(tmp, cfg, data, port, web, hub, edge, client)
        wait_until(lambda: s.out("arm", "pier/heater")[0] == 0, 30, "the edge to hear the hub")
        yield s
    finally:
        if client is not None:
            client.close()
        for p in (edge, hub):
            if p is not None:
                p.kill()


def test_hostile_text_on_the_command_line_is_refused_and_nothing_is_done(site: Site) -> None:
    before = site.commands_sent()
    heater = site.heater_now()
    for what in ("an escape sequence", "a newline", "a bidi override", "over-long text"):
        code, stdout, stderr = site.out(
            "set", "pier/heater", "2.5", "--reason", HOSTILE[what], "--command-id", "hostile-cli"
        )
        assert code == 2, (what, stdout, stderr)
        assert stderr.startswith("set pier/heater: reason holds a ") or "at most" in stderr
        assert KIND[what] in stderr, stderr
    # A byte that is not UTF-8 on the command line reaches Python as a lone surrogate.
    r = subprocess.run(
        [sys.executable.encode(), b"-m", b"fleetdaq", b"out", b"set", b"pier/heater", b"2.5",
         b"--reason", b"warm \xff", b"--config", str(site.cfg).encode()],
        cwd=REPO, capture_output=True, timeout=60, check=False,
    )  # fmt: skip
    assert r.returncode == 2, r.stderr
    assert b"reason holds a lone UTF-16 surrogate (U+DCFF) at character 5" in r.stderr
    code, _, stderr = site.out("set", "pier/heater", "2.5", env={"LOGNAME": "eve\x1b[31m"})
    assert code == 2
    assert "user holds a control character (U+001B)" in stderr
    code, _, stderr = site.out("arm", "pier/heater\x07")
    assert code == 2
    assert "output holds a control character (U+0007)" in stderr
    assert site.commands_sent() == before + 1  # heater_now's own arm below counts, nothing else
    assert site.heater_now() == pytest.approx(heater, abs=STEP)


def test_hostile_text_in_a_raw_zenoh_request_is_refused_and_nothing_is_done(site: Site) -> None:
    before = site.commands_sent()
    for what, text in HOSTILE.items():
        body = {"action": "set", "output": "pier/heater", "value": 2.5, "reason": text,
                "user": "mallory", "host": "h", "command_id": "hostile-zenoh"}  # fmt: skip
        answer = site.ask_hub(json.dumps(body).encode())  # "\ud800" travels as valid JSON
        assert answer["ok"] is False, what
        assert KIND[what] in answer["error"], answer
        assert answer["error"].startswith("reason "), answer
    for key in ("user", "host", "command_id"):
        body = {"action": "pulse", "output": "pier/lamp", "value": 1, "pulse_s": 1, key: "\ud800"}
        answer = site.ask_hub(json.dumps(body).encode())
        assert answer["error"] == f"{key} holds a lone UTF-16 surrogate (U+D800) at character 0"
    assert site.commands_sent() == before


def test_hostile_text_from_the_dashboard_is_refused_with_400_and_nothing_is_done(
    site: Site,
) -> None:
    http = Http(site.web)
    assert http.login("alice")[0] == 200
    before = site.commands_sent()
    for action in ("set", "pulse", "arm", "disarm"):
        for what, text in HOSTILE.items():
            body = {"action": action, "output": "pier/lamp", "value": 1, "reason": text}
            if action == "pulse":
                body["pulse_s"] = 1
            status, answer = http.post("/api/outputs", body)
            assert status == 400, (action, what, answer)
            assert KIND[what] in answer["error"], answer
    assert site.commands_sent() == before


def test_ordinary_non_ascii_text_is_applied_and_recorded_as_typed(site: Site) -> None:
    code, stdout, stderr = site.out(
        "set", "pier/heater", "1.5", "--reason", KINDLY, "--command-id", "kindly-cli"
    )
    assert code == 0, stderr
    assert "applied; readback 1.5" in stdout
    http = Http(site.web)
    assert http.login("bob")[0] == 200
    status, answer = http.post(
        "/api/outputs", {"action": "set", "output": "pier/lamp", "value": 1, "reason": KINDLY}
    )
    assert status == 200, answer
    assert answer["reply"]["applied"] is True
    assert answer["command"]["who"] == "bob@127.0.0.1"


def test_a_command_issued_in_1970_that_allows_itself_1e300_s_is_refused_too_old(site: Site) -> None:
    heater = site.heater_now()
    cmd = OutputCommand("from-1970", "heater", "set", 2.0, 0.0, "operator", "mallory", "x",
                        issued_ns=1, max_age_s=1e300)  # fmt: skip
    reply = site.ask_edge(cmd)
    assert (reply.applied, reply.refusal) == (False, "too_old")
    assert "older than 5 s; its own max_age_s 1e+300 cannot raise this node's limit" in (
        reply.message
    )
    assert site.heater_now() == pytest.approx(heater, abs=STEP)


def _readback(line: str) -> float:
    return float(line.split("readback ", 1)[1].split(maxsplit=1)[0].rstrip(";"))


def test_a_replayed_command_id_gets_its_original_outcome_and_is_not_applied_again(
    site: Site,
) -> None:
    code, stdout, _ = site.out("set", "pier/heater", "1", "--command-id", "replay-x")
    assert code == 0, stdout
    assert _readback(stdout) == pytest.approx(1.0, abs=STEP)
    code, stdout, _ = site.out("set", "pier/heater", "2", "--command-id", "replay-y")
    assert code == 0, stdout
    assert _readback(stdout) == pytest.approx(2.0, abs=STEP)
    code, stdout, stderr = site.out("set", "pier/heater", "1", "--command-id", "replay-x")
    assert code == 0, stderr
    assert stdout.startswith(
        "pier/heater: set is a replay of command replay-x: applied then; readback then "
    ), stdout
    assert _readback(stdout.replace("readback then", "readback")) == pytest.approx(1.0, abs=STEP)
    assert stdout.rstrip().endswith("; not applied again"), stdout
    assert site.heater_now() == pytest.approx(2.0, abs=STEP)
    # The same id for another command is refused, not taken for a replay.
    code, _, stderr = site.out("set", "pier/heater", "0.5", "--command-id", "replay-x")
    assert code == 1
    assert "was used for another command" in stderr
    assert site.heater_now() == pytest.approx(2.0, abs=STEP)


def test_commands_to_unknown_nodes_are_refused(site: Site) -> None:
    for target in ("mallory/valve", "*/valve", "hub/valve"):
        code, _, stderr = site.out("set", target, "1", "--command-id", f"stray-{target[0]}")
        assert code == 1
        assert f"unknown_output: the site file has no output {target}" in stderr


def _records(data: Path) -> list[tuple[str, CommandRecord]]:
    out = []
    for session in sessions(data):
        for f in sorted(session.glob("*.mcap")):
            with f.open("rb") as fh:
                for _, channel, message in make_reader(fh).iter_messages():
                    if channel.topic.endswith("/commands"):
                        out.append((channel.topic, decode(message.data, CommandRecord)))
    return out


def _events(data: Path) -> list[Event]:
    out = []
    for session in sessions(data):
        for f in sorted(session.glob("*.mcap")):
            with f.open("rb") as fh:
                for _, _, message in make_reader(fh).iter_messages(topics=["/events"]):
                    out.append(decode(message.data, Event))
    return out


def test_zz_the_recording_holds_every_command_done_and_nothing_refused_for_its_text(
    site: Site,
) -> None:
    """Last (zz): stops the processes and reads what was recorded."""
    assert site.edge.terminate() == 0, site.edge.output()[-2000:]
    assert site.hub.terminate() == 0, site.hub.output()[-2000:]
    records = _records(site.data)
    topics = {topic for topic, _ in records}
    assert topics == {"/pier/commands", "/hub/commands"}, topics
    by_id = {r.command.command_id: (topic, r) for topic, r in records}

    assert not [i for i in by_id if i.startswith("hostile")]
    assert not [r for _, r in records if r.command.reason != KINDLY and "warm" in r.command.reason]

    topic, kindly = by_id["kindly-cli"]
    assert (topic, kindly.command.reason, kindly.reply.applied) == ("/pier/commands", KINDLY, True)
    web = [r for _, r in records if r.command.who == "bob@127.0.0.1"]
    assert [(r.command.output, r.command.reason) for r in web] == [("lamp", KINDLY)]
    assert all(r.command.max_age_s == 5.0 for _, r in records if r.node == "pier")

    stray = [(topic, r.node) for topic, r in records if r.command.command_id.startswith("stray-")]
    assert sorted(stray) == [("/hub/commands", "*"), ("/hub/commands", "hub"),
                             ("/hub/commands", "mallory")]  # fmt: skip

    replays = [r for _, r in records if r.command.command_id == "replay-x"]
    first, again, reused = replays
    assert (first.reply.applied, first.reply.replay) == (True, False)
    assert (again.reply.applied, again.reply.replay) == (True, True)
    assert again.reply.readback == first.reply.readback
    assert again.reply.replied_ns == first.reply.replied_ns
    assert (reused.reply.refusal, reused.reply.replay) == ("not_allowed", False)

    events = _events(site.data)
    tags = [e.tag for e in events if any(f.value == "replay-x" for f in e.fields)]
    assert tags.count("command_applied") == 2, "the hub's and the edge's, once"
    assert tags.count("command_replayed") == 1
    assert tags.count("command_retried") == 1
    log = (site.data / "events.log").read_text(encoding="utf-8")
    assert "hostile" not in log
    assert "\x1b" not in log
    assert KINDLY in log
