"""``fleetdaq fleet status`` and ``fleet logs`` as an operator runs them, against real OpenSSH
servers on loopback (one per "host", each with its own host key), a real hub, and each host's
own fleetdaq answering ``--version``, ``ptp status`` and ``rec status``.

The command runs with HOME in tmp (no ~/.ssh of the machine's, nothing written there) and no
SSH agent: only the test's key (``--identity``) and known_hosts (``--known-hosts``) count."""

from __future__ import annotations

import json
import os
import pwd
import shutil
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
import yaml

from tests.fleet.hosts import SITE_FILE, USER, VENV, Sshd, bin_without, ensure_sshd, keygen
from tests.procs import REPO, Proc, free_port, wait_for_port

SITE = """\
site: fleettest
hub: {{listen: [tcp/127.0.0.1:{port}], recorder: {{file_duration_s: 600}}}}
nodes:
  edge-a:
    streams:
      env: {{driver: environment_sim, rate_hz: 1, channels: [{{name: air, unit: degC}}]}}
  edge-b:
    streams:
      env: {{driver: environment_sim, rate_hz: 1, channels: [{{name: air, unit: degC}}]}}
"""


@dataclass
class Fleet:
    root: Path
    home: Path
    key: Path
    site: Path
    hub: Sshd
    a: Sshd
    b: Sshd
    spool_a: int
    spool_b: int
    known_hosts: Path
    hub_proc: Proc

    def host(self, sshd: Sshd, **extra: Any) -> dict[str, Any]:
        return {"ansible_port": sshd.port, "fleetdaq_prefix": str(sshd.fs), **extra}

    def inventory(
        self,
        name: str,
        hub: dict[str, Any] | None = None,
        edges: dict[str, Any] | None = None,
    ) -> Path:
        doc = {
            "all": {
                "vars": {
                    "ansible_host": "127.0.0.1",
                    "ansible_user": USER,
                    "fleetdaq_venv": VENV,
                    "fleetdaq_site_file": SITE_FILE,
                },
                "children": {
                    "hub": {"hosts": hub or {"hub": self.host(self.hub)}},
                    "edges": {
                        "hosts": edges
                        or {
                            "pi-a": self.host(self.a, fleetdaq_node="edge-a"),
                            "edge-b": self.host(self.b),
                        }
                    },
                },
            }
        }
        path = self.root / f"{name}.yml"
        path.write_text(yaml.safe_dump(doc, sort_keys=False))
        return path

    def known(self, name: str, *lines: str) -> Path:
        path = self.root / f"{name}.known_hosts"
        path.write_text("".join(line + "\n" for line in lines))
        return path

    def run(self, *args: str, timeout: float = 180) -> subprocess.CompletedProcess[str]:
        env = {k: v for k, v in os.environ.items() if k not in ("SSH_AUTH_SOCK", "SSH_AGENT_PID")}
        env.update(HOME=str(self.home), PYTHONPATH=str(REPO))
        return subprocess.run(
            [sys.executable, "-m", "fleetdaq", "fleet", *args],
            cwd=REPO,
            env=env,
            capture_output=True,
            text=True,
            timeout=timeout,
            check=False,
        )

    def status(self, inventory: Path, *args: str, known: Path | None = None) -> Any:
        r = self.run(
            "status",
            "-i",
            str(inventory),
            "--known-hosts",
            str(known or self.known_hosts),
            "--identity",
            str(self.key),
            *args,
        )
        return r


@pytest.fixture(scope="module")
def fleet(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Fleet]:
    ensure_sshd()
    root = tmp_path_factory.mktemp("fleet")
    home = root / "home"
    home.mkdir()
    key = root / "client_ed25519"
    public = keygen(key)
    site_text = SITE.format(port=free_port())
    site = root / "site.yaml"
    site.write_text(site_text)
    started: list[Sshd] = []
    hub_proc: Proc | None = None
    try:
        for name in ("hub", "a", "b"):
            started.append(Sshd(root / name, public))
        hub, a, b = started
        for s in started:
            s.install_fleetdaq(site_text)
        spool_a = a.spool("edge-a", "env", [70_001, 3_333]) + a.spool("edge-a", "other", [17])
        spool_b = b.spool("edge-b", "env", [123_456])
        port = int(site_text.split("tcp/127.0.0.1:")[1].split("]")[0])
        hub_proc = Proc(
            ["hub", "--config", str(site), "--data", str(hub.data_dir())], root / "hub.log"
        )
        wait_for_port(port, timeout=60)
        known = root / "all.known_hosts"
        # What real files hold besides plain lines: a CA, a line of some other tool, a comment.
        odd = (
            f"@cert-authority *.example.com {public}\n"
            "garbage ssh-ed25519 not-base64!!\n"
            "# a comment\n"
        )
        known.write_text(odd + "".join(s.known_hosts_line() + "\n" for s in started))
        yield Fleet(root, home, key, site, hub, a, b, spool_a, spool_b, known, hub_proc)
    finally:
        if hub_proc is not None:
            hub_proc.terminate()
        for s in started:
            s.stop()
    assert not (home / ".ssh").exists(), "nothing is written to the user's ~/.ssh"


def _fingerprint(public_key: str, tmp: Path) -> str:
    pub = tmp / "fp.pub"
    pub.write_text(public_key + "\n")
    out = subprocess.run(
        ["ssh-keygen", "-l", "-E", "sha256", "-f", str(pub)],
        capture_output=True,
        text=True,
        check=True,
    ).stdout
    return out.split()[1]


def _hosts(out: str) -> dict[str, dict[str, Any]]:
    return {h["host"]: h for h in json.loads(out)["hosts"]}


def _local_version() -> str:
    r = subprocess.run(
        [sys.executable, "-m", "fleetdaq", "--version"],
        cwd=REPO,
        capture_output=True,
        text=True,
        check=True,
    )
    return r.stdout.strip().rpartition(" ")[2]


def test_status_of_the_hub_and_two_edges_reports_what_each_host_says(fleet: Fleet):
    inv = fleet.inventory("full")
    r = fleet.status(inv, "--json", "--config", str(fleet.site))
    assert r.returncode == 0, r.stdout + r.stderr
    assert "Traceback" not in r.stderr
    out = json.loads(r.stdout)
    assert out["healthy"] is True
    hosts = _hosts(r.stdout)
    assert list(hosts) == ["hub", "pi-a", "edge-b"]
    version = _local_version()
    for h in hosts.values():
        assert h["reachable"], h
        assert h["healthy"], h
        assert h["version"] == version
        assert h["port"] in (fleet.hub.port, fleet.a.port, fleet.b.port)
        # This machine is the host: its uptime, as /proc says it (the host answered it).
        assert abs(h["uptime_s"] - float(Path("/proc/uptime").read_text().split()[0])) < 120
        if not Path("/run/systemd/system").is_dir():
            assert h["systemd"] is False
            assert h["units"] == []
            assert "no systemd on this host: services not checked" in h["notes"]
        # No PTP in this inventory: each host's own `ptp status` is shown, not held against it.
        assert h["time"]["state"] in ("freerun", "holdover", "locked")
        assert h["time"]["expected"] is False
    assert hosts["pi-a"]["node"] == "edge-a"
    assert hosts["edge-b"]["node"] == "edge-b"
    assert hosts["pi-a"]["spool_bytes"] == fleet.spool_a
    assert hosts["edge-b"]["spool_bytes"] == fleet.spool_b
    assert hosts["hub"]["spool_bytes"] is None
    (data,) = hosts["hub"]["dirs"]
    assert data["role"] == "data"
    assert data["path"] == str(fleet.hub.data_dir())
    assert data["exists"]
    assert data["bytes"] > 0
    usage = shutil.disk_usage(fleet.hub.data_dir())
    assert abs(data["free_bytes"] - usage.free) < 0.02 * usage.total
    assert abs(data["total_bytes"] - usage.total) < 0.02 * usage.total
    recorder = hosts["hub"]["recorder"]
    assert recorder["state"] == "recording"
    current = Path(recorder["current_file"])
    assert current.is_relative_to(fleet.hub.data_dir())
    assert current.name.endswith(".mcap.active")
    assert current.exists()
    assert hosts["pi-a"]["recorder"] is None

    table = fleet.status(inv)
    assert table.returncode == 0, table.stdout + table.stderr
    for word in ("hub", "pi-a (edge-a)", "edge-b", "recording", current.name, version):
        assert word in table.stdout, (word, table.stdout)
    assert "3 of 3 hosts healthy" in table.stdout


def test_an_unreachable_host_says_why_and_the_others_still_answer(fleet: Fleet):
    closed = free_port()  # nothing listens there
    inv = fleet.inventory(
        "one-down",
        edges={
            "pi-a": fleet.host(fleet.a, fleetdaq_node="edge-a"),
            "edge-b": {"ansible_port": closed, "fleetdaq_prefix": str(fleet.b.fs)},
        },
    )
    r = fleet.status(inv, "--json")
    assert r.returncode == 1, r.stdout + r.stderr
    hosts = _hosts(r.stdout)
    down = hosts["edge-b"]
    assert down["reachable"] is False
    assert down["healthy"] is False
    assert down["unreachable"]["kind"] == "refused"
    assert f"connection refused at 127.0.0.1:{closed}" in down["unreachable"]["message"]
    assert down["version"] is None
    assert down["spool_bytes"] is None
    assert hosts["hub"]["healthy"]
    assert hosts["pi-a"]["healthy"]
    assert hosts["pi-a"]["spool_bytes"] == fleet.spool_a
    assert hosts["hub"]["recorder"]["state"] == "recording"

    table = fleet.status(inv)
    assert table.returncode == 1
    assert f"✗ edge-b: connection refused at 127.0.0.1:{closed}" in table.stdout
    assert "2 of 3 hosts healthy" in table.stdout


def test_hosts_that_never_answer_time_out_in_parallel(fleet: Fleet):
    """Two "hosts" accept TCP but never speak SSH: each is given up after --timeout, both at
    once (one after the other would take twice as long), while a real host answers in full."""
    silent = [socket.create_server(("127.0.0.1", 0)) for _ in range(2)]
    try:
        ports = [s.getsockname()[1] for s in silent]
        inv = fleet.inventory(
            "silent",
            hub={"hub": {"ansible_port": ports[0]}},
            edges={
                "pi-a": fleet.host(fleet.a, fleetdaq_node="edge-a"),
                "edge-b": {"ansible_port": ports[1]},
            },
        )
        timeout = 6.0
        start = time.monotonic()
        r = fleet.status(inv, "--json", "--timeout", str(timeout))
        elapsed = time.monotonic() - start
    finally:
        for s in silent:
            s.close()
    assert r.returncode == 1, r.stdout + r.stderr
    hosts = _hosts(r.stdout)
    for name, port in (("hub", ports[0]), ("edge-b", ports[1])):
        assert hosts[name]["unreachable"]["kind"] == "timeout", hosts[name]
        assert (
            f"127.0.0.1:{port} accepted the connection but did not complete an SSH"
            in (hosts[name]["unreachable"]["message"])
        )
    assert hosts["pi-a"]["healthy"]
    assert hosts["pi-a"]["spool_bytes"] == fleet.spool_a
    assert timeout <= elapsed < 2 * timeout, elapsed


def test_a_host_whose_key_is_not_known_is_refused_with_how_to_add_it(fleet: Fleet):
    inv = fleet.inventory("full")
    known = fleet.known("no-b", fleet.hub.known_hosts_line(), fleet.a.known_hosts_line())
    before = known.read_text()
    r = fleet.status(inv, "--json", known=known)
    assert r.returncode == 1, r.stdout + r.stderr
    hosts = _hosts(r.stdout)
    b = hosts["edge-b"]
    assert b["unreachable"]["kind"] == "host key unknown"
    message = b["unreachable"]["message"]
    fp = _fingerprint(fleet.b.host_key_public, fleet.root)
    assert f"host key of [127.0.0.1]:{fleet.b.port} is not in known_hosts" in message
    assert f"ssh-ed25519 {fp}" in message
    assert f"ssh-keyscan -p {fleet.b.port} -t ssh-ed25519 127.0.0.1 >> {known}" in message
    assert f"ssh -p {fleet.b.port} {USER}@127.0.0.1" in message
    assert hosts["hub"]["healthy"]
    assert hosts["pi-a"]["healthy"]
    assert known.read_text() == before, "a key is never added silently"
    assert b["version"] is None

    # Added as the message says, the same host is let in.
    scan = subprocess.run(
        ["ssh-keyscan", "-p", str(fleet.b.port), "-t", "ssh-ed25519", "127.0.0.1"],
        capture_output=True,
        text=True,
        timeout=30,
        check=True,
    ).stdout
    with known.open("a") as f:
        f.write(scan)
    # As Debian's ssh writes it (HashKnownHosts yes): hashed names are found too.
    subprocess.run(["ssh-keygen", "-H", "-f", str(known)], capture_output=True, check=True)
    assert "[127.0.0.1]" not in known.read_text()
    again = fleet.status(inv, "--json", known=known)
    assert again.returncode == 0, again.stdout + again.stderr


def test_a_changed_host_key_is_refused_with_both_fingerprints(fleet: Fleet):
    other = keygen(fleet.root / "impostor_ed25519")
    known = fleet.known(
        "changed",
        fleet.hub.known_hosts_line(),
        fleet.a.known_hosts_line(other),
        fleet.b.known_hosts_line(),
    )
    r = fleet.status(fleet.inventory("full"), "--json", known=known)
    assert r.returncode == 1, r.stdout + r.stderr
    hosts = _hosts(r.stdout)
    a = hosts["pi-a"]
    assert a["unreachable"]["kind"] == "host key changed"
    message = a["unreachable"]["message"]
    assert f"host key of [127.0.0.1]:{fleet.a.port} has CHANGED" in message
    assert f"known_hosts has ssh-ed25519 {_fingerprint(other, fleet.root)}" in message
    assert f"the host offers ssh-ed25519 {_fingerprint(fleet.a.host_key_public, fleet.root)}" in (
        message
    )
    assert f"ssh-keygen -R '[127.0.0.1]:{fleet.a.port}'" in message
    assert a["version"] is None
    assert a["spool_bytes"] is None
    assert hosts["hub"]["healthy"]
    assert hosts["edge-b"]["healthy"]


def test_a_revoked_host_key_is_refused_even_when_listed(fleet: Fleet):
    known = fleet.known(
        "revoked",
        fleet.hub.known_hosts_line(),
        fleet.a.known_hosts_line(),
        fleet.b.known_hosts_line(),
        "@revoked * " + fleet.b.host_key_public,
    )
    r = fleet.status(fleet.inventory("full"), "--json", known=known)
    assert r.returncode == 1, r.stdout + r.stderr
    hosts = _hosts(r.stdout)
    b = hosts["edge-b"]
    assert b["unreachable"]["kind"] == "host key revoked"
    assert f"host key of [127.0.0.1]:{fleet.b.port}" in b["unreachable"]["message"]
    assert hosts["hub"]["healthy"]
    assert hosts["pi-a"]["healthy"]


def test_a_key_the_host_does_not_accept_is_auth_failed(fleet: Fleet):
    stranger = fleet.root / "stranger_ed25519"
    keygen(stranger)
    r = fleet.run(
        "status",
        "-i",
        str(fleet.inventory("full")),
        "--known-hosts",
        str(fleet.known_hosts),
        "--identity",
        str(stranger),
        "--json",
    )
    assert r.returncode == 1, r.stdout + r.stderr
    for h in _hosts(r.stdout).values():
        assert h["unreachable"]["kind"] == "auth failed"
        assert f"{USER}@127.0.0.1:{h['port']} refused our keys" in h["unreachable"]["message"]


def test_a_host_set_up_for_ptp_without_time_sync_is_unhealthy(fleet: Fleet):
    inv = fleet.inventory(
        "ptp",
        edges={
            "pi-a": fleet.host(fleet.a, fleetdaq_node="edge-a", fleetdaq_ptp_interface="lo"),
            "edge-b": fleet.host(fleet.b),
        },
    )
    r = fleet.status(inv, "--json")
    assert r.returncode == 1, r.stdout + r.stderr
    hosts = _hosts(r.stdout)
    a = hosts["pi-a"]
    assert a["reachable"]
    assert a["time"]["expected"]
    assert a["time"]["level"] == "fail"
    assert any(p.startswith("time: freerun: no ptp4l socket") for p in a["problems"]), a
    assert hosts["edge-b"]["healthy"]


def test_a_bad_inventory_is_one_line_and_exit_2(fleet: Fleet):
    bad = fleet.root / "bad.yml"
    bad.write_text("all:\n  children:\n    hub:\n      hosts:\n        h: {ansible_port: ssh}\n")
    r = fleet.status(bad)
    assert r.returncode == 2
    assert r.stderr == f"{bad}: all.children.hub.hosts.h.ansible_port: 'ssh' is not a port number\n"
    assert r.stdout == ""


def test_an_inventory_that_does_not_match_the_site_is_one_line_per_mismatch(fleet: Fleet):
    inv = fleet.inventory(
        "mismatch",
        edges={
            "pi-a": fleet.host(fleet.a, fleetdaq_node="edge-a"),
            "edge-c": fleet.host(fleet.b),
        },
    )
    r = fleet.status(inv, "--config", str(fleet.site))
    assert r.returncode == 2
    assert r.stderr.splitlines() == [
        f"{inv}: all.children.edges.hosts.edge-c: node 'edge-c' (from its name (no "
        f"fleetdaq_node)) is not in {fleet.site} (nodes: edge-a, edge-b)",
        f"{fleet.site}: nodes.edge-b: no host of {inv} runs it (add one to the edges group "
        "with fleetdaq_node: edge-b)",
    ]
    assert r.stdout == ""


def test_a_bare_host_says_fleetdaq_is_missing_and_it_has_no_journalctl(
    fleet: Fleet, tmp_path: Path
):
    """A host reachable over SSH with nothing of fleetdaq's on it and no systemd tools."""
    root = tmp_path / "bare"
    public = (fleet.key.with_name(fleet.key.name + ".pub")).read_text().strip()
    bare = Sshd(root, public, path_env=str(bin_without(tmp_path, "journalctl", "systemctl")))
    try:
        inv = fleet.inventory("bare", edges={"bare": fleet.host(bare, fleetdaq_node="edge-a")})
        known = fleet.known("bare", fleet.hub.known_hosts_line(), bare.known_hosts_line())
        args = ["--known-hosts", str(known), "--identity", str(fleet.key)]
        r = fleet.run("logs", "-i", str(inv), *args, "edge-a", "-n", "20")
        assert r.returncode == 1, r.stdout + r.stderr
        assert r.stderr.startswith("bare has no journalctl: it keeps no systemd journal"), r.stderr
        assert r.stdout == ""

        status = fleet.status(inv, "--json", known=known)
        assert status.returncode == 1, status.stdout + status.stderr
        host = _hosts(status.stdout)["bare"]
        assert host["reachable"]
        assert host["systemd"] is False
        assert host["version"] is None
        assert host["spool_bytes"] is None
        assert host["problems"] == [
            f"no site file at {bare.fs}{SITE_FILE}",
            f"fleetdaq is not installed at {bare.fs}{VENV}/bin/fleetdaq",
        ]
    finally:
        bare.stop()


def test_logs_of_a_host_not_booted_with_systemd_say_so(fleet: Fleet):
    inv = fleet.inventory("full")
    args = ["--known-hosts", str(fleet.known_hosts), "--identity", str(fleet.key)]
    r = fleet.run("logs", "-i", str(inv), *args, "hub", "--unit", "hub", "--since", "-1h")
    if Path("/run/systemd/system").is_dir():  # a host with a journal: journalctl's own output
        assert r.returncode == 0, r.stderr
    else:
        assert r.returncode == 1, r.stdout + r.stderr
        assert r.stderr.startswith("hub has no systemd journal: journalctl found no journal"), (
            r.stderr
        )


def test_logs_refuse_a_unit_the_host_does_not_run_and_an_unknown_host(fleet: Fleet):
    inv = fleet.inventory("full")
    args = ["--known-hosts", str(fleet.known_hosts), "--identity", str(fleet.key)]
    r = fleet.run("logs", "-i", str(inv), *args, "edge-b", "--unit", "hub")
    assert r.returncode == 2
    assert r.stderr == "edge-b is not the hub (not in the inventory's hub group)\n"
    r = fleet.run("logs", "-i", str(inv), *args, "nowhere")
    assert r.returncode == 2
    assert r.stderr == f"{inv}: no host or node 'nowhere' (hosts: hub, pi-a, edge-b)\n"


def test_a_hub_host_whose_hub_is_down_is_unhealthy_and_says_why(fleet: Fleet, tmp_path: Path):
    public = (fleet.key.with_name(fleet.key.name + ".pub")).read_text().strip()
    lonely = Sshd(tmp_path / "lonely", public)
    try:
        lonely.install_fleetdaq(SITE.format(port=free_port()))  # no hub listens there
        inv = fleet.inventory("hub-down", hub={"hub": fleet.host(lonely)})
        known = fleet.known(
            "hub-down",
            lonely.known_hosts_line(),
            fleet.a.known_hosts_line(),
            fleet.b.known_hosts_line(),
        )
        r = fleet.status(inv, "--json", known=known)
    finally:
        lonely.stop()
    assert r.returncode == 1, r.stdout + r.stderr
    hosts = _hosts(r.stdout)
    hub = hosts["hub"]
    assert hub["reachable"]
    assert hub["recorder"] is None
    (problem,) = hub["problems"]
    assert problem.startswith("recorder: cannot reach the hub at tcp/127.0.0.1:"), problem
    assert hosts["pi-a"]["healthy"]
    assert hosts["edge-b"]["healthy"]


def test_each_host_says_when_its_certificates_end_and_which_ca_it_holds(fleet: Fleet):
    """Edges on a TLS site, each with its own PKI folder as Ansible copies it: pi-a's pair ends
    in 10 days; edge-b still holds the CA from before a rotation the others had."""
    from fleetdaq.pki import init, issue_node

    tls_site = "/etc/fleetdaq/site-tls.yaml"
    for sshd, node, days, ca_name in (
        (fleet.a, "edge-a", 10, "new"),
        (fleet.b, "edge-b", 825, "old"),
    ):
        pki = sshd.fs / "etc/fleetdaq/pki"
        shutil.rmtree(pki, ignore_errors=True)
        init(pki, f"fleettest-{ca_name}", ["127.0.0.1"])
        issue_node(pki, node, days=days)
        text = SITE.format(port=free_port()).replace("tcp/", "tls/")
        # The services' path, as Ansible renders it: the host's fleetdaq finds it under the prefix.
        text += "security: {tls: true, pki_dir: /etc/fleetdaq/pki}\n"
        (sshd.fs / tls_site.lstrip("/")).write_text(text)
    inv = fleet.inventory(
        "certificates",
        edges={
            "pi-a": fleet.host(fleet.a, fleetdaq_node="edge-a", fleetdaq_site_file=tls_site),
            "edge-b": fleet.host(fleet.b, fleetdaq_site_file=tls_site),
        },
    )
    r = fleet.status(inv, "--json")
    assert r.returncode == 1, r.stdout + r.stderr
    out = json.loads(r.stdout)
    hosts = _hosts(r.stdout)
    a, b, hub = hosts["pi-a"]["certificates"], hosts["edge-b"]["certificates"], hosts["hub"]
    assert hub["certificates"] == {
        "tls": False, "first_not_after_ns": 0, "days_left": None, "ca_fingerprint": "",
        "worst": "ok", "problems": [], "unchecked": [], "pki_dir": "",
    }  # fmt: skip
    assert hub["healthy"]
    assert a["tls"]
    assert a["worst"] == "expiring"
    assert 9 < a["days_left"] <= 10
    (problem,) = hosts["pi-a"]["problems"]
    assert problem.startswith(f"certificate: node edge-a {fleet.a.fs}/etc/fleetdaq/pki/nodes/")
    assert "fleetdaq pki issue edge-a --force" in problem
    assert b["worst"] == "ok"
    assert 824 < b["days_left"] <= 825
    assert hosts["edge-b"]["healthy"]
    assert len({a["ca_fingerprint"], b["ca_fingerprint"]}) == 2
    (different,) = out["problems"]
    assert different.startswith("hosts hold different site CAs (SHA-256): pi-a ")
    assert f"edge-b {b['ca_fingerprint'][:16]}" in different

    table = fleet.status(inv)
    assert table.returncode == 1
    assert "certs" in table.stdout
    assert "no TLS" in table.stdout
    assert "expiring" in table.stdout
    assert "✗ fleet: hosts hold different site CAs" in table.stdout


def test_a_tls_hub_is_asked_with_the_ssh_users_operator_pair_or_says_what_is_missing(
    fleet: Fleet,
):
    """On a TLS site `rec status` on the hub host asks as an operator: without a pair for the
    SSH user the recorder is "not asked", with what to do; with one it is asked (nobody listens
    on this site's TLS port, so it cannot reach the hub). The pair and the CA are read under
    the prefix, as the host's services would see them."""
    from fleetdaq.pki import init, issue_operator

    port = free_port()
    pki = fleet.hub.fs / "etc/fleetdaq/pki"
    shutil.rmtree(pki, ignore_errors=True)
    init(pki, "fleettest", ["127.0.0.1"])
    tls_site = "/etc/fleetdaq/site-tls-hub.yaml"
    text = SITE.format(port=port).replace("tcp/", "tls/")
    text += "security: {tls: true, pki_dir: /etc/fleetdaq/pki, operators: {watch: view}}\n"
    (fleet.hub.fs / tls_site.lstrip("/")).write_text(text)
    inv = fleet.inventory(
        "tls-hub", hub={"hub": fleet.host(fleet.hub, fleetdaq_site_file=tls_site)}
    )

    r = fleet.status(inv, "--json")
    assert r.returncode == 1, r.stdout + r.stderr
    (problem,) = _hosts(r.stdout)["hub"]["problems"]
    assert problem.startswith("recorder: not asked: security.tls is on, but the operator's "), (
        problem
    )
    assert "operator.crt: no such file ($FLEETDAQ_CERT, else ~/.config/fleetdaq/operator.crt;" in (
        problem
    )
    assert "fleetdaq_status_operator" in problem
    assert "--operator --role view" in problem

    home = Path(pwd.getpwnam(USER).pw_dir)  # the SSH session's $HOME
    config = fleet.hub.fs / home.relative_to("/") / ".config/fleetdaq"
    config.mkdir(parents=True)
    try:
        issue_operator(pki, "watch", days=10)
        for ext in ("crt", "key"):
            shutil.copy(pki / f"operators/watch.{ext}", config / f"operator.{ext}")
        (config / "operator.key").chmod(0o600)
        r = fleet.status(inv, "--json")
    finally:
        shutil.rmtree(config)
    assert r.returncode == 1, r.stdout + r.stderr
    hub = _hosts(r.stdout)["hub"]
    (problem,) = hub["problems"]
    assert problem.startswith(f"recorder: cannot reach the hub at tls/127.0.0.1:{port}"), problem
    # The pair ends within 30 days: said as the host's note, with the command that renews it.
    (ending,) = [n for n in hub["notes"] if n.startswith("rec status: ")]
    assert ending.startswith("rec status: your certificate "), ending
    assert "in 10.0 days" in ending or "in 9.9 days" in ending, ending
    assert ending.endswith("fleetdaq pki issue watch --operator --role view --force)"), ending
