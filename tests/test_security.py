"""Security with real processes and real TLS: a site CA (`fleetdaq pki`), a hub whose router
speaks mutual TLS only with the access control list made from the site file, two edges and
operators with their own certificates.

Proved: a client with no certificate, or one from another CA, cannot connect; node shore's
certificate cannot publish on wec's data keys (nothing of it is recorded), cannot forge wec's
acks or liveliness, cannot command an output or ask the hub; a view-role operator cannot
act; the user recorded with a command is the certificate's, not the request's; the fleet
records with no gaps throughout; a private key others may read is refused at start.
"""

from __future__ import annotations

import datetime as dt
import json
import logging
import os
import shutil
import subprocess
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import zenoh
from mcap.reader import make_reader

from fleetdaq.contract.cdr import decode, encode
from fleetdaq.contract.keys import SiteKeys
from fleetdaq.contract.messages import CommandRecord, OutputCommand, make_event
from fleetdaq.contract.wire import BatchEncoder, encode_u64
from fleetdaq.pki import init, issue_hub, issue_node, issue_operator
from fleetdaq.ptp.quality import UNSYNCED
from fleetdaq.read import read_stream
from fleetdaq.runtime.security import TlsFiles, read_certificate
from fleetdaq.runtime.zenoh_session import client_config
from tests.procs import REPO, Proc, free_port, sessions, stream_view, wait_for_port, wait_until

FORGED = 12345.0
SITE = """\
site: sec
security:
  tls: true
  pki_dir: {pki}
  operators: {{ann: control, bob: view}}
hub:
  listen: [tls/127.0.0.1:{port}]
  recorder: {{file_duration_s: 3600, flush_interval_s: 0.2}}
  universal_alarms: {{node_down: false}}
nodes:
  wec:
    streams:
      t8: {{driver: wave_sim, rate_hz: 500, scans_per_batch: 50, channels: [{{name: heave}}]}}
    outputs:
      lamp: {{driver: pcf8574, address: 0x20, pin: 1, safe: 0, sim: {{}}}}
  shore:
    streams:
      env: {{driver: environment_sim, rate_hz: 4, channels: [{{name: air}}]}}
"""


@dataclass
class Site:
    tmp: Path
    pki: Path
    port: int
    cfg: Path
    data: Path
    keys: SiteKeys
    procs: list[Proc]

    @property
    def endpoint(self) -> str:
        return f"tls/127.0.0.1:{self.port}"

    def tls(self, kind: str, name: str) -> TlsFiles:
        stem = self.pki / kind / name
        return TlsFiles(self.pki / "ca.crt", stem.with_suffix(".crt"), stem.with_suffix(".key"))

    def session(self, tls: TlsFiles | None, timeout_ms: int = 5000) -> Any:
        return zenoh.open(client_config([self.endpoint], timeout_ms=timeout_ms, tls=tls))

    def fleetdaq(
        self, operator: str, *args: str, pki: Path | None = None
    ) -> subprocess.CompletedProcess[str]:
        """A fleetdaq command as `operator`, with its pair from `pki` (default the site's)."""
        stem = (pki or self.pki) / "operators" / operator
        env = {
            **os.environ,
            "FLEETDAQ_CERT": str(stem.with_suffix(".crt")),
            "FLEETDAQ_KEY": str(stem.with_suffix(".key")),
        }
        return subprocess.run(
            [sys.executable, "-m", "fleetdaq", *args, "--config", str(self.cfg)],
            cwd=REPO,
            env=env,
            capture_output=True,
            text=True,
            timeout=60,
            check=False,
        )

    def status(self) -> dict[str, Any]:
        r = self.fleetdaq("bob", "rec", "status", "--json")
        assert r.returncode == 0, r.stderr
        return json.loads(r.stdout)  # type: ignore[no-any-return]

    def hub_view(self) -> dict[str, Any]:
        view = self.try_view()
        assert view is not None, "bob may ask the hub's status"
        return view

    def try_view(self) -> dict[str, Any] | None:
        s = self.session(self.tls("operators", "bob"))
        try:
            key = f"{self.keys.hub('status')}/by/bob"
            replies = [r for r in s.get(key, timeout=5) if r.ok is not None]
            return json.loads(replies[0].ok.payload.to_bytes()) if replies else None
        finally:
            s.close()


def small_site(tmp_path: Path, pki: Path, name: str) -> Site:
    """Another site on `pki` (its operator bob only), for a test of its own hub and edges."""
    port = free_port()
    cfg = tmp_path / "site.yaml"
    cfg.write_text(
        SITE.replace("site: sec", f"site: {name}").format(pki=pki, port=port)
        .replace("{ann: control, bob: view}", "{bob: view}")
    )  # fmt: skip
    return Site(tmp_path, pki, port, cfg, tmp_path / "data", SiteKeys(name), [])


@pytest.fixture(scope="module")
def site(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Site]:
    tmp = tmp_path_factory.mktemp("sec")
    pki = tmp / "pki"
    init(pki, "sec", ["127.0.0.1"])
    for node in ("wec", "shore"):
        issue_node(pki, node)
    issue_operator(pki, "ann", "control")
    issue_operator(pki, "bob", "view")
    issue_operator(pki, "eve", "control")  # a valid certificate, not in security.operators
    port = free_port()
    cfg = tmp / "site.yaml"
    cfg.write_text(SITE.format(pki=pki, port=port))
    s = Site(tmp, pki, port, cfg, tmp / "data", SiteKeys("sec"), [])
    try:
        s.procs.append(Proc(["hub", "--config", str(cfg), "--data", str(s.data)], tmp / "hub.log"))
        wait_for_port(port)
        for node in ("wec", "shore"):
            s.procs.append(
                Proc(
                    ["edge", "--config", str(cfg), "--node", node, "--spool", str(tmp / "sp")],
                    tmp / f"{node}.log",
                )
            )
        wait_until(
            lambda: (
                (view := s.try_view()) is not None
                and all(
                    (stream_view(view, n, st) or {}).get("batches", 0) > 5
                    for n, st in (("wec", "t8"), ("shore", "env"))
                )
            ),
            60,
            "both edges recording over mutual TLS",
        )
        yield s
    finally:
        for p in s.procs:
            p.kill()


def test_no_certificate_or_another_ca_cannot_connect(site: Site, tmp_path: Path):
    with pytest.raises(zenoh.ZError):
        site.session(None, timeout_ms=3000)
    plain = f"tcp/127.0.0.1:{site.port}"
    with pytest.raises(zenoh.ZError):
        zenoh.open(client_config([plain], timeout_ms=3000))
    rogue = tmp_path / "rogue"
    init(rogue, "sec", ["127.0.0.1"])
    issue_node(rogue, "wec")  # the right name, from the wrong CA
    forged = TlsFiles(site.pki / "ca.crt", rogue / "nodes/wec.crt", rogue / "nodes/wec.key")
    with pytest.raises(zenoh.ZError):
        site.session(forged, timeout_ms=3000)


def test_a_node_cannot_publish_forge_acks_or_command_for_another(site: Site):
    before = stream_view(site.hub_view(), "wec", "t8")
    assert before is not None
    shore = site.session(site.tls("nodes", "shore"))
    try:
        enc = BatchEncoder("wec", "t8", ("heave",), ("",))
        data = site.keys.data("wec", "t8")
        for i in range(20):  # forged batches, far ahead in sequence, on wec's key
            payload = enc.encode(10**9 + i, time.time_ns(), 2e6, np.full((50, 1), FORGED), UNSYNCED)
            shore.put(data, bytes(payload), attachment=encode_u64(0))
        shore.put(site.keys.ack("wec", "t8"), encode_u64(10**12))  # a forged ack
        shore.put(site.keys.hub("heartbeat"), b"\x00" * 16)
        shore.put(
            site.keys.events("wec"),
            encode(make_event(time.time_ns(), "wec", logging.CRITICAL, "x", "forged", "forged")),
        )
        token = shore.liveliness().declare_token(site.keys.alive("wec"))
        cmd = OutputCommand(
            "f1", "lamp", "set", 1.0, 0.0, "operator", "shore", "", time.time_ns(), 0.0
        )
        asked = [r for r in shore.get(site.keys.out("wec", "lamp"), payload=encode(cmd),
                                      timeout=3) if r.ok is not None]  # fmt: skip
        assert asked == [], "the edge's output is not reachable with a node certificate"
        for key in (site.keys.hub("out"), f"{site.keys.hub('out')}/by/ann"):
            body = json.dumps({"action": "set", "output": "wec/lamp", "value": 1}).encode()
            assert [r for r in shore.get(key, payload=body, timeout=3) if r.ok] == []
        token.undeclare()
    finally:
        shore.close()
    view = site.hub_view()
    after = stream_view(view, "wec", "t8")
    assert after is not None
    assert after["malformed"] == before["malformed"]
    assert after["duplicates"] == before["duplicates"]
    assert after["last_sequence"] < 10**9, "the forged sequences never reached the recorder"
    tags = {e["tag"] for e in view["recent_events"]}
    assert "ack_refused" not in tags, "the forged ack never reached wec"
    assert "forged" not in tags
    assert "heartbeat_refused" not in tags
    lamp = next(o for o in view["nodes"] if o["node"] == "wec")["health"]["outputs"][0]
    assert lamp["commands"] == 0, "no command reached the lamp"


def test_a_view_operator_cannot_act_and_a_control_operator_is_recorded_as_itself(site: Site):
    assert site.fleetdaq("bob", "out", "list").returncode == 0, "view may look"
    r = site.fleetdaq("bob", "out", "set", "wec/lamp", "1")
    assert r.returncode == 2
    assert "view role" in r.stderr
    r = site.fleetdaq("bob", "rec", "split")
    assert r.returncode == 2
    assert "view role" in r.stderr
    r = site.fleetdaq("eve", "rec", "status")
    assert r.returncode == 2, "a certificate not in security.operators gets no answer"
    # ann claims to be somebody else in the request: the certificate's name is recorded.
    s = site.session(site.tls("operators", "ann"))
    try:
        body = {"action": "set", "output": "wec/lamp", "value": 1, "user": "mallory"}
        key = f"{site.keys.hub('out')}/by/ann"
        (reply,) = [r for r in s.get(key, payload=json.dumps(body).encode(), timeout=10) if r.ok]
        answer = json.loads(reply.ok.payload.to_bytes())
        assert answer["ok"], answer
        assert answer["command"]["who"].startswith("ann@")
        # ann cannot ask under bob's name (the router binds the key to the certificate).
        assert [r for r in s.get(f"{site.keys.hub('out')}/by/bob", timeout=3) if r.ok] == []
    finally:
        s.close()
    r = site.fleetdaq("ann", "out", "set", "wec/lamp", "0")
    assert r.returncode == 0, r.stderr


def test_keys_others_may_read_are_refused_at_start(site: Site, tmp_path: Path):
    bad = tmp_path / "site.yaml"
    pki = tmp_path / "pki"
    init(pki, "sec", ["127.0.0.1"])
    issue_node(pki, "wec")
    (pki / "nodes/wec.key").chmod(0o640)
    bad.write_text(SITE.format(pki=pki, port=free_port()))
    for args in (["edge", "--node", "wec"], ["hub", "--data", str(tmp_path / "d")]):
        if args[0] == "hub":
            (pki / "hub.key").chmod(0o644)
        r = subprocess.run(
            [sys.executable, "-m", "fleetdaq", *args, "--config", str(bad)],
            cwd=REPO,
            capture_output=True,
            text=True,
            timeout=60,
            check=False,
        )
        assert r.returncode == 2, r.stderr
        lines = r.stderr.strip().splitlines()
        assert len(lines) == 1, r.stderr
        assert "chmod 600" in lines[0]


def test_the_hubs_certificates_are_watched_and_one_near_its_end_is_an_alarm(
    site: Site, tmp_path: Path
):
    """The site's 10-year CA and 825-day pairs: watched, no alarm; each edge's health says
    when its pair ends. A site whose CA (and so every pair) ends in 10 days:
    ``certificate_expiring/hub`` and ``certificate_expiring/wec`` (from the edge's health) are
    active with the days left, and WARNING events (the hub's, the edge's) name the file and how
    to rotate."""
    view = site.hub_view()
    assert view["certificates"]["hub"]["cn"] == "hub"
    assert view["certificates"]["ca"]["not_after_ns"] > time.time_ns() + 3000 * 86_400e9
    for name in ("certificate_expiring/hub", "certificate_expiring/wec"):
        (alarm,) = [a for a in view["alarms"] if a["name"] == name]
        assert not alarm["active"]
    wec = read_certificate(site.pki / "nodes/wec.crt")["not_after_ns"]
    (node,) = [n for n in view["nodes"] if n["node"] == "wec"]
    assert node["health"]["certificate_not_after_ns"] == wec  # before the CA's, so its own

    pki = tmp_path / "pki"
    init(pki, "soon", ["127.0.0.1"], days=10)
    issue_operator(pki, "bob", "view")
    issue_node(pki, "wec")  # never past the CA: 10 days too
    soon = small_site(tmp_path, pki, "soon")
    port, cfg = soon.port, soon.cfg
    hub = Proc(["hub", "--config", str(cfg), "--data", str(soon.data)], tmp_path / "hub.log")
    edge = None
    try:
        wait_for_port(port)
        edge = Proc(
            ["edge", "--config", str(cfg), "--node", "wec", "--spool", str(tmp_path / "sp")],
            tmp_path / "wec.log",
        )

        def expiring(name: str) -> dict[str, Any] | None:
            v = soon.try_view()
            alarms = [a for a in (v or {}).get("alarms", []) if a["active"]]
            return next((a for a in alarms if a["name"] == name), None)

        for name in ("certificate_expiring/hub", "certificate_expiring/wec"):
            wait_until(lambda n=name: expiring(n) is not None, 30, f"{name} raised")
            alarm = expiring(name)
            assert alarm is not None
            assert 9.0 < alarm["value"] <= 10.0, alarm
            assert alarm["unit"] == "days"
            assert alarm["severity"] == "major"
        events = [e for e in soon.hub_view()["recent_events"] if e["tag"] == "certificate_expiring"]
        which = {
            (e["node"], kv["value"]) for e in events for kv in e["fields"] if kv["key"] == "which"
        }
        assert which == {("hub", "hub"), ("hub", "ca"), ("wec", "ca")}, events
        assert all(e["level"] == logging.WARNING for e in events)
        for e in events:  # the CA: a rotation; the hub's own pair: that pair, same CA
            fix = (
                "pki hub --force"
                if (e["node"], e["fields"][0]["value"]) == ("hub", "hub")
                else ("pki init --force")
            )
            assert fix in e["message"], e
        assert str(pki / "hub.crt") in " ".join(e["message"] for e in events)
        (said,) = [e for e in events if e["node"] == "wec"]
        assert "the hub refuses this node" in said["message"]
        assert str(pki / "ca.crt") in said["message"]
        assert edge.terminate(30) == 0, edge.output()[-3000:]
        assert hub.terminate(30) == 0, hub.output()[-3000:]
    finally:
        if edge is not None:
            edge.kill()
        hub.kill()


def test_the_hubs_pair_issued_again_with_the_same_ca_lets_every_node_back_in(tmp_path: Path):
    """A hub pair that ends in 10 days (the CA goes on): ``certificate_expiring/hub`` says to
    issue the hub's pair again, not to rotate. `fleetdaq pki hub --force` makes it with the
    names of the one it replaces; the hub restarted on it, the edge (its own pair and ca.crt
    untouched, never restarted) is let back in and delivers, and the alarm is clear."""
    pki = tmp_path / "pki"
    init(pki, "renew", ["127.0.0.1"])
    issue_hub(pki, days=10, force=True)
    issue_operator(pki, "bob", "view")
    issue_node(pki, "wec")
    wec_pair = [(pki / "nodes" / f).read_bytes() for f in ("wec.crt", "wec.key")]
    s = small_site(tmp_path, pki, "renew")
    port, cfg = s.port, s.cfg
    args = ["hub", "--config", str(cfg), "--data", str(s.data)]
    hub = Proc(args, tmp_path / "hub.log")
    edge = hub2 = None

    def alarm(view: dict[str, Any] | None) -> dict[str, Any] | None:
        found = [
            a for a in (view or {}).get("alarms", []) if a["name"] == "certificate_expiring/hub"
        ]
        return found[0] if found else None

    def batches(view: dict[str, Any] | None) -> int:
        return int((stream_view(view or {}, "wec", "t8") or {}).get("batches", 0))

    try:
        wait_for_port(port)
        edge = Proc(
            ["edge", "--config", str(cfg), "--node", "wec", "--spool", str(tmp_path / "sp")],
            tmp_path / "wec.log",
        )
        wait_until(lambda: (alarm(s.try_view()) or {}).get("active"), 30, "the alarm raised")
        wait_until(lambda: batches(s.try_view()) > 3, 30, "wec recording")
        hub_said = {"key": "which", "value": "hub"}
        (said,) = [
            e for e in s.hub_view()["recent_events"]
            if e["tag"] == "certificate_expiring" and hub_said in e["fields"]
        ]  # fmt: skip
        assert "fleetdaq pki hub --force" in said["message"]
        assert "the nodes keep theirs" in said["message"]

        r = subprocess.run(
            [sys.executable, "-m", "fleetdaq", "pki", "hub", "--force", "--dir", str(pki)],
            cwd=REPO, capture_output=True, text=True, timeout=60, check=False,
        )  # fmt: skip
        assert r.returncode == 0, r.stderr
        assert "for 127.0.0.1;" in r.stdout  # the names of the pair it replaced
        assert hub.terminate(30) == 0, hub.output()[-3000:]
        hub2 = Proc(args, tmp_path / "hub2.log")
        wait_for_port(port)
        wait_until(lambda: batches(s.try_view()) > 3, 60, "wec back in with its old pair")
        view = s.hub_view()
        assert view["certificates"]["hub"]["not_after_ns"] > time.time_ns() + 800 * 86_400e9
        wait_until(
            lambda: not (alarm(s.try_view()) or {"active": True})["active"], 30, "the alarm clear"
        )
        cleared = alarm(s.hub_view())
        assert cleared is not None
        assert cleared["value"] > 800, cleared
        assert [(pki / "nodes" / f).read_bytes() for f in ("wec.crt", "wec.key")] == wec_pair
        assert edge.terminate(30) == 0, edge.output()[-3000:]
        assert hub2.terminate(30) == 0, hub2.output()[-3000:]
    finally:
        for p in (edge, hub, hub2):
            if p is not None:
                p.kill()


def test_an_operator_whose_certificate_ended_is_told_so_and_how_to_renew_it(
    site: Site, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
):
    """The hub refuses an ended certificate in the TLS handshake, which says nothing of why:
    the command looks at the operator's own pair and says it ended, and the command that makes
    it again."""
    pki = tmp_path / "pki"
    shutil.copytree(site.pki, pki)
    made = dt.datetime.now(dt.UTC) - dt.timedelta(days=10)
    monkeypatch.setattr("fleetdaq.pki._now", lambda: made)
    ended = issue_operator(pki, "bob", "view", days=1, force=True)  # ended 9 days ago
    r = site.fleetdaq("bob", "rec", "status", pki=pki)
    assert r.returncode == 2
    assert f"(your certificate {ended.cert}: expired on " in r.stderr, r.stderr
    assert "make it again: fleetdaq pki issue bob --operator --role view --force)" in r.stderr, (
        r.stderr
    )
    assert "Traceback" not in r.stderr


def test_an_operator_whose_certificate_ends_soon_is_told_and_the_command_runs(
    site: Site, tmp_path: Path
):
    pki = tmp_path / "pki"
    shutil.copytree(site.pki, pki)
    soon = issue_operator(pki, "bob", "view", days=10, force=True)
    r = site.fleetdaq("bob", "rec", "status", "--json", pki=pki)
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout)["recorder"]["state"] == "recording"
    (note,) = r.stderr.splitlines()
    assert note.startswith(f"note: your certificate {soon.cert} expires on "), note
    assert note.endswith("(make it again: fleetdaq pki issue bob --operator --role view --force)")
    # Far from its end: nothing is said.
    r = site.fleetdaq("bob", "rec", "status", "--json")
    assert r.returncode == 0, r.stderr
    assert r.stderr == ""


def test_zz_the_fleet_recorded_without_gaps_and_nothing_forged(site: Site):
    view = site.hub_view()
    for node, stream in (("wec", "t8"), ("shore", "env")):
        v = stream_view(view, node, stream)
        assert v is not None
        assert v["gaps"] == 0, (node, v)
        assert v["lost"] == 0, (node, v)
    codes = [p.terminate() for p in reversed(site.procs)]
    assert codes == [0, 0, 0], [p.output()[-2000:] for p in site.procs]
    (session,) = sessions(site.data)
    t8 = read_stream(session, "wec/t8")
    assert t8.gaps == ()
    assert not np.any(t8.data == FORGED), "no forged sample was recorded"
    who = []
    for f in sorted(session.glob("*.mcap")):
        with f.open("rb") as fh:
            for _, _, m in make_reader(fh).iter_messages(topics=["/wec/commands"]):
                who.append(decode(m.data, CommandRecord).command.who)
    assert who
    assert all(w.startswith("ann@") for w in who), who


def test_no_secret_in_the_recording_events_or_logs(tmp_path: Path, monkeypatch: pytest.MonkeyPatch):
    """The SMTP password (from the environment), the private keys and the dashboard's password
    hashes: in no file the hub writes (the MCAP with its attached config, events.log, the
    journal, the outbox) nor in its log."""
    from fleetdaq.hub.config.load import parse_config
    from fleetdaq.hub.live.web.users import hash_password, write_users
    from fleetdaq.hub.runtime import HubRuntime

    secret = "s3cret-Smtp-Passw0rd"
    monkeypatch.setenv("FLEETDAQ_TEST_SMTP_PASSWORD", secret)
    pki = tmp_path / "pki"
    init(pki, "sec", ["127.0.0.1"])
    users = tmp_path / "users"
    write_users(users, {"ann": hash_password("dashboard-Passw0rd")})
    text = SITE.format(pki=pki, port=free_port()).replace(
        "hub:\n",
        "hub:\n"
        "  notify:\n"
        "    smtp: {host: 127.0.0.1, port: 1, security: starttls, username: hub,\n"
        "           password_env: FLEETDAQ_TEST_SMTP_PASSWORD,\n"
        "           sender: hub@x.example}\n"
        "    groups: {ops: {to: [ops@x.example]}}\n"
        f"  dashboard: {{enabled: true, listen: 127.0.0.1:0, users_file: {users}}}\n",
        1,
    )
    site = parse_config(text, "<test>")
    log_file = tmp_path / "hub.log"
    handler = logging.FileHandler(log_file)
    logging.getLogger().addHandler(handler)
    logging.getLogger().setLevel(logging.DEBUG)
    try:
        with HubRuntime(site, tmp_path / "data") as hub:
            hub.bus.emit(logging.ERROR, "test", "hello", "an event to record")
            hub.recorder.split("test")
    finally:
        logging.getLogger().removeHandler(handler)
    keys = [p.read_bytes() for p in pki.rglob("*.key")]
    key_bodies = [k.split(b"-----")[2].strip()[:40] for k in keys]
    hashes = users.read_text().split(":", 1)[1].strip().encode()
    written = [p for p in (tmp_path / "data").rglob("*") if p.is_file()] + [log_file]
    assert any(p.suffix == ".mcap" for p in written)
    for p in written:
        body = p.read_bytes()
        assert secret.encode() not in body, p
        assert hashes[:30] not in body, p
        for k in key_bodies:
            assert k not in body, p
