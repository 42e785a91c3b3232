"""The dashboard as part of the hub process: a taken port stops the hub with one line; what a
failed login leaves in events.log and the recording; the Foxglove live view of a closed view."""

from __future__ import annotations

import json
import socket
import subprocess
import sys
from pathlib import Path

import pytest
from rosbags.highlevel import AnyReader

from fleetdaq.hub.live.web.users import hash_password, write_users
from tests.procs import REPO, Proc, free_port, wait_for_port, wait_until
from tests.web.conftest import Http
from tests.web.netns import Netns, netns_problem, run

SITE = """\
site: webport
hub:
  listen: [tcp/127.0.0.1:{router}]
  dashboard: {{enabled: true, listen: "127.0.0.1:{port}"}}
nodes:
  wec:
    streams:
      t8: {{driver: wave_sim, rate_hz: 100, channels: [{{name: heave, unit: m}}]}}
"""


def test_a_hub_whose_dashboard_port_is_taken_does_not_start_and_says_why_in_one_line(
    tmp_path: Path,
):
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        port = s.getsockname()[1]
        site = tmp_path / "site.yaml"
        site.write_text(SITE.format(router=free_port(), port=port))
        r = subprocess.run(
            [sys.executable, "-m", "fleetdaq", "hub", "--config", str(site), "--data",
             str(tmp_path / "data")],
            cwd=REPO, capture_output=True, text=True, timeout=120, check=False,
        )  # fmt: skip
    assert r.returncode == 1
    assert "Traceback" not in r.stderr
    last = r.stderr.strip().splitlines()[-1]
    assert last == (
        f"dashboard: cannot listen on 127.0.0.1:{port}: the address is in use (another hub or "
        "program); set hub.dashboard.listen to a free port, or hub.dashboard.enabled: false"
    )


TYPED = "Correct-Horse-Battery-9"
"""A password typed into the user-name field."""


def test_a_login_with_a_name_that_is_nobodys_leaves_it_in_no_file_the_hub_writes(tmp_path: Path):
    users = tmp_path / "users"
    write_users(users, {"ann": hash_password("ann-password")}, {"ann": "control"})
    port = free_port()
    site = tmp_path / "site.yaml"
    site.write_text(
        SITE.format(router=free_port(), port=port).replace(
            "dashboard: {", f"dashboard: {{users_file: {users}, "
        )
    )
    data = tmp_path / "data"
    hub = Proc(["hub", "--config", str(site), "--data", str(data)], tmp_path / "hub.log")
    try:
        wait_for_port(port, 60)
        http = Http(port)
        assert http.login(TYPED, "ann-password")[0] == 401
        assert http.login("ann", "not-her-password")[0] == 401
        events_log = data / "events.log"
        wait_until(
            lambda: events_log.exists() and "login refused for 'ann'" in events_log.read_text(),
            30,
            "both refusals in events.log",
        )
    finally:
        code = hub.terminate(60)
    assert code == 0, hub.output()[-3000:]
    log = events_log.read_text()
    assert "dashboard login refused for an unknown user name from 127.0.0.1" in log
    assert TYPED not in log
    assert TYPED not in hub.output(), "nor in the hub's own log"
    files = sorted(data.glob("*/*.mcap"))
    assert files, "the hub recorded"
    with AnyReader(files) as reader:
        conns = [c for c in reader.connections if c.topic == "/events"]
        recorded = [reader.deserialize(raw, c.msgtype) for c, _, raw in reader.messages(conns)]
    refused = [e for e in recorded if e.tag == "login_failed"]
    assert [e.message.split(" (")[0] for e in refused] == [
        "dashboard login refused for an unknown user name from 127.0.0.1",
        "dashboard login refused for 'ann' from 127.0.0.1",
    ]
    assert not any(TYPED in f.read_bytes().decode("latin-1") for f in files)


def test_a_closed_view_with_foxglove_on_the_lan_stops_the_hub_with_one_line(tmp_path: Path):
    site = tmp_path / "site.yaml"
    site.write_text(
        SITE.format(router=free_port(), port=free_port()).replace(
            "dashboard: {",
            "dashboard: {open_view: false, foxglove: {enabled: true, listen: '0.0.0.0:8765'}, ",
        )
    )
    r = subprocess.run(
        [sys.executable, "-m", "fleetdaq", "hub", "--config", str(site), "--data",
         str(tmp_path / "data")],
        cwd=REPO, capture_output=True, text=True, timeout=120, check=False,
    )  # fmt: skip
    assert r.returncode == 2
    assert "Traceback" not in r.stderr
    (line,) = r.stderr.strip().splitlines()
    assert line.startswith(f"{site}: hub.dashboard: ")
    assert "foxglove.listen 0.0.0.0:8765 would show every stream to anyone" in line
    assert not (tmp_path / "data").exists() or not any((tmp_path / "data").iterdir())


LAN = "10.251.0.1"
"""The hub's address on its own network: a veth inside the test's namespace, nowhere else."""

PROBE = """\
import json, socket, sys, time
targets = json.loads(sys.argv[1])

def reach(host, port):
    try:
        socket.create_connection((host, port), timeout=5).close()
        return "open"
    except ConnectionRefusedError:
        return "refused"
    except OSError as err:
        return f"error: {err}"

deadline = time.monotonic() + 90
for ready in (targets[0], targets[-1]):  # the hub serves both (they start one after the other)
    while reach(*ready) != "open":
        if time.monotonic() > deadline:
            sys.exit("the hub never served " + repr(ready))
        time.sleep(0.2)
print(json.dumps({f"{h}:{p}": reach(h, p) for h, p in targets}))
"""


def test_with_the_view_closed_foxglove_is_not_reachable_at_the_hubs_lan_address(tmp_path: Path):
    problem = netns_problem()
    if problem is not None:
        pytest.skip(f"needs a network namespace of its own: {problem}")
    users = tmp_path / "users"
    write_users(users, {"ann": hash_password("ann-password")}, {"ann": "control"})
    dash, fox = free_port(), free_port()
    site = tmp_path / "site.yaml"
    site.write_text(
        SITE.format(router=free_port(), port=dash)
        .replace(f'"127.0.0.1:{dash}"', f'"0.0.0.0:{dash}"')
        .replace(
            "dashboard: {",
            f"dashboard: {{users_file: {users}, open_view: false, "
            f"foxglove: {{enabled: true, listen: '127.0.0.1:{fox}'}}, ",
        )
    )
    with Netns("fox") as ns:
        run("ip", "-n", ns.name, "link", "add", "fdqlan0", "type", "veth", "peer", "fdqlan1")
        run("ip", "-n", ns.name, "addr", "add", f"{LAN}/24", "dev", "fdqlan0")
        for link in ("fdqlan0", "fdqlan1"):
            run("ip", "-n", ns.name, "link", "set", link, "up")
        hub = ns.start(
            [sys.executable, "-m", "fleetdaq", "hub", "--config", str(site), "--data",
             str(tmp_path / "data")],
            tmp_path / "hub.log",
        )  # fmt: skip
        targets = [["127.0.0.1", fox], [LAN, fox], [LAN, dash]]
        probe = ns.start(
            [sys.executable, "-c", PROBE, json.dumps(targets)],
            tmp_path / "probe.log",
            stdout=tmp_path / "probe.json",
        )
        assert probe.wait(120) == 0, (probe.output(), hub.output()[-3000:])
        assert hub.terminate(60) == 0, hub.output()[-3000:]
    reached = json.loads((tmp_path / "probe.json").read_text())
    assert reached == {
        f"127.0.0.1:{fox}": "open",  # this machine (and an SSH tunnel to it) sees it
        f"{LAN}:{fox}": "refused",  # the network does not
        f"{LAN}:{dash}": "open",  # while the hub is reachable there: the dashboard's login
    }
