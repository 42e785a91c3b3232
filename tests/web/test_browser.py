"""The dashboard in a real browser: `fleetdaq demo` (hub + three simulated edges, each its own
process) and headless Debian Chromium driven by Playwright, all inside a network namespace that
has nothing but loopback. What the browser saw is judged here, with what the hub wrote on disk
(the alarm journal, events.log, the recording's files).

Screenshots: ``tests/web/output/`` (not committed).
"""

from __future__ import annotations

import base64
import hashlib
import json
import re
import shutil
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

from fleetdaq.hub.recording.session import ACTIVE_SUFFIX
from tests.procs import REPO, wait_until
from tests.web.netns import Netns, NsProc, ensure_chromium, netns_problem

OUTPUT = Path(__file__).resolve().parent / "output"
NODES = ("wec", "am-cell", "shore")
STREAMS = ("wec/t8", "am-cell/tc", "am-cell/robot", "shore/env")
USER, PASSWORD = "night-shift", "a long night at sea"
VIEWER, VIEWER_PASSWORD = "deck-watch", "only looking at the sea"
"""A user with the view role: sees everything, can do nothing."""
LOGIN_LINE = re.compile(r"dashboard: (\S+)\s+log in as (\S+) / (\S+)")


@dataclass
class Tour:
    result: dict[str, Any]
    url: str
    data: Path
    demo_exit: int
    demo_log: str
    summary: dict[str, Any]
    left_running: list[int]


def needs_a_namespace() -> None:
    problem = netns_problem()
    if problem is not None:
        pytest.skip(f"the browser tests run Chromium in a loopback-only namespace: {problem}")
    ensure_chromium()


def add_user(
    users: Path, user: str = USER, password: str = PASSWORD, role: str = "control"
) -> None:
    """`fleetdaq users add USER --role ROLE` into the file `users`, as an operator would."""
    added = subprocess.run(
        [sys.executable, "-m", "fleetdaq", "users", "add", user, "--role", role,
         "--password-stdin", "--file", str(users)],
        input=password + "\n", capture_output=True, text=True, cwd=REPO, check=False,
    )  # fmt: skip
    assert added.returncode == 0, added.stderr


def start_demo_and_wait_for_login(ns: Netns, tmp: Path, data: Path) -> tuple[NsProc, str, str]:
    demo = ns.start(
        [sys.executable, "-m", "fleetdaq", "demo", "--data", str(data), "--json"],
        tmp / "demo.log",
        stdout=tmp / "demo.json",
    )

    def login_line() -> re.Match[str] | None:
        if demo.popen.poll() is not None:
            raise AssertionError(f"the demo exited: {demo.output()[-3000:]}")
        return LOGIN_LINE.search(demo.output())

    m = wait_until(login_line, 60, "the demo to print the dashboard's address and login")
    return demo, m.group(1), m.group(3)


def run_browser(ns: Netns, tmp: Path, scenario: str, args: dict[str, Any]) -> dict[str, Any]:
    out = tmp / f"{scenario}-out"
    args = {**args, "out": str(out)}
    (tmp / f"{scenario}.json").write_text(json.dumps(args))
    driver = ns.start(
        [sys.executable, "-m", "tests.web.browser", scenario, str(tmp / f"{scenario}.json")],
        tmp / f"{scenario}-browser.log",
    )
    driver.wait(300)
    result: dict[str, Any] = (
        json.loads((out / "result.json").read_text())
        if (out / "result.json").exists()
        else {"ok": False, "error": driver.output()[-4000:]}
    )
    OUTPUT.mkdir(exist_ok=True)
    for png in out.glob("*.png"):
        shutil.copy(png, OUTPUT / f"{scenario}-{png.name}")
    return result


@pytest.fixture(scope="module")
def tour(tmp_path_factory: pytest.TempPathFactory) -> Tour:
    needs_a_namespace()
    tmp = tmp_path_factory.mktemp("dashboard")
    data = tmp / "data"
    with Netns("tour") as ns:
        demo, url, demo_password = start_demo_and_wait_for_login(ns, tmp, data)
        # A user added with the command line while the hub runs: the hub reads the file again.
        add_user(data / "dashboard-users")
        add_user(data / "dashboard-users", VIEWER, VIEWER_PASSWORD, "view")
        result = run_browser(
            ns,
            tmp,
            "tour",
            {
                "url": url, "user": USER, "password": PASSWORD, "demo_user": "demo",
                "demo_password": demo_password, "nodes": list(NODES), "streams": list(STREAMS),
                "fast_stream": "wec/t8", "alarm": "substrate_hot",
                "viewer": VIEWER, "viewer_password": VIEWER_PASSWORD,
            },
        )  # fmt: skip
        demo_exit = demo.terminate(60)
        left = ns.close()
    stdout = (tmp / "demo.json").read_text()
    return Tour(
        result=result,
        url=url,
        data=data,
        demo_exit=demo_exit,
        demo_log=demo.output(),
        summary=json.loads(stdout) if stdout.strip() else {},
        left_running=left,
    )


def completed(t: Tour) -> dict[str, Any]:
    assert t.result["ok"], t.result.get("error")
    return t.result


def test_the_page_loads_and_runs_with_no_outside_network(tour: Tour):
    r = completed(tour)
    assert r["requests"], "the page made requests"
    outside = [u for u in r["requests"] if not u.startswith(tour.url.rstrip("/"))]
    assert outside == [], "every request goes to the hub"
    assert r["failed_requests"] == []
    assert r["console_errors"] == [], "nothing went wrong before the deliberate refusals"
    assert r["console_errors_after"] == [], "and nothing but them after"
    assert r["page_errors"] == []


def test_every_demo_node_and_stream_is_shown(tour: Tour):
    r = completed(tour)
    fleet = {row[0]: row for row in r["fleet"]}
    assert set(fleet) == {*NODES, "hub"}
    assert all(fleet[n][1] == "yes" for n in NODES), fleet
    assert all(fleet[n][2] == "0.1.0" for n in NODES), "each node's version"
    assert all(row[12] == "–" for row in fleet.values()), "the demo has no TLS: no certificate"
    streams = {row[0]: row for row in r["streams"]}
    assert set(streams) == set(STREAMS)
    assert "heave" in streams["wec/t8"][6]
    assert " m" in streams["wec/t8"][6], "values with their units"
    assert "degC" in streams["am-cell/tc"][6]


def test_values_and_plots_change_live(tour: Tour):
    r = completed(tour)
    first, later = r["values"]
    assert first != later
    assert r["plots"] == ["Plot of wec/t8: heave, surge"]
    assert r["plots_after_adding"] == [
        "Plot of wec/t8: heave, surge", "Plot of am-cell/tc: substrate"
    ]  # fmt: skip
    # Drawn at the stream's pace (100 ms batches, ~10 frames/s), not at the 2 Hz state pace.
    assert r["plot_fps"] > 5, r["plot_fps"]
    # A whole frame, then deltas, each applied to the one before: none had to be asked again.
    frames, resyncs = r["plot_frames"]
    assert frames >= 30
    assert resyncs == 0


def test_an_alarm_is_acked_through_the_page_and_its_audit_names_the_user(tour: Tour):
    r = completed(tour)
    name = r["alarm"]
    assert r["ack_toast"].startswith(f"ack {name}: done"), r["ack_toast"]
    assert r["alarm_after_ack"][0] == name
    assert r["alarm_after_ack"][1] in ("active acked", "normal")
    journal = [json.loads(line) for line in (tour.data / "alarms.journal").read_text().splitlines()]
    acks = [j for j in journal if j["name"] == name and j["transition"] == "acked"]
    assert len(acks) == 1, acks
    assert (acks[0]["user"], acks[0]["host"]) == (USER, "127.0.0.1")
    assert acks[0]["note"] == "seen from the dashboard test"
    events = (tour.data / "events.log").read_text()
    assert f"{name} acked by {USER}@127.0.0.1: seen from the dashboard test" in events


def test_an_ack_is_refused_without_a_login_without_the_csrf_token_and_from_another_origin(
    tour: Tour,
):
    r = completed(tour)
    assert r["ack_button_disabled_logged_out"] is True
    assert r["ack_without_login"]["status"] == 401
    assert r["ack_without_csrf"]["status"] == 403
    assert "X-CSRF-Token" in r["ack_without_csrf"]["body"]["error"]
    status, body = r["ack_foreign_origin"]
    assert status == 403
    assert "evil.example" in body["error"]
    assert r["cookie_flags"] == [
        {"name": "fleetdaq_session", "httpOnly": True, "sameSite": "Strict"}
    ]  # fmt: skip
    journal = (tour.data / "alarms.journal").read_text().splitlines()
    acks = [j for j in map(json.loads, journal) if j["transition"] == "acked"]
    assert len(acks) == 1, "only the ack made through the page went through"


def test_a_wrong_password_is_refused_and_said_on_the_page(tour: Tour):
    r = completed(tour)
    assert r["wrong_password_status"] == 401
    assert r["wrong_password_text"] == "wrong user name or password"
    assert f"dashboard login refused for '{USER}'" in (tour.data / "events.log").read_text()


def test_a_split_from_the_page_closes_the_file_and_starts_a_new_one(tour: Tour):
    r = completed(tour)
    assert r["split_toast"].startswith("recorder split: done — closed"), r["split_toast"]
    before, after = r["recorder_before"], r["recorder_after"]
    assert int(after["Files written"]) == int(before["Files written"]) + 1
    assert after["Current file"] != before["Current file"]
    assert before["Current file"].endswith(ACTIVE_SUFFIX)
    closed = before["Current file"].removesuffix(ACTIVE_SUFFIX)
    session = tour.data / before["Session"]
    assert (session / closed).is_file(), "the file the split closed is on disk, finished"
    events = (tour.data / "events.log").read_text()
    assert re.search(rf"{re.escape(closed)} closed on request by {USER}@127\.0\.0\.1", events)
    assert r["split_disabled_after_logout"] is True


def test_a_view_role_login_sees_the_page_with_every_action_disabled(tour: Tour):
    r = completed(tour)["viewer"]
    assert r["view_only_shown"] is True
    assert r["split_disabled"] is True
    assert r["split_title"] == "your role is view: acting needs control"
    assert len(r["action_buttons"]) >= 4, "the recorder's, the alarms', the outputs'"
    assert all(r["action_buttons"]), "every action button disabled"
    assert r["split_by_fetch"]["status"] == 403
    assert "has the view role" in r["split_by_fetch"]["body"]["error"]


def test_the_demo_prints_the_dashboard_address_and_login_and_its_summary_has_it(tour: Tour):
    r = completed(tour)
    assert tour.url == "http://127.0.0.1:8080/"
    assert r["demo_login"] is True
    assert tour.demo_exit == 0, tour.demo_log[-3000:]
    assert tour.summary["dashboard"] == {
        "url": tour.url, "user": "demo", "users_file": str(tour.data / "dashboard-users")
    }  # fmt: skip


def test_nothing_started_by_the_test_is_left_running(tour: Tour):
    assert tour.left_running == []


# --- outputs: needs the edge's outputs (the control branch) ------------------------------------

OUTPUT_SITE = """\
site: webout
security: {{tls: true, pki_dir: {pki}}}
hub:
  listen: [tls/127.0.0.1:7447]
  recorder: {{file_duration_s: 60}}
  dashboard:
    enabled: true
    listen: "127.0.0.1:8080"
    users_file: {users}
    tls: {{cert_file: {pki}/hub.crt, key_file: {pki}/hub.key}}
nodes:
  rig:
    streams:
      env:
        driver: environment_sim
        rate_hz: 2
        channels: [{{name: air, unit: degC}}, {{name: humidity, unit: "%RH"}}]
    outputs:
      valve:
        driver: mcp4725
        unit: V
        min: 0
        max: 3
        safe: 0
        sim: {{}}
"""


def _spki_sha256(cert: Path) -> str:
    """What Chromium's --ignore-certificate-errors-spki-list takes for this certificate."""
    from cryptography import x509
    from cryptography.hazmat.primitives import serialization

    key = x509.load_pem_x509_certificate(cert.read_bytes()).public_key()
    der = key.public_bytes(
        serialization.Encoding.DER, serialization.PublicFormat.SubjectPublicKeyInfo
    )
    return base64.b64encode(hashlib.sha256(der).digest()).decode()


def test_an_output_set_from_the_page_reaches_the_edge_and_its_readback_is_shown(
    tmp_path: Path,
):
    """Over HTTPS (`hub.dashboard.tls`, the site CA's hub pair, as the example site): the
    page, its login (a Secure cookie), its live WebSocket (wss) and an action. The site runs
    mutual TLS too, and the edge's pair ends in 10 days: the Fleet panel says so, amber."""
    needs_a_namespace()
    from fleetdaq import pki

    pki.init(tmp_path / "pki", "webout", ["127.0.0.1"])
    pki.issue_node(tmp_path / "pki", "rig", days=10)
    data, users = tmp_path / "data", tmp_path / "users"
    add_user(users)
    site = tmp_path / "site.yaml"
    site.write_text(OUTPUT_SITE.format(users=users, pki=tmp_path / "pki"))
    checked = subprocess.run(
        [sys.executable, "-m", "fleetdaq", "check", str(site)],
        capture_output=True, text=True, cwd=REPO, check=False,
    )  # fmt: skip
    assert checked.returncode == 0, f"this site needs the edge's outputs: {checked.stderr}"
    with Netns("out") as ns:
        hub = ns.start(
            [sys.executable, "-m", "fleetdaq", "hub", "--config", str(site), "--data", str(data)],
            tmp_path / "hub.log",
        )
        edge = ns.start(
            [sys.executable, "-m", "fleetdaq", "edge", "--config", str(site), "--node", "rig",
             "--spool", str(tmp_path / "spool")],
            tmp_path / "edge.log",
        )  # fmt: skip
        wait_until(
            lambda: "dashboard on https://127.0.0.1:8080/" in hub.output() or hub.popen.poll(),
            60,
            "the hub's dashboard",
        )
        assert hub.popen.poll() is None, hub.output()[-3000:]
        result = run_browser(
            ns,
            tmp_path,
            "outputs",
            {"url": "https://127.0.0.1:8080/", "user": USER, "password": PASSWORD,
             "output": "rig/valve", "value": 1.5,
             "trust_spki": _spki_sha256(tmp_path / "pki" / "hub.crt")},
        )  # fmt: skip
        assert edge.terminate(30) == 0, edge.output()[-3000:]
        assert hub.terminate(30) == 0, hub.output()[-3000:]
        assert ns.close() == []
    assert result["ok"], result.get("error")
    assert "applied" in result["toast"]
    assert set(result["websockets"]) == {"wss://127.0.0.1:8080/api/live"}  # again after login
    certs = {name: (text, cls, title) for name, text, cls, title in result["certificates"]}
    text, cls, title = certs["rig"]
    assert text in ("9 d", "10 d"), certs
    assert "warn" in cls, certs  # its alarm: within 30 days
    assert re.fullmatch(r"ends \d{4}-\d\d-\d\d \d\d:\d\d UTC", title), title
    text, cls, _ = certs["hub"]  # the CA's hub pair: years
    assert re.fullmatch(r"\d+ d", text), certs
    assert int(text.split()[0]) > 300, certs
    assert "warn" not in cls, certs
    assert result["cookies"] == [{"name": "fleetdaq_session", "secure": True, "httpOnly": True}]
    events = (data / "events.log").read_text()
    assert re.search(rf"rig/valve: set 1\.5 applied.*by operator {USER}@127\.0\.0\.1", events)


PARTS_SITE = """\
site: webparts
hub:
  listen: [tcp/127.0.0.1:7447]
  dashboard: {{enabled: true, listen: "127.0.0.1:8080", users_file: {users}}}
  partitions:
    bay2:
      listen: [tcp/127.0.0.1:7448]
      nodes: [cell]
nodes:
  wec:
    streams:
      env: {{driver: environment_sim, rate_hz: 2, channels: [{{name: air, unit: degC}}]}}
  cell:
    streams:
      env: {{driver: environment_sim, rate_hz: 2, channels: [{{name: air, unit: degC}}]}}
"""


def test_a_stop_from_the_page_stops_every_hub_of_a_partitioned_site(tmp_path: Path):
    """A main hub, a partition hub and an edge each: the Fleet panel shows the partition hub's
    machine (hub/bay2), the Recorder panel its recorder, the stop's confirmation says it is for
    every hub, and the stop reaches the partition hub (its answer in the toast, its audit
    naming the page's user)."""
    needs_a_namespace()
    users = tmp_path / "users"
    add_user(users)
    site = tmp_path / "site.yaml"
    site.write_text(PARTS_SITE.format(users=users))

    def fleetdaq(ns: Netns, name: str, *args: str) -> NsProc:
        return ns.start(
            [sys.executable, "-m", "fleetdaq", *args, "--config", str(site)],
            tmp_path / f"{name}.log",
        )

    with Netns("parts") as ns:
        main = fleetdaq(ns, "main", "hub", "--data", str(tmp_path / "main"))
        bay2 = fleetdaq(ns, "bay2", "hub", "--partition", "bay2", "--data", str(tmp_path / "bay2"))
        edges = [
            fleetdaq(ns, node, "edge", "--node", node, "--spool", str(tmp_path / "spool"))
            for node in ("wec", "cell")
        ]
        wait_until(
            lambda: "dashboard on http://127.0.0.1:8080/" in main.output() or main.popen.poll(),
            60,
            "the main hub's dashboard",
        )
        assert main.popen.poll() is None, main.output()[-3000:]
        result = run_browser(
            ns,
            tmp_path,
            "partitions",
            {"url": "http://127.0.0.1:8080/", "user": USER, "password": PASSWORD,
             "partition": "bay2"},
        )  # fmt: skip
        for proc in (*edges, bay2, main):
            assert proc.terminate(30) == 0, proc.output()[-3000:]
        assert ns.close() == []
    assert result["ok"], result.get("error")
    fleet = {row[0]: row for row in result["fleet"]}
    assert set(fleet) == {"wec", "cell", "hub", "hub/bay2"}, fleet
    assert fleet["hub/bay2"][1:3] == ["yes", "0.1.0"], fleet["hub/bay2"]
    assert fleet["hub/bay2"][4].endswith(" %"), "its CPU"
    assert result["after"]["State"] == "stopped"
    assert result["after"]["Partition bay2"].startswith("stopped · ")
    assert re.search(r" · disk [\d.]+ % free$", result["after"]["Partition bay2"])
    assert result["after_class"] == "bad"
    assert "On every hub of the site." in result["dialog"]
    assert "partition bay2: stopped; session " in result["toast"]
    assert re.search(
        rf"hub/bay2/recorder \[recording_stopped\]: recording stopped by {USER}@127\.0\.0\.1",
        (tmp_path / "main" / "events.log").read_text(),
    ), "bay2's stop, naming the page's user, in the main hub's log"
