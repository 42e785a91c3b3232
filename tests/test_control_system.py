"""Control across machines with real processes: a hub and three edges over Zenoh on loopback.

- `fleetdaq out` sets, refuses (exit 1 with the reason) and lists, through the hub;
- a rule on one node's channel drives a relay on another node;
- the AM layer wait: the hub's rule resumes the weld robot only after the substrate cooled, for
  at least three layers;
- the hub killed with SIGKILL: the edges put their outputs safe within safe_after_s + 1 s on
  their own, and once a hub is back, commands are refused until each output is armed again;
- commands are recorded as typed `CommandRecord` messages in the MCAP.
"""

from __future__ import annotations

import datetime as dt
import json
import re
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from mcap.reader import make_reader

from fleetdaq.contract.cdr import decode
from fleetdaq.contract.messages import CommandRecord
from fleetdaq.read import read_stream
from tests.procs import REPO, HubClient, Proc, free_port, sessions, wait_for_port, wait_until

SAFE_AFTER_S = 2.0
INTERPASS_C = 100.0
SITE = """\
site: ctlsys
hub:
  listen: [tcp/127.0.0.1:{port}]
  recorder: {{file_duration_s: 3600, flush_interval_s: 0.2}}
  dashboard: {{enabled: false}}
  universal_alarms: {{node_down: false, stream_stale: false}}
  interlocks:
    wec_down:
      when: {{node: wec, alive: false}}
      outputs: [pier/lamp]
      force_safe: true
nodes:
  wec:
    streams:
      t8:
        driver: wave_sim
        rate_hz: 200
        scans_per_batch: 20
        wave_period_s: 2
        channels: [{{name: load, unit: kN}}]
  pier:
    control: {{safe_after_s: {safe_after}}}
    streams:
      env: {{driver: environment_sim, rate_hz: 2, channels: [{{name: air, unit: degC}}]}}
    outputs:
      beacon: {{driver: pcf8574, address: 0x20, pin: 0, initial: 0, safe: 1, sim: {{}}}}
      lamp: {{driver: pcf8574, address: 0x20, pin: 1, safe: 0, sim: {{}}}}
      valve: {{driver: mcp4725, address: 0x60, min: 0, max: 3, safe: 0.5, arm_required: true,
              sim: {{}}}}
  am-cell:
    control: {{safe_after_s: {safe_after}}}
    streams:
      tc:
        driver: max31855
        rate_hz: 4
        sim: {{cell: weld1, ambient_c: 24, peak_c: 450}}
        channels: [{{name: substrate, unit: degC}}, {{name: cold_junction, unit: degC}}]
      robot:
        driver: weld_robot_sim
        rate_hz: 4
        cell: weld1
        layer_s: 3
        max_wait_s: 120
        channels: [{{name: welding}}, {{name: layer_done}}, {{name: layer}}, {{name: waits}},
                   {{name: timeouts}}, {{name: last_wait_s, unit: s}}]
    outputs:
      resume: {{driver: weld_robot_resume, cell: weld1, safe: 0}}
rules:
  wave_beacon:
    when: {{channel: wec/t8/load, above: 0}}
    do: [{{set: pier/beacon, value: 1}}]
    on_clear: [{{set: pier/beacon, value: 0}}]
  resume_next_layer:
    when: {{channel: am-cell/tc/substrate, below: {interpass}}}
    for_s: 2
    precondition: {{channel: am-cell/robot/layer_done, above: 0.5}}
    cooldown_s: 2
    do: [{{pulse: am-cell/resume, for_s: 0.3}}]
"""


class Site:
    def __init__(self, tmp: Path) -> None:
        self.tmp = tmp
        self.port = free_port()
        self.cfg = tmp / "site.yaml"
        self.cfg.write_text(
            SITE.format(port=self.port, safe_after=SAFE_AFTER_S, interpass=INTERPASS_C)
        )
        self.data = tmp / "data"
        self.hub: Proc | None = None
        self.edges: dict[str, Proc] = {}

    def start_hub(self, n: int) -> None:
        self.hub = Proc(
            ["hub", "--config", str(self.cfg), "--data", str(self.data)],
            self.tmp / f"hub{n}.log",
        )
        wait_for_port(self.port)

    def start_edges(self) -> None:
        for node in ("wec", "pier", "am-cell"):
            self.edges[node] = Proc(
                ["edge", "--config", str(self.cfg), "--node", node, "--spool",
                 str(self.tmp / "spool")],
                self.tmp / f"{node}.log",
            )  # fmt: skip

    def out(self, *args: str) -> tuple[int, str, str]:
        r = subprocess.run(
            [sys.executable, "-m", "fleetdaq", "out", *args, "--config", str(self.cfg)],
            cwd=REPO,
            capture_output=True,
            text=True,
            timeout=60,
            check=False,
        )
        return r.returncode, r.stdout, r.stderr

    def outputs(self) -> dict[str, Any]:
        code, stdout, stderr = self.out("list", "--json")
        assert code == 0, stderr
        return {r["output"]: r for r in json.loads(stdout)}


@pytest.fixture(scope="module")
def site(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Site]:
    s = Site(tmp_path_factory.mktemp("ctl"))
    try:
        s.start_hub(1)
        s.start_edges()
        with HubClient(s.port, "ctlsys") as hub:
            hub.wait(lambda st: sum(n["alive"] for n in st["nodes"]) == 3, 60, "three nodes alive")
        yield s
    finally:
        for p in [*s.edges.values(), *([s.hub] if s.hub else [])]:
            p.kill()


def state(site: Site, ref: str) -> dict[str, Any]:
    out: dict[str, Any] = site.outputs()[ref]["state"] or {}
    return out


def test_out_set_refuse_and_list_through_the_hub(site: Site):
    listed = site.outputs()
    assert set(listed) == {"pier/beacon", "pier/lamp", "pier/valve", "am-cell/resume"}
    assert listed["pier/valve"]["config"]["arm_required"] is True

    code, stdout, _ = site.out("set", "pier/lamp", "1", "--reason", "test lamp")
    assert code == 0
    assert "applied; readback 1" in stdout
    code, _, stderr = site.out("set", "pier/lamp", "0.5")
    assert code == 1
    assert "not_allowed" in stderr
    code, _, stderr = site.out("set", "pier/valve", "1")
    assert code == 1
    assert "not_armed" in stderr
    assert site.out("arm", "pier/valve")[0] == 0
    code, _, stderr = site.out("set", "pier/valve", "9")
    assert code == 1
    assert "out_of_limits" in stderr
    code, stdout, _ = site.out("set", "pier/valve", "2.5")
    assert code == 0
    readback = float(re.search(r"readback ([\d.]+)", stdout).group(1))  # type: ignore[union-attr]
    assert readback == pytest.approx(2.5, abs=3.3 / 4096), "the DAC's 12-bit step"
    code, _, stderr = site.out("set", "pier/nope", "1")
    assert code == 1
    assert "unknown_output" in stderr
    wait_until(lambda: state(site, "pier/lamp").get("value") == 1.0, 20, "health shows the lamp")


def test_a_rule_on_one_node_drives_a_relay_on_another(site: Site):
    with HubClient(site.port, "ctlsys") as hub:
        rule = hub.wait(
            lambda st: next(
                (r for r in st["rules"]["rules"] if r["name"] == "wave_beacon" and r["fired"] >= 2),
                None,
            ),
            30,
            "the wave rule to fire twice",
        )
        assert re.match(r"pier/beacon set [01]: applied", rule["last_result"]), rule
        events = [e for e in hub.status()["recent_events"] if e["tag"] == "command_applied"]
    readbacks = set()
    deadline = time.monotonic() + 20
    while len(readbacks) < 2 and time.monotonic() < deadline:
        readbacks.add(state(site, "pier/beacon").get("readback"))
    assert readbacks >= {0.0, 1.0}, "the relay on the other node follows the waves"
    assert any("sender" in json.dumps(e) and "rule" in json.dumps(e) for e in events)


def test_the_am_cell_resumes_only_after_cooling_for_three_layers(site: Site):
    with HubClient(site.port, "ctlsys") as hub:
        hub.wait(
            lambda st: next(
                (
                    r["fired"]
                    for r in st["rules"]["rules"]
                    if r["name"] == "resume_next_layer" and r["fired"] >= 3
                ),
                None,
            ),
            150,
            "three resumes by the rule",
        )


def test_hub_killed_outputs_go_safe_and_need_arming_after(site: Site):
    assert site.hub is not None
    assert site.out("set", "pier/lamp", "1")[0] == 0
    killed = time.time()
    site.hub.popen.send_signal(signal.SIGKILL)
    site.hub.popen.wait()
    log = site.edges["pier"].log_path

    def safe_at() -> float | None:
        for line in log.read_text().splitlines():
            m = re.match(r"^(\S+ \S+) .*\[safe_state\]", line)
            if m:
                t = dt.datetime.strptime(m.group(1), "%Y-%m-%d %H:%M:%S,%f").timestamp()
                if t >= killed - 1:
                    return t
        return None

    when = wait_until(safe_at, 20, "the pier's safe state")
    assert when - killed <= SAFE_AFTER_S + 1.0, f"safe {when - killed:.2f} s after the kill"

    site.start_hub(2)
    with HubClient(site.port, "ctlsys") as hub:
        hub.wait(lambda st: sum(n["alive"] for n in st["nodes"]) == 3, 60, "nodes back")
    wait_until(lambda: state(site, "pier/lamp").get("safe_state") is False, 30, "hub heard")
    outputs = site.outputs()
    readback = {k: (v["state"] or {}).get("readback") for k, v in outputs.items()}
    assert readback["pier/lamp"] == 0.0
    assert readback["pier/beacon"] == 1.0, "the beacon's safe value: on (the rule is refused)"
    assert readback["pier/valve"] == pytest.approx(0.5, abs=3.3 / 4096)
    assert not any((v["state"] or {}).get("armed") for v in outputs.values())
    code, _, stderr = site.out("set", "pier/lamp", "1")
    assert code == 1
    assert "not_armed" in stderr
    assert site.out("arm", "pier/lamp")[0] == 0
    assert site.out("set", "pier/lamp", "1")[0] == 0


def test_a_hub_interlock_across_nodes_blocks_and_forces_safe(site: Site):
    wait_until(lambda: state(site, "pier/lamp").get("readback") == 1.0, 20, "the lamp on")
    site.edges["wec"].terminate()
    with HubClient(site.port, "ctlsys") as hub:
        hub.wait(
            lambda st: any(i["name"] == "wec_down" and i["active"] for i in
                           st["rules"]["interlocks"]),
            30,
            "the interlock",
        )  # fmt: skip
    wait_until(lambda: state(site, "pier/lamp").get("readback") == 0.0, 20, "lamp forced safe")
    code, _, stderr = site.out("set", "pier/lamp", "1")
    assert code == 1
    assert "interlock wec_down active" in stderr
    site.edges["wec"] = Proc(
        ["edge", "--config", str(site.cfg), "--node", "wec", "--spool", str(site.tmp / "spool")],
        site.tmp / "wec2.log",
    )
    with HubClient(site.port, "ctlsys") as hub:
        hub.wait(lambda st: not any(i["active"] for i in st["rules"]["interlocks"]), 60, "cleared")
    assert site.out("set", "pier/lamp", "1")[0] == 0


def test_zz_commands_are_recorded_and_every_resume_came_after_cooling(site: Site):
    """Last (zz): stops the processes and reads what was recorded."""
    assert site.hub is not None
    codes = [p.terminate() for p in site.edges.values()]
    codes.append(site.hub.terminate())
    assert codes == [0, 0, 0, 0], [p.output()[-2000:] for p in site.edges.values()]
    records: list[CommandRecord] = []
    for session in sessions(site.data):
        for f in sorted(session.glob("*.mcap")):
            with f.open("rb") as fh:
                for _, channel, message in make_reader(fh).iter_messages(
                    topics=["/pier/commands", "/am_cell/commands"]
                ):
                    assert channel.topic.endswith("/commands")
                    records.append(decode(message.data, CommandRecord))
    by = {(r.node, r.command.output, r.command.sender) for r in records}
    assert ("pier", "lamp", "operator") in by
    assert ("pier", "beacon", "rule") in by
    assert ("am-cell", "resume", "rule") in by
    refused = [r for r in records if not r.reply.applied]
    assert {r.reply.refusal for r in refused} >= {"not_allowed", "not_armed", "out_of_limits"}
    lamp = next(r for r in records if r.command.output == "lamp" and r.reply.applied)
    assert lamp.command.who.count("@") == 1, "who sent it: user@host"
    assert lamp.command.reason == "test lamp"

    # Each resume pulse the rule sent came after the substrate was below the interpass
    # temperature for the rule's 2 s, in acquisition time.
    first = sessions(site.data)[0]
    tc = read_stream(first, "am-cell/tc", channels=["substrate"])
    robot = read_stream(first, "am-cell/robot", channels=["timeouts", "layer"])
    resumes = [
        r.sent_ns
        for r in records
        if r.command.output == "resume" and r.reply.applied and r.node == "am-cell"
        and r.sent_ns < tc.time_ns[-1]
    ]  # fmt: skip
    assert len(resumes) >= 3
    for t in resumes:
        window = (tc.time_ns >= t - 2_000_000_000) & (tc.time_ns < t)
        assert window.sum() >= 6
        assert np.all(tc.data[window, 0] < INTERPASS_C), "resumed while still hot"
    assert np.nanmax(robot.data[:, 1]) >= 3, "three layers"
    assert np.nanmax(robot.data[:, 0]) == 0, "never the fixed pause"
