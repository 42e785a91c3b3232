"""Every operator action is recorded, or not done: alarm actions (ack, shelve, unshelve, disable,
enable) and recorder actions (start, stop, split, snapshot) with hostile text (a lone UTF-16
surrogate, control and bidirectional characters, over-long text) are refused with the reason
before anything changes — alarm state, journal, events.log, recording, files — through a Zenoh
query, the `fleetdaq` command line and the dashboard of a real hub process; the same actions
with ordinary non-ASCII text are done and recorded everywhere."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
import zenoh

from fleetdaq.contract.keys import SiteKeys
from fleetdaq.read import read_alarms
from fleetdaq.runtime.zenoh_session import client_config
from tests.procs import REPO, Proc, free_port, wait_for_port, wait_until
from tests.web.conftest import PASSWORDS, Http, write_cheap_users

SITE = """\
site: actiontext
hub:
  listen: [tcp/127.0.0.1:{port}]
  recorder: {{flush_interval_s: 0.2, file_duration_s: 3600}}
  dashboard: {{enabled: true, listen: "127.0.0.1:{web}", users_file: "{users}"}}
  universal_alarms: {{node_down: false, stream_stale: false, stream_gaps: false,
                      clock_unsynced: false}}
nodes:
  wec:
    streams:
      t8: {{driver: wave_sim, rate_hz: 100, channels: [{{name: heave, unit: m}}]}}
alarms:
  # Raised as soon as the hub looks at its own machine, and active all along.
  hub_memory: {{node: hub, memory_percent_above: 0.01, severity: info}}
"""
ALARM = "hub_memory"

SURROGATE = "\ud800"
HOSTILE = {
    "lone surrogate": ("note " + SURROGATE, "holds a lone UTF-16 surrogate (U+D800)"),
    "escape sequence": ("\x1b[2Jgone", "holds a control character (U+001B) at character 0"),
    "bidi override": ("ok \u202egnp.exe", "holds a bidirectional control (U+202E)"),
    "over-long": ("x" * 501, "must be at most"),
}
NOT_ON_THE_DASHBOARD = "action must be one of ack, shelve, unshelve"
"""Disable and enable (out of service) are the command line's: the dashboard refuses them."""
ORDINARY = "Zoë's layer 12 — 温度 ok 🌊"
OPERATOR_TAGS = re.compile(
    r"\[(alarm_(acked|shelved|unshelved|disabled|enabled)|recording_(started|stopped)|split"
    r"|snapshot|snapshot_failed)\]"
)


@dataclass
class Hub:
    data: Path
    cfg: Path
    session: Any
    keys: SiteKeys
    web: Http
    done: list[tuple[str, str]]
    """(service, note) of every action done, in order (each is in the audit exactly once)."""

    def ask(self, service: str, body: dict[str, Any] | bytes, by: str = "") -> dict[str, Any]:
        """A request as the command line sends it (`body` as JSON, or these very bytes)."""
        payload = body if isinstance(body, bytes) else json.dumps(body).encode()
        key = self.keys.hub(service) + (f"/by/{by}" if by else "")
        for reply in self.session.get(key, payload=payload, timeout=30.0):
            if reply.ok is not None:
                out: dict[str, Any] = json.loads(reply.ok.payload.to_bytes())
                return out
        raise AssertionError(f"no reply on {key}")

    def alarm_state(self) -> str:
        alarms = self.ask("alarms", {"action": "list"})["alarms"]
        return str(next(a for a in alarms if a["name"] == ALARM)["state"])

    def recorder(self) -> dict[str, Any]:
        rec: dict[str, Any] = self.ask("recorder", {"action": "status"})["recorder"]
        return rec

    def cli(self, *args: str | bytes, env: dict[str, str | bytes] | None = None
            ) -> subprocess.CompletedProcess[bytes]:  # fmt: skip
        environ: dict[str | bytes, str | bytes] = {**os.environ, **(env or {})}
        return subprocess.run(
            [sys.executable, "-m", "fleetdaq", *args, "--config", str(self.cfg)],
            cwd=REPO, env=environ, capture_output=True, timeout=120, check=False,  # type: ignore[arg-type]
        )  # fmt: skip

    def operator_lines(self) -> list[str]:
        """events.log's lines of operators' alarm and recorder actions."""
        text = (self.data / "events.log").read_text(encoding="utf-8", errors="replace")
        return [line for line in text.splitlines() if OPERATOR_TAGS.search(line)]

    def audit(self) -> tuple[object, ...]:
        """Everything an action changes, but events.log (written off the request's thread:
        `settled` waits for it)."""
        journal = (self.data / "alarms.journal").read_text(encoding="utf-8").splitlines()
        rec = self.recorder()
        files = sorted(
            str(p.relative_to(self.data))
            for p in self.data.rglob("*")
            if p.parent.name != "cache" and p.name != "cache" and not p.name.startswith("events.")
        )
        return (
            self.alarm_state(),
            [line for line in journal if json.loads(line).get("user")],
            rec["state"],
            rec["session"],
            rec["files"],
            files,
        )

    def settled(self) -> None:
        """events.log holds every action done so far, each once, in order, and nothing else."""

        def caught_up() -> bool:
            return len(self.operator_lines()) >= len(self.done)

        wait_until(caught_up, 30, "events.log to take the actions done")
        lines = self.operator_lines()
        assert len(lines) == len(self.done), "\n".join(lines)
        for line, (_, note) in zip(lines, self.done, strict=True):
            assert note in line, line


@pytest.fixture(scope="module")
def hub(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Hub]:
    tmp = tmp_path_factory.mktemp("action_text")
    port, web = free_port(), free_port()
    users = tmp / "users"
    write_cheap_users(users, PASSWORDS)
    cfg = tmp / "site.yaml"
    cfg.write_text(SITE.format(port=port, web=web, users=users), encoding="utf-8")
    data = tmp / "data"
    proc = Proc(["hub", "--config", str(cfg), "--data", str(data)], tmp / "hub.log")
    session = None
    try:
        wait_for_port(web, timeout=60)
        session = zenoh.open(client_config([f"tcp/127.0.0.1:{port}"], timeout_ms=20_000))
        http = Http(web)
        assert http.login("alice")[0] == 200
        h = Hub(data, cfg, session, SiteKeys("actiontext"), http, [])
        wait_until(lambda: h.alarm_state() == "active_unacked", 60, f"{ALARM} to be raised")
        wait_until(lambda: h.recorder()["state"] == "recording", 30, "the recorder")
        yield h
    finally:
        if session is not None:
            session.close()
        proc.terminate()
        print(proc.output()[-3000:])


Refuse = Callable[[str, str, str], str]
"""(service, action, hostile text) -> the reason the refusal gave."""


def by_zenoh(hub: Hub, field: str = "note", by: str = "") -> Refuse:
    def send(service: str, action: str, text: str) -> str:
        body: dict[str, Any] = {"action": action, "user": "ops", "host": "console", field: text}
        if service == "alarms":
            body.update(names=[ALARM], for_s=600.0)
        reply = hub.ask(service, body, by)
        assert reply["ok"] is False, reply
        return str(reply["error"])

    return send


def by_web(hub: Hub) -> Refuse:
    def send(service: str, action: str, text: str) -> str:
        body: dict[str, Any] = {"action": action, "note": text}
        if service == "alarms":
            body.update(names=[ALARM], for_s=600.0)
        path = "/api/alarms" if service == "alarms" else "/api/recorder"
        status, reply = hub.web.post(path, body)
        assert status == 400, reply
        assert reply["ok"] is False
        return str(reply["error"])

    return send


def by_cli(hub: Hub, note: bytes | None = None, user: bytes | None = None) -> Refuse:
    """The command line with a note typed in a terminal that is not UTF-8 (its bytes reach
    Python as lone surrogates), or run by a login name that is not UTF-8."""

    def send(service: str, action: str, text: str) -> str:
        args: list[str | bytes] = ["alarms", action, ALARM] if service == "alarms" else [
            "rec", action]  # fmt: skip
        if action == "shelve":
            args += ["--for", "10m"]
        args += ["--note", note if note is not None else text]
        env: dict[str, str | bytes] = {"USER": user, "LOGNAME": user} if user else {}
        r = hub.cli(*args, env=env)
        assert r.returncode != 0, r
        assert b"Traceback" not in r.stderr, r.stderr.decode(errors="replace")
        return r.stderr.decode("utf-8", errors="replace")

    return send


def act(hub: Hub, service: str, action: str, note: str, how: str = "zenoh") -> None:
    """Do an action with an ordinary note (through Zenoh or the dashboard) and check it done."""
    rec = hub.recorder()
    if how == "web" and action not in ("disable", "enable"):
        body: dict[str, Any] = {"action": action, "note": note}
        if service == "alarms":
            body.update(names=[ALARM], for_s=600.0)
        status, reply = hub.web.post("/api/alarms" if service == "alarms" else "/api/recorder",
                                     body)  # fmt: skip
        assert status == 200, reply
    else:
        body = {"action": action, "user": "zoë", "host": "pont-l'évêque", "note": note}
        if service == "alarms":
            body.update(names=[ALARM], for_s=600.0)
        reply = hub.ask(service, body)
    assert reply["ok"] is True, reply
    hub.done.append((service, note))
    # The recorder's view follows: the file closed, the next one opened.
    if action == "split":
        wait_until(lambda: len(hub.recorder()["files"]) > len(rec["files"]), 30, "the split")
    if action in ("split", "start"):
        wait_until(lambda: hub.recorder()["current_file"], 30, "the recorder's next file")


def refused_whole(hub: Hub, service: str, action: str, senders: list[tuple[str, Refuse]]
                  ) -> None:  # fmt: skip
    """Each sender's hostile request is refused with the reason, and nothing changes."""
    before = hub.audit()
    for (name, send), (text, why) in zip(senders, HOSTILE.values(), strict=False):
        reason = send(service, action, text)
        if reason != NOT_ON_THE_DASHBOARD:
            assert why in reason, f"{name}: {reason}"
        assert hub.audit() == before, f"{service} {action} through {name} changed something"


CYCLE = [
    ("alarms", "ack", "active_acked"),
    ("alarms", "shelve", "shelved"),
    ("alarms", "unshelve", "active_unacked"),
    ("alarms", "disable", "disabled"),
    ("alarms", "enable", "active_unacked"),
    ("recorder", "split", ""),
    ("recorder", "snapshot", ""),
    ("recorder", "stop", ""),
    ("recorder", "start", ""),
]
"""Each action where it would apply (the alarm is active all along), in the order that makes
the next one apply."""


def run_cycle(hub: Hub, senders: list[tuple[str, Refuse]], how: str) -> None:
    for service, action, state in CYCLE:
        refused_whole(hub, service, action, senders)
        note = f"{action} {how}: {ORDINARY}"
        act(hub, service, action, note, how)
        if state:
            assert hub.alarm_state() == state
        hub.settled()
    assert not list((hub.data / "snapshots").rglob("*.active"))


def test_hostile_text_in_a_zenoh_request_is_refused_before_anything_changes(hub: Hub):
    z = by_zenoh(hub)
    # Every kind of hostile text, in the note, the user and the host field.
    senders = [(f"zenoh note ({k})", z) for k in HOSTILE]
    run_cycle(hub, senders, "zenoh")
    for field in ("user", "host"):
        refused_whole(hub, "alarms", "ack", [(f"zenoh {field}", by_zenoh(hub, field))] * 4)
        refused_whole(hub, "recorder", "split", [(f"zenoh {field}", by_zenoh(hub, field))] * 4)


def test_a_user_name_in_the_key_is_requester_text_too(hub: Hub):
    before = hub.audit()
    for name in ("eve\u202e", "eve\x7f"):
        for service, body in (
            ("alarms", {"action": "ack", "names": [ALARM], "note": ORDINARY}),
            ("recorder", {"action": "split", "note": ORDINARY}),
        ):
            reply = hub.ask(service, body, by=name)
            assert reply["ok"] is False
            assert reply["error"].startswith("the user name in the key holds a"), reply
    assert hub.audit() == before


def test_a_hostile_alarm_name_is_refused_with_the_reason(hub: Hub):
    raw = b'{"action": "ack", "names": ["hub_memory\\ud800"], "user": "ops", "host": "c"}'
    reply = hub.ask("alarms", raw)
    assert reply["error"] == "names[0] holds a lone UTF-16 surrogate (U+D800) at character 10"


def test_hostile_text_from_the_command_line_is_refused_before_anything_changes(hub: Hub):
    senders: list[tuple[str, Refuse]] = [
        ("cli note not UTF-8", by_cli(hub, note=b"layer \xff\xfe")),
        ("cli note escape", by_cli(hub)),
        ("cli login name not UTF-8", by_cli(hub, note=b"fine", user=b"ev\xe9")),
    ]
    for service, action, state in CYCLE:
        before = hub.audit()
        for name, send in senders:
            text = "\x1b[2Jgone" if name == "cli note escape" else ""
            reason = send(service, action, text)
            assert re.search(r"(note|user) holds a (lone UTF-16 surrogate|control character)",
                             reason), f"{name}: {reason}"  # fmt: skip
            assert hub.audit() == before, f"{service} {action} through {name} changed something"
        act(hub, service, action, f"{action} after the cli: {ORDINARY}")
        if state:
            assert hub.alarm_state() == state
        hub.settled()


def test_hostile_text_from_the_dashboard_is_refused_before_anything_changes(hub: Hub):
    w = by_web(hub)
    run_cycle(hub, [(f"web note ({k})", w) for k in HOSTILE], "web")


def test_every_action_done_is_in_the_journal_and_the_recording_with_its_text(hub: Hub):
    hub.settled()
    journal = [
        json.loads(line)
        for line in (hub.data / "alarms.journal").read_text(encoding="utf-8").splitlines()
    ]
    by_operators = [j for j in journal if j["user"]]
    alarm_notes = [note for service, note in hub.done if service == "alarms"]
    assert [j["note"] for j in by_operators] == alarm_notes
    by_web = [(j["transition"], j["user"], j["host"]) for j in by_operators if "web" in j["note"]]
    assert by_web[:3] == [
        ("acked", "alice", "127.0.0.1"),
        ("shelved", "alice", "127.0.0.1"),
        ("unshelved", "alice", "127.0.0.1"),
    ], "the dashboard's actions name the logged-in user and where they are"
    # The recording: stop (files closed), read every session's /alarms back.
    assert hub.ask("recorder", {"action": "stop", "user": "ops", "host": "c"})["ok"]
    recorded = [
        a
        for session in sorted(p for p in hub.data.iterdir() if p.is_dir() and p.name[0] == "2")
        for a in read_alarms(session)
        if a.user
    ]
    assert [a.note for a in recorded] == alarm_notes
    assert all(a.name == ALARM for a in recorded)
    # Every snapshot done holds its note; no snapshot was begun for a refused one.
    snapshots = sorted((hub.data / "snapshots").iterdir())
    assert len(snapshots) == sum(note.startswith("snapshot ") for _, note in hub.done)
    assert not list((hub.data / "snapshots").rglob("*.active"))
