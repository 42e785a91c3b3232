"""`fleetdaq status`: the site on one screen, from the hub's status request.

Against a real hub and a real sim edge (each its own process, Zenoh on loopback): all well
(exit 0) with every node and stream on the screen, then the edge gone (exit 1, and the screen
says why), then no hub (exit 2, one line). Against a router of the test's own that answers the
status key with what a stray host could put there: garbage is one line and exit 2, and hostile
text or wrong-typed values never crash the command nor reach the terminal as escape sequences.
The other commands that print a hub's answer (alarms, rules, rec, out, ptp fleet) say in one
line when they cannot read it (a hub of another version), never with a traceback."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from fleetdaq.cli.status import attention, render
from tests.procs import REPO, HubClient, Proc, free_port, node_alive, stream_view, wait_for_port

SITE = """\
site: statustest
hub:
  listen: [tcp/127.0.0.1:{port}]
  recorder: {{file_duration_s: 3600}}
  snapshot: {{enabled: false}}
  dashboard: {{enabled: false}}
  # Nothing here may depend on the host: a CI disk that is nearly full would otherwise be an
  # alarm (rightly) and the "all well" below would not hold.
  universal_alarms: {{disk_nearly_full: false, node_down: {{after_s: 1}}}}
nodes:
  wec:
    streams:
      t8:
        driver: wave_sim
        rate_hz: 1000
        scans_per_batch: 50
        channels: [{{name: heave, unit: m}}, {{name: surge, unit: m}}]
"""


def fleetdaq(*args: str, env: dict[str, str] | None = None) -> subprocess.CompletedProcess[str]:
    """The command line, as a person runs it."""
    return subprocess.run(
        [sys.executable, "-m", "fleetdaq", *args],
        cwd=REPO,
        capture_output=True,
        check=False,
        text=True,
        timeout=60,
        env=env,
    )


def status(cfg: Path, *args: str) -> subprocess.CompletedProcess[str]:
    return fleetdaq("status", "--config", str(cfg), *args)


def test_status_of_a_running_site_then_a_node_gone_then_no_hub(tmp_path: Path) -> None:
    port = free_port()
    cfg = tmp_path / "site.yaml"
    cfg.write_text(SITE.format(port=port))
    hub = Proc(["hub", "--config", str(cfg), "--data", str(tmp_path / "data")], tmp_path / "h.log")
    edge = None
    try:
        wait_for_port(port)
        edge = Proc(
            ["edge", "--config", str(cfg), "--node", "wec", "--spool", str(tmp_path / "spool")],
            tmp_path / "wec.log",
        )
        with HubClient(port, "statustest") as client:
            client.wait(
                lambda s: (v := stream_view(s, "wec", "t8")) and v["batches"] > 5,
                30,
                "batches from the edge",
            )
            client.wait(
                lambda s: s["hub_health"] is not None and s["nodes"][0]["health"] is not None,
                20,
                "the hub's own health and the edge's",
            )

            ok = status(cfg)
            assert ok.returncode == 0, ok.stdout + ok.stderr
            out = ok.stdout
            assert "site statustest" in out
            assert "all well" in out
            lines = out.splitlines()
            wec = next(line for line in lines if line.startswith("wec "))
            assert " yes " in wec
            assert "0.1.0" in wec
            assert " %" in wec
            assert any(line.startswith("hub ") for line in lines), out
            t8 = next(line for line in lines if line.startswith("wec/t8 "))
            assert t8.split()[3] == "1000", t8  # configured scans/s
            assert int(t8.split()[4].replace(",", "")) > 5, t8  # batches
            assert "recorder: recording" in out
            assert "no alarm in alarm" in out

            js = status(cfg, "--json")
            assert js.returncode == 0, js.stderr
            view = json.loads(js.stdout)
            assert [n["node"] for n in view["nodes"]] == ["wec"]

            edge.terminate()
            client.wait(lambda s: not node_alive(s, "wec"), 30, "the edge gone")
            client.wait(
                lambda s: any(
                    a["name"] == "node_down/wec" and a["state"] == "active_unacked"
                    for a in s["alarms"]
                ),
                30,
                "node_down/wec raised",
            )
            down = status(cfg)
            assert down.returncode == 1, down.stdout + down.stderr
            assert "needs attention (2):" in down.stdout
            assert "node wec: not alive" in down.stdout
            assert "alarm node_down/wec: active_unacked (critical)" in down.stdout
            assert "last warnings and errors:" in down.stdout
            assert "WARNING  hub/hub [node_gone]: wec: gone" in down.stdout
            wec = next(line for line in down.stdout.splitlines() if line.startswith("wec "))
            assert " NO " in wec
        assert hub.terminate() == 0, hub.output()[-3000:]
        gone = status(cfg, "--connect", f"tcp/127.0.0.1:{port}")
        assert gone.returncode == 2
        assert gone.stdout == ""
        assert len(gone.stderr.strip().splitlines()) == 1, gone.stderr
        assert "no hub answered" in gone.stderr or "cannot reach the hub" in gone.stderr
        assert ".rs:" not in gone.stderr, "not the Rust source file Zenoh raised it in"
    finally:
        for p in (edge, hub):
            if p is not None:
                p.kill()


# --- what a stray host could answer --------------------------------------------------------


@pytest.fixture
def stray(tmp_path: Path) -> Iterator[tuple[Path, dict[str, bytes]]]:
    """A Zenoh router of the test's own on the site's port answering every hub service's key
    with ``answer["bytes"]``: a stray host on the LAN (without TLS anyone may answer there), or
    a hub of another fleetdaq version."""
    import zenoh

    from fleetdaq.contract.keys import SiteKeys
    from fleetdaq.runtime.zenoh_session import router_config

    port = free_port()
    cfg = tmp_path / "site.yaml"
    cfg.write_text(SITE.format(port=port))
    answer = {"bytes": b""}
    session = zenoh.open(router_config([f"tcp/127.0.0.1:{port}"]))
    # Every hub service: status, alarms, rules, recorder, out.
    queryable = session.declare_queryable(
        SiteKeys("statustest").hub("**"), lambda q: q.reply(q.key_expr, answer["bytes"])
    )
    try:
        yield cfg, answer
    finally:
        queryable.undeclare()
        session.close()


HOSTILE: dict[str, Any] = {
    "site": "\x1b[2Jstatustest",
    "time_ns": 1e300,
    "nodes": [
        {"node": "\x1b]0;owned\x07wec", "alive": "yes", "health": {"host": "x", "streams": [1]}},
        {"node": ["x"], "alive": True, "health": {"time_ns": "now", "uptime_s": "long"}},
        7,
    ],
    "hub_health": {"node": "hub", "host": {"cpu_percent": float("nan"), "disks": [{}, 3]}},
    "streams": [
        {"node": 5, "stream": None, "scan_rate": "fast", "batches": 1e300, "rate_hz": -1},
        "t8",
    ],
    "recorder": {"state": "recording", "files": 3, "current_file_bytes": "big"},
    "partitions": {
        "p\x1b[1m": 7,
        "q": {"alive": True, "recorder": [], "data_disk": {"total_bytes": 0}},
    },
    "failures": [["a"], "b", ["svc", "\x1b[31mdied"]],
    "alarms": [{"state": "active_unacked", "name": "\x1b]52;c;AAAA\x07x", "value": "NaN"}, 4],
    "fleet": {"grandmasters": "abc", "max_abs_offset_ns": {}},
    "recent_events": [
        {"level": 40, "node": "\x1b[2J", "source": "x", "tag": 5, "message": "\x1b]0;t\x07m"},
        {"level": "high", "time_ns": "now"},
        3,
        {"level": 1e300, "message": ["x"]},
    ],
}


def test_a_hostile_answer_is_shown_without_escapes_or_a_crash(
    stray: tuple[Path, dict[str, bytes]],
) -> None:
    cfg, answer = stray
    answer["bytes"] = json.dumps(HOSTILE).encode()
    r = status(cfg)
    assert "Traceback" not in r.stderr, r.stderr
    assert r.returncode == 1, r.stdout + r.stderr  # an alarm in alarm, a failed service
    assert "\x1b" not in r.stdout
    assert "\x07" not in r.stdout
    assert "service svc failed: ?[31mdied" in r.stdout
    assert "partition hub p?[1m: gone" in r.stdout
    assert "ERROR    ?[2J/x [5]: ?]0;t?m" in r.stdout


@pytest.mark.parametrize(
    ("payload", "why"),
    [
        (b"\x00\xffnot json", "is not JSON"),
        (b"[1, 2]", "is not a JSON object"),
        (b'{"site": "statustest"}', "not one this fleetdaq reads"),
    ],
)
def test_an_answer_that_is_not_a_status_is_one_line_and_exit_2(
    stray: tuple[Path, dict[str, bytes]], payload: bytes, why: str
) -> None:
    cfg, answer = stray
    answer["bytes"] = payload
    r = status(cfg)
    assert r.returncode == 2, r.stdout + r.stderr
    assert why in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1, r.stderr


def test_attention_names_each_thing_to_look_at() -> None:
    view = {
        "site": "s",
        "time_ns": 1_800_000_000_000_000_000,
        "nodes": [{"node": "a", "alive": True}, {"node": "b", "alive": False}],
        "recorder": {"state": "stopped"},
        "partitions": {
            "bay2": {"alive": False},
            "bay3": {"alive": True, "recorder": {"state": "disk_error"}},
            "bay4": {"alive": True, "recorder": {"state": "recording"}},
        },
        "failures": [["recorder", "the writer died"]],
        "alarms": [
            {"name": "x", "state": "active_acked", "severity": "major"},
            {"name": "y", "state": "shelved", "severity": "critical"},
            {"name": "z", "state": "normal", "severity": "critical"},
        ],
    }
    assert attention(view) == [
        "node b: not alive (its liveliness token is gone)",
        "recorder: stopped",
        "partition hub bay2: gone (its nodes spool until it returns)",
        "partition hub bay3: recorder disk_error",
        "service recorder failed: the writer died",
        "alarm x: active_acked (major)",
    ]
    lines, todo = render(view, "hub")
    assert lines[-1 - len(todo)] == "needs attention (6):"
    assert "partition bay2: GONE" in lines
    healthy = {
        "site": "s",
        "nodes": [{"node": "a", "alive": True}],
        "recorder": {"state": "recording"},
    }
    lines, todo = render(healthy, "hub")
    assert todo == []
    assert lines[-1].startswith("all well")


def test_a_watch_says_when_the_hub_does_not_answer_and_shows_it_when_it_does(
    stray: tuple[Path, dict[str, bytes]],
) -> None:
    """`--watch`: a hub restarting is a line saying so, not the end of the watch."""
    cfg, answer = stray
    answer["bytes"] = b"junk"  # not an answer: as no hub
    proc = subprocess.Popen(
        [sys.executable, "-m", "fleetdaq", "status", "--config", str(cfg), "--watch", "0.5"],
        cwd=REPO,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        assert proc.stdout is not None
        first = proc.stdout.readline()
        assert first.startswith("no answer at "), first
        answer["bytes"] = json.dumps(
            {"site": "statustest", "recorder": {"state": "recording"}}
        ).encode()
        for line in proc.stdout:  # redrawn once the "hub" answers
            if line.startswith("all well"):
                break
        else:
            raise AssertionError("the watch ended without showing the answer")
        assert proc.poll() is None, "still watching"
    finally:
        proc.send_signal(signal.SIGINT)
        assert proc.wait(30) == 0
    assert proc.stderr is not None
    assert "is not JSON" in proc.stderr.read()


@pytest.mark.parametrize(
    "command",
    [
        ["alarms"],
        ["alarms", "ack", "x"],
        ["rules"],
        ["rec", "status"],
        ["rec", "split"],
        ["out", "list"],
        ["out", "set", "wec/valve", "1"],
    ],
)
@pytest.mark.parametrize("payload", [b'{"ok": true}', b'{"ok": true, "alarms": 5, "reply": []}'])
def test_every_command_reading_a_hub_answer_says_so_in_one_line_when_it_cannot(
    stray: tuple[Path, dict[str, bytes]], command: list[str], payload: bytes
) -> None:
    """What a hub of another fleetdaq version (or not a hub) answers: one line, exit 2."""
    cfg, answer = stray
    answer["bytes"] = payload
    r = fleetdaq(*command, "--config", str(cfg))
    assert "Traceback" not in r.stderr, r.stderr
    assert r.returncode == 2, r.stdout + r.stderr
    assert len(r.stderr.strip().splitlines()) == 1, r.stderr
    assert "the hub's answer is not one this fleetdaq (0.1.0) reads" in r.stderr


def test_ptp_fleet_says_so_in_one_line_when_it_cannot_read_the_fleet(
    stray: tuple[Path, dict[str, bytes]],
) -> None:
    cfg, answer = stray
    answer["bytes"] = b'{"fleet": {"nodes": 5}, "nodes": []}'
    r = fleetdaq("ptp", "fleet", "--config", str(cfg))
    assert r.returncode == 2, r.stdout + r.stderr
    assert len(r.stderr.strip().splitlines()) == 1, r.stderr
    assert "the hub's answer is not one this fleetdaq (0.1.0) reads" in r.stderr


def test_the_site_file_may_come_from_fleetdaq_config_or_where_ansible_puts_it(
    stray: tuple[Path, dict[str, bytes]],
) -> None:
    """On a site's machine, `fleetdaq status` needs no argument: $FLEETDAQ_CONFIG, else
    /etc/fleetdaq/site.yaml (where the deployment puts it)."""
    import os

    from fleetdaq.cli.common import DEFAULT_SITE_FILE

    cfg, answer = stray
    answer["bytes"] = json.dumps(
        {"site": "statustest", "recorder": {"state": "recording"}}
    ).encode()
    env = {k: v for k, v in os.environ.items() if k != "FLEETDAQ_CONFIG"}
    for command in (["status"], ["rules"], ["rec", "status"], ["alarms"], ["ptp", "fleet"]):
        r = fleetdaq(*command, env={**env, "FLEETDAQ_CONFIG": str(cfg)})
        assert "--config" not in r.stderr, (command, r.stderr)
        assert "Traceback" not in r.stderr, (command, r.stderr)
        if command == ["status"]:
            assert r.returncode == 0, r.stdout + r.stderr
            assert "all well" in r.stdout
        if DEFAULT_SITE_FILE.is_file():  # this host has one: it would be taken
            continue
        bare = fleetdaq(*command, env=env)
        assert bare.returncode == 2, (command, bare.stdout + bare.stderr)
        assert "--config" in bare.stderr, (command, bare.stderr)


PARTITIONED_SITE = """\
site: statustest
hub:
  listen: [tcp/127.0.0.1:{main}]
  partitions:
    bay2: {{listen: ["tcp/127.0.0.1:{bay2}"], nodes: [cell]}}
    bay3: {{listen: ["tcp/127.0.0.1:{bay3}"], nodes: [dock]}}
nodes:
  wec: {{streams: {{t8: {{driver: wave_sim, rate_hz: 100, channels: [{{name: heave}}]}}}}}}
  cell: {{streams: {{t8: {{driver: wave_sim, rate_hz: 100, channels: [{{name: heave}}]}}}}}}
  dock: {{streams: {{t8: {{driver: wave_sim, rate_hz: 100, channels: [{{name: heave}}]}}}}}}
"""


def test_with_the_main_hub_silent_each_partition_hub_is_asked_for_its_slice(
    stray: tuple[Path, dict[str, bytes]], tmp_path: Path
) -> None:
    """The main hub's port dead: bay2's (here the stray router, answering hostile text) is
    shown, read as defensively as the main hub's; bay3 (dead too) is one line; exit 2."""
    cfg, answer = stray
    port = int(cfg.read_text().split("tcp/127.0.0.1:", 1)[1].split("]", 1)[0])
    site = tmp_path / "parts.yaml"
    site.write_text(PARTITIONED_SITE.format(main=free_port(), bay2=port, bay3=free_port()))
    answer["bytes"] = json.dumps(HOSTILE).encode()
    r = status(site)
    assert "Traceback" not in r.stderr, r.stderr
    assert r.returncode == 2, r.stdout + r.stderr
    assert r.stderr.startswith("cannot reach the hub at tcp/127.0.0.1:"), r.stderr
    assert "--partition" not in r.stderr  # it asks them itself
    assert "the main hub does not answer; each partition hub, for its own slice:" in r.stdout
    assert "partition hub bay2 · site ?[2Jstatustest" in r.stdout, r.stdout
    assert "service svc failed: ?[31mdied" in r.stdout
    assert "\x1b" not in r.stdout
    assert "\x07" not in r.stdout
    assert "partition hub bay3: no answer either (cannot reach the hub at" in r.stdout, r.stdout

    answer["bytes"] = b'{"site": "statustest"}'  # an answer, but not a status
    r = status(site, "--json")
    assert r.returncode == 2, r.stdout + r.stderr
    out = json.loads(r.stdout)
    assert out["error"].startswith("cannot reach the hub at")
    assert "not one this fleetdaq reads" in out["partitions"]["bay2"]["error"]
    assert out["partitions"]["bay3"]["error"].startswith("cannot reach the hub at")
