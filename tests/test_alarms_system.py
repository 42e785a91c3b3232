"""Alarms with real parts: a hub and three edges as processes, with simulated faults (an open
thermocouple, an unplugged T8), an edge stalled with SIGSTOP and one killed; operators ack and
shelve through the CLI; the hub is killed with SIGKILL and restarted and still knows every
ack and shelve; every transition is in the recording; the mails reach a real SMTP server
(aiosmtpd, STARTTLS and AUTH) with each group's recipients."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
import zenoh
from rosbags.highlevel import AnyReader

from fleetdaq.contract.keys import SiteKeys
from fleetdaq.runtime.zenoh_session import client_config
from tests.notify.smtp_server import Received, SmtpServer, ThrowawayCA
from tests.procs import REPO, Proc, free_port, wait_for_port

SMTP_PASSWORD = "correct horse battery staple"

SITE = """\
site: alarmsys
hub:
  listen: [tcp/127.0.0.1:{port}]
  universal_alarms:
    node_down: {{severity: critical, after_s: 3}}
    stream_stale: {{severity: critical, after_s: 2}}
  notify:
    smtp: {{host: 127.0.0.1, port: {smtp_port}, security: starttls, ca_file: "{ca_file}",
           username: hub, password_env: FLEETDAQ_SMTP_PASSWORD, sender: hub@alarmsys.example,
           timeout_s: 5}}
    groups:
      ops: {{to: [ops@alarmsys.example], min_severity: critical}}
      cell: {{to: [cell@alarmsys.example, lead@alarmsys.example], min_severity: info,
             nodes: [am-cell]}}
nodes:
  am-cell:
    streams:
      tc:
        driver: max31855
        rate_hz: 4
        sim: {{ambient_c: 24, peak_c: 300, layer_s: 20, cool_s: 15,
              faults: [{{kind: open_circuit, at_s: 3, for_s: 3}}]}}
        channels: [{{name: substrate, unit: degC}}, {{name: cold_junction, unit: degC}}]
  wec:
    streams:
      t8:
        driver: labjack_t8
        rate_hz: 1000
        sim: {{faults: [{{kind: unplug, at_s: 4, for_s: 5}}]}}
        channels: [{{name: heave, unit: m}}, {{name: surge, unit: m}}]
  shore:
    streams:
      env: {{driver: environment_sim, rate_hz: 4, channels: [{{name: air, unit: degC}}]}}
alarms:
  substrate_hot: {{channel: am-cell/tc/substrate, above: 400, deadband: 5, latch: true}}
  # The hub's own machine (any machine uses more than 0.01 % of its memory).
  hub_memory: {{node: hub, memory_percent_above: 0.01, severity: info}}
"""


class Hub:
    def __init__(self, tmp: Path, port: int) -> None:
        self.tmp, self.port = tmp, port
        self.keys = SiteKeys("alarmsys")
        self.cfg = tmp / "site.yaml"

    def alarms(self) -> dict[str, dict[str, Any]]:
        session = zenoh.open(client_config([f"tcp/127.0.0.1:{self.port}"]))
        try:
            for reply in session.get(
                self.keys.hub("alarms"), payload=b'{"action": "list"}', timeout=5.0
            ):
                if reply.ok is not None:
                    out = json.loads(reply.ok.payload.to_bytes())["alarms"]
                    return {a["name"]: a for a in out}
        finally:
            session.close()
        return {}

    def cli(self, *args: str) -> subprocess.CompletedProcess[str]:
        return subprocess.run(
            [sys.executable, "-m", "fleetdaq", "alarms", *args, "--config", str(self.cfg)],
            cwd=REPO,
            capture_output=True,
            text=True,
            timeout=60,
            check=False,
        )


def wait_for(hub: Hub, cond: Callable[[dict[str, dict[str, Any]]], bool], what: str,
             timeout: float = 30.0) -> dict[str, dict[str, Any]]:  # fmt: skip
    deadline = time.monotonic() + timeout
    while True:
        alarms = hub.alarms()
        if alarms and cond(alarms):
            return alarms
        assert time.monotonic() < deadline, f"timed out waiting for {what}: " + json.dumps(
            {n: a["state"] for n, a in alarms.items() if a["state"] != "normal"}
        )
        time.sleep(0.2)


def state(alarms: dict[str, dict[str, Any]], name: str) -> str:
    return str(alarms[name]["state"])


def test_alarms_pass_through_their_states_and_survive_a_hub_kill(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
):
    port = free_port()
    hub = Hub(tmp_path, port)
    ca = ThrowawayCA(tmp_path / "smtp-ca")
    smtp = SmtpServer("starttls", ca, {"hub": SMTP_PASSWORD}).start()
    hub.cfg.write_text(SITE.format(port=port, smtp_port=smtp.port, ca_file=ca.ca_file))
    monkeypatch.setenv("FLEETDAQ_SMTP_PASSWORD", SMTP_PASSWORD)  # the hub process inherits it
    data = tmp_path / "data"

    def start_hub(n: int) -> Proc:
        p = Proc(["hub", "--config", str(hub.cfg), "--data", str(data)], tmp_path / f"hub{n}.log")
        wait_for_port(port)
        return p

    procs: dict[str, Proc] = {}
    try:
        procs["hub"] = start_hub(1)
        for node in ("am-cell", "wec", "shore"):
            procs[node] = Proc(
                ["edge", "--config", str(hub.cfg), "--node", node, "--spool", str(tmp_path / "sp")],
                tmp_path / f"{node}.log",
            )
        # The open thermocouple (3 s after start, for 3 s): the fault alarm is raised, then
        # clears; latched and unacked, it stays returned-unacked.
        wait_for(hub, lambda a: state(a, "substrate_hot.fault") == "active_unacked",
                 "the sensor fault to be raised")  # fmt: skip
        wait_for(hub, lambda a: state(a, "substrate_hot.fault") == "returned_unacked",
                 "the sensor fault to clear, unacked")  # fmt: skip
        wait_for(hub, lambda a: state(a, "hub_memory") == "active_unacked",
                 "the alarm on the hub's own machine")  # fmt: skip
        assert hub.alarms()["hub_memory"]["value"] > 0.01
        # The unplugged T8 (4 s after start, for 5 s): its stream goes stale, then recovers.
        wait_for(hub, lambda a: state(a, "stream_stale/wec/t8") == "active_unacked",
                 "the unplugged T8's stream to go stale", 40)  # fmt: skip
        wait_for(hub, lambda a: state(a, "stream_stale/wec/t8") == "normal",
                 "the replugged T8's stream to recover", 40)  # fmt: skip
        # An edge stalled (SIGSTOP): stale; running again (SIGCONT): cleared.
        os.kill(procs["shore"].popen.pid, signal.SIGSTOP)
        try:
            wait_for(hub, lambda a: state(a, "stream_stale/shore/env") == "active_unacked",
                     "the stalled edge's stream to go stale")  # fmt: skip
        finally:
            os.kill(procs["shore"].popen.pid, signal.SIGCONT)
        wait_for(hub, lambda a: state(a, "stream_stale/shore/env") == "normal",
                 "the resumed edge's stream to clear")  # fmt: skip

        # Operators, through the CLI.
        r = hub.cli("ack", "substrate_hot.fault", "--note", "thermocouple re-seated")
        assert r.returncode == 0, r.stdout + r.stderr
        assert "substrate_hot.fault: ack -> normal" in r.stdout
        r = hub.cli("ack", "substrate_hot.fault")
        assert r.returncode == 1
        assert "nothing to ack: it is normal" in r.stderr
        r = hub.cli("shelve", "stream_stale/shore/env", "--for", "2h", "--note", "pier work")
        assert r.returncode == 0, r.stdout + r.stderr
        r = hub.cli("ack", "no_such_alarm")
        assert r.returncode == 1
        assert "no alarm matches" in r.stderr or "no alarm of that name" in r.stderr

        # A node killed: node_down after 3 s; acked.
        procs["am-cell"].popen.kill()
        procs["am-cell"].popen.wait()
        down = wait_for(hub, lambda a: state(a, "node_down/am-cell") == "active_unacked",
                        "node_down/am-cell")  # fmt: skip
        # (a loaded host may start an edge later than node_down's 3 s: count what is there)
        raises = down["node_down/am-cell"]["count"]
        r = hub.cli("ack", "node_down/*", "--note", "known: cell powered down")
        assert r.returncode == 0, r.stdout + r.stderr
        listed = hub.cli()
        assert listed.returncode == 0
        assert "node_down/am-cell" in listed.stdout
        assert "active_acked" in listed.stdout

        # The hub killed and restarted: acks and shelves are remembered.
        procs["hub"].popen.kill()
        procs["hub"].popen.wait()
        procs["hub"] = start_hub(2)
        alarms = wait_for(hub, lambda a: True, "the restarted hub to answer")
        assert state(alarms, "node_down/am-cell") == "active_acked"
        assert state(alarms, "stream_stale/shore/env") == "shelved"
        assert state(alarms, "substrate_hot.fault") == "normal"
        # ... and the node is still down: it stays acked (no new raise).
        time.sleep(4.0)  # longer than node_down's 3 s, so a wrongly reset alarm would re-raise
        alarms = hub.alarms()
        assert state(alarms, "node_down/am-cell") == "active_acked"
        assert alarms["node_down/am-cell"]["count"] == raises

        # E-mail through a real SMTP server (STARTTLS, AUTH), per group: the sensor fault of
        # am-cell (minor) to the cell group only; the critical stale T8 to ops only.
        def mails_about(name: str, transition: str) -> list[Received]:
            return [
                m
                for m in smtp.handler.received
                if name in m.subject or f"{name} {transition}" in m.text()
            ]

        deadline = time.monotonic() + 60
        while not (mails_about("substrate_hot.fault", "raised")
                   and mails_about("stream_stale/wec/t8", "raised")):  # fmt: skip
            assert time.monotonic() < deadline, [m.subject for m in smtp.handler.received]
            time.sleep(0.2)
    finally:
        codes = {name: p.terminate() for name, p in procs.items() if name != "am-cell"}
        smtp.stop()
    assert codes == {"hub": 0, "wec": 0, "shore": 0}
    for m in smtp.handler.received:
        assert m.tls, m.subject
        assert m.login == "hub", m.subject
        assert m.mail_from == "hub@alarmsys.example"
        assert "alarmsys" in m.subject
    fault = mails_about("substrate_hot.fault", "raised")
    assert {r for m in fault for r in m.rcpt_tos} == {
        "cell@alarmsys.example",
        "lead@alarmsys.example",
    }
    stale = mails_about("stream_stale/wec/t8", "raised")
    assert {r for m in stale for r in m.rcpt_tos} == {"ops@alarmsys.example"}
    assert "critical" in stale[0].subject.lower()

    # Every transition is in the recording, with who did it.
    files = sorted(data.glob("*/*.mcap"))
    seen: list[tuple[str, str, str, str]] = []
    with AnyReader(files) as reader:
        conns = [c for c in reader.connections if c.topic == "/alarms"]
        for c, _, raw in reader.messages(conns):
            m = reader.deserialize(raw, c.msgtype)
            seen.append((m.name, m.transition, m.state, m.user))
    fault = [(t, s) for n, t, s, _ in seen if n == "substrate_hot.fault"]
    assert fault == [
        ("raised", "active_unacked"),
        ("cleared", "returned_unacked"),
        ("acked", "normal"),
    ]
    assert any(n == "stream_stale/shore/env" and t == "shelved" and u for n, t, _, u in seen)
    log = (data / "events.log").read_text()
    assert "substrate_hot.fault acked by" in log
    assert "thermocouple re-seated" in log
