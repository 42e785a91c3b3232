"""ansible/site.yml against real hosts: an OpenSSH server per host, each in a network namespace
of its own, ansible-playbook in a control namespace joined to them by a bridge. No namespace
reaches any network but the lab's, so the hosts' pip has no package registry: fleetdaq comes
from the wheelhouse. Every host writes under its own ``fleetdaq_prefix``; systemd does not run
these hosts, so the plays that start services and the health gate are off there (the prefix
switches off ``fleetdaq_manage_services``, and with it the health gate).

Checked: the first run installs fleetdaq, the site file, the certificates (owners, modes, each
host only its own pair, never the CA's key; the partition hub bay2's own pair, never the main
hub's, whose pair a run takes away from it), the units and linuxptp's configurations; a second
run changes nothing (PLAY RECAP); every unit it wrote passes ``systemd-analyze verify`` with
nothing printed; an inventory that does not fit the site file stops the run before any host
is touched."""

from __future__ import annotations

import os
import pwd
import re
import shutil
import stat
import subprocess
import sys
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest
import yaml

from tests.deploy.conftest import ANSIBLE, BIN
from tests.deploy.lab import Host, Lab, netns_possible
from tests.fleet.hosts import USER, ensure_sshd

SITE = """\
# Rendered by site.yml as a template: the edges connect to the hub's inventory address.
site: deploytest
hub:
  listen: ["tls/{{ hostvars['controller'].ansible_host }}:7447"]
  partitions:
    bay2: {listen: ["tls/{{ hostvars['bay2'].ansible_host }}:7447"], nodes: [shore]}
security:
  tls: true
  pki_dir: /etc/fleetdaq/pki
  operators: {fleet-status: view}
nodes:
  wec:
    connect: ["tls/{{ hostvars[groups['hub'][0]].ansible_host }}:7447"]
    clock: {source: ptp4l, timestamping: software}
    streams:
      env: {driver: environment_sim, rate_hz: 1, channels: [{name: air, unit: degC}]}
  shore:
    connect: ["tls/{{ hostvars['bay2'].ansible_host }}:7447"]
    streams:
      env: {driver: environment_sim, rate_hz: 1, channels: [{name: air, unit: degC}]}
"""

LOGIN_HOME = pwd.getpwnam(USER).pw_dir

RECAP = re.compile(
    r"^(\S+)\s*:\s*ok=(\d+)\s+changed=(\d+)\s+unreachable=(\d+)\s+failed=(\d+)", re.M
)


@dataclass
class Deploy:
    lab: Lab
    root: Path
    inventory: Path
    env: dict[str, str]
    first: subprocess.CompletedProcess[str]

    def host(self, name: str) -> Host:
        return next(h for h in self.lab.hosts if h.name == name)

    def playbook(self, inventory: Path | None = None) -> subprocess.CompletedProcess[str]:
        return self.lab.run_in_control(
            playbook_command(inventory or self.inventory), self.env, timeout=600
        )


def playbook_command(inventory: Path) -> list[str]:
    return [str(BIN / "ansible-playbook"), "-i", str(inventory), str(ANSIBLE / "site.yml")]


def recap(out: str) -> dict[str, dict[str, int]]:
    return {
        m[1]: {"ok": int(m[2]), "changed": int(m[3]), "unreachable": int(m[4]), "failed": int(m[5])}
        for m in RECAP.finditer(out)
    }


def ansible_env(root: Path) -> dict[str, str]:
    home = root / "home"
    home.mkdir()
    env = {k: v for k, v in os.environ.items() if not k.startswith(("ANSIBLE_", "PYTHON"))}
    env.update(
        HOME=str(home),
        PATH=f"{BIN}:{env.get('PATH', '/usr/bin:/bin')}",
        ANSIBLE_HOME=str(home / ".ansible"),
        ANSIBLE_LOCAL_TEMP=str(root / "ansible-tmp"),
        ANSIBLE_NOCOLOR="1",
        ANSIBLE_PIPELINING="1",
        ANSIBLE_RETRY_FILES_ENABLED="0",
        # Masters end on their own soon after a run, or with the lab's sshds.
        ANSIBLE_SSH_ARGS="-o ControlMaster=auto -o ControlPersist=10s",
        ANSIBLE_SSH_CONTROL_PATH_DIR=str(root / "cp"),
    )
    return env


def write_inventory(
    lab: Lab,
    root: Path,
    wheelhouse: Path,
    path: Path,
    partition: str = "bay2",
    pki: Path | None = None,
    status_operator: str = "fleet-status",
    **edge_nodes: str,
) -> Path:
    known_hosts = root / "known_hosts"
    known_hosts.write_text("".join(h.known_hosts_line() + "\n" for h in lab.hosts))

    def host(h: Host, **extra: object) -> dict[str, object]:
        return {
            "ansible_host": h.address,
            "fleetdaq_prefix": str(h.fs),
            "ansible_remote_tmp": str(h.root / "ansible-tmp"),
            **extra,
        }

    hub, bay2, *edges = lab.hosts
    doc = {
        "all": {
            "vars": {
                "ansible_user": USER,
                "ansible_ssh_private_key_file": str(lab.client_key),
                "ansible_ssh_common_args": (
                    f"-o UserKnownHostsFile={known_hosts} -o StrictHostKeyChecking=yes "
                    "-o IdentitiesOnly=yes"
                ),
                "ansible_python_interpreter": "/usr/bin/python3",
                # The tests' hosts: no sudo (we log in as the user the files belong to), and
                # the services' account is that user (no system account is made under a prefix).
                "fleetdaq_become": False,
                "fleetdaq_user": USER,
                "fleetdaq_group": USER,
                "fleetdaq_python": "/usr/bin/python3",
                "fleetdaq_wheelhouse": str(wheelhouse),
                "fleetdaq_site_src": str(root / "site.yaml"),
                "fleetdaq_pki_src": str(pki or root / "pki"),
                "fleetdaq_hub_extras": [],
                "fleetdaq_status_operator": status_operator,
            },
            "children": {
                "hub": {
                    "hosts": {
                        hub.name: host(hub),
                        bay2.name: host(bay2, fleetdaq_partition=partition),
                    }
                },
                "ptp_grandmaster": {
                    "hosts": {
                        hub.name: {
                            "fleetdaq_ptp_interface": "eth0",
                            "fleetdaq_ptp_timestamping": "hardware",
                        }
                    }
                },
                "edges": {
                    "vars": {"fleetdaq_ptp_interface": "eth0"},
                    "hosts": {
                        e.name: host(e, fleetdaq_node=edge_nodes.get(e.name, e.name)) for e in edges
                    },
                },
            },
        }
    }
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    return path


def fleetdaq(*args: str) -> None:
    r = subprocess.run(
        [sys.executable, "-m", "fleetdaq", *args], capture_output=True, text=True, check=False
    )
    assert r.returncode == 0, r.stderr


@pytest.fixture(scope="module")
def deploy(tmp_path_factory: pytest.TempPathFactory, wheelhouse: Path) -> Iterator[Deploy]:
    why = netns_possible()
    if why:
        pytest.skip(why)
    ensure_sshd()
    root = tmp_path_factory.mktemp("deploy")
    (root / "site.yaml").write_text(SITE)
    pki = root / "pki"
    fleetdaq("pki", "init", "--site", "deploytest", "--hub-name", "10.233.0.10", "--dir", str(pki))
    for node in ("wec", "shore"):
        fleetdaq("pki", "issue", node, "--dir", str(pki))
    fleetdaq("pki", "issue", "bay2", "--partition", "--hub-name", "10.233.0.11", "--dir", str(pki))
    fleetdaq("pki", "issue", "fleet-status", "--operator", "--role", "view", "--dir", str(pki))
    lab = Lab(root / "hosts", ["controller", "bay2", "wec", "shore-pi"])
    try:
        # bay2 as a site upgraded from the time every hub had the main hub's pair: the run
        # takes it away (the first test sees only partitions/bay2.key there).
        stale = lab.hosts[1].fs / "etc/fleetdaq/pki"
        stale.mkdir(parents=True)
        for name in ("hub.crt", "hub.key"):
            (stale / name).write_bytes((pki / name).read_bytes())
        inventory = write_inventory(
            lab, root, wheelhouse, root / "inventory.yml", **{"shore-pi": "shore"}
        )
        env = ansible_env(root)
        first = lab.run_in_control(playbook_command(inventory), env, timeout=600)
        yield Deploy(lab, root, inventory, env, first)
    finally:
        lab.close()


def test_the_first_run_deploys_every_host_from_the_wheelhouse(deploy: Deploy):
    out = deploy.first.stdout
    assert deploy.first.returncode == 0, out[-6000:] + deploy.first.stderr[-3000:]
    counts = recap(out)
    assert set(counts) == {"controller", "bay2", "wec", "shore-pi"}
    for name, c in counts.items():
        assert c["failed"] == 0, name
        assert c["unreachable"] == 0, name
        assert c["changed"] > 0, name

    for host in deploy.lab.hosts:
        fs = host.fs
        fleetdaq_bin = fs / "opt/fleetdaq/venv/bin/fleetdaq"
        version = subprocess.run(
            [str(fleetdaq_bin), "--version"], capture_output=True, text=True, check=False
        )
        assert version.returncode == 0, version.stderr
        assert "0.1.0" in version.stdout
        site = fs / "etc/fleetdaq/site.yaml"
        assert "tls/10.233.0.10:7447" in site.read_text()  # rendered from the inventory
        assert stat.S_IMODE(site.stat().st_mode) == 0o640
        pki = fs / "etc/fleetdaq/pki"
        assert stat.S_IMODE(pki.stat().st_mode) == 0o750
        assert stat.S_IMODE((pki / "ca.crt").stat().st_mode) == 0o644
        assert not (pki / "ca.key").exists()
        keys = sorted(p.relative_to(pki).as_posix() for p in pki.rglob("*.key"))
        for key in keys:
            assert stat.S_IMODE((pki / key).stat().st_mode) == 0o600, key
        own = {"controller": "hub", "bay2": "partitions/bay2", "wec": "nodes/wec"}
        assert keys == [own.get(host.name, "nodes/shore") + ".key"], host.name
        # fleet status's operator pair, for the login user, on the hub hosts only.
        operator = fs / LOGIN_HOME.lstrip("/") / ".config/fleetdaq"
        if host.name in ("controller", "bay2"):
            assert stat.S_IMODE(operator.stat().st_mode) == 0o700
            assert stat.S_IMODE((operator / "operator.crt").stat().st_mode) == 0o644
            assert stat.S_IMODE((operator / "operator.key").stat().st_mode) == 0o600
            assert (operator / "operator.crt").read_bytes() == (
                deploy.root / "pki/operators/fleet-status.crt"
            ).read_bytes()
        else:
            assert not operator.exists(), host.name

    units = deploy.host("controller").fs / "etc/systemd/system"
    hub = (units / "fleetdaq-hub.service").read_text()
    assert "ExecStart=/opt/fleetdaq/venv/bin/fleetdaq hub --config /etc/fleetdaq/site.yaml" in hub
    assert "ReadWritePaths=/var/lib/fleetdaq/data\n" in hub
    assert "-rr" in (units / "phc2sys.service").read_text()  # the grandmaster's NIC clock
    bay2 = (deploy.host("bay2").fs / "etc/systemd/system/fleetdaq-hub.service").read_text()
    assert "--data /var/lib/fleetdaq/data/bay2 --partition bay2\n" in bay2
    conf = deploy.host("controller").fs / "etc/linuxptp/fleetdaq-ptp4l.conf"
    assert "priority1\t\t10" in conf.read_text()
    assert "time_stamping\t\thardware" in conf.read_text()

    wec = deploy.host("wec").fs
    edge = (wec / "etc/systemd/system/fleetdaq-edge.service").read_text()
    assert "--node wec --spool /var/lib/fleetdaq/spool" in edge
    assert "ReadWritePaths=/var/lib/fleetdaq/spool\n" in edge
    assert "slaveOnly\t\t1" in (wec / "etc/linuxptp/fleetdaq-ptp4l.conf").read_text()
    assert not (wec / "etc/systemd/system/phc2sys.service").exists()  # software: no phc2sys
    assert (
        "--node shore"
        in (deploy.host("shore-pi").fs / "etc/systemd/system/fleetdaq-edge.service").read_text()
    )


def test_a_second_run_changes_nothing(deploy: Deploy):
    assert deploy.first.returncode == 0, "the first run failed"
    again = deploy.playbook()
    assert again.returncode == 0, again.stdout[-6000:]
    counts = recap(again.stdout)
    assert set(counts) == {"controller", "bay2", "wec", "shore-pi"}
    assert {name: c["changed"] for name, c in counts.items()} == dict.fromkeys(counts, 0), (
        "\n".join(line for line in again.stdout.splitlines() if line.startswith("changed"))
    )


def test_fleet_status_sees_each_deployed_host_as_the_playbook_left_it(deploy: Deploy):
    """`fleetdaq fleet status` over the inventory the playbook ran with, from the control
    machine: each host's own deployed fleetdaq answers (the wheel's version), each holds the
    site CA the control machine has and its own pair, read where the site file puts them. No
    service runs on these hosts (no systemd), so the hubs' recorders cannot be reached: said,
    and nothing else is wrong with any host."""
    import json

    from cryptography import x509
    from cryptography.hazmat.primitives import hashes

    assert deploy.first.returncode == 0, "the first run failed"
    r = deploy.lab.run_in_control(
        [
            sys.executable, "-m", "fleetdaq", "fleet", "status", "-i", str(deploy.inventory),
            "--known-hosts", str(deploy.root / "known_hosts"),
            "--identity", str(deploy.lab.client_key), "--json",
        ],
        deploy.env,
        timeout=300,
    )  # fmt: skip
    assert "Traceback" not in r.stderr, r.stderr
    out = json.loads(r.stdout)
    hosts = {h["host"]: h for h in out["hosts"]}
    assert list(hosts) == ["controller", "bay2", "wec", "shore-pi"]
    ca = x509.load_pem_x509_certificate((deploy.root / "pki" / "ca.crt").read_bytes())
    for name, h in hosts.items():
        assert h["reachable"], h
        assert h["version"] == "0.1.0", h
        certs = h["certificates"]
        assert certs["tls"], (name, certs)
        assert certs["worst"] == "ok", (name, certs)
        assert certs["ca_fingerprint"] == ca.fingerprint(hashes.SHA256()).hex(), name
        assert 800 < certs["days_left"] <= 825, (name, certs)
    assert hosts["wec"]["node"] == "wec"
    assert hosts["shore-pi"]["node"] == "shore"
    # What is wrong is only what does not run here: the hubs (no systemd starts them: their
    # recorders are asked over TLS with the operator pair the playbook gave the login user, and
    # nobody answers) and ptp4l on the hosts the inventory sets up for PTP (unless this machine
    # runs its own).
    for name, h in hosts.items():
        problems = [p for p in h["problems"] if not p.startswith("time: ")]
        if name in ("controller", "bay2"):
            address = deploy.host(name).address
            (problem,) = problems
            assert problem.startswith(f"recorder: cannot reach the hub at tls/{address}:7447"), (
                problem
            )
        else:
            assert problems == [], (name, problems)
    assert out["problems"] == []  # one site CA across the fleet
    assert r.returncode == 1, r.stdout


def verify(analyze: str, unit: Path) -> str:
    r = subprocess.run(
        [analyze, "verify", "--man=no", str(unit)],
        capture_output=True,
        text=True,
        check=False,
        timeout=120,
    )
    return (
        f"exit {r.returncode}\n{r.stdout}{r.stderr}" if r.returncode or r.stdout or r.stderr else ""
    )


def test_every_unit_passes_systemd_analyze_verify(deploy: Deploy, tmp_path: Path):
    assert deploy.first.returncode == 0, "the first run failed"
    analyze = shutil.which("systemd-analyze")
    if analyze is None:
        pytest.fail("systemd-analyze is missing (Debian's systemd package)")
    verified = []
    for host in deploy.lab.hosts:
        for unit in sorted((host.fs / "etc/systemd/system").glob("*.service")):
            # As systemd would load it: a template as an instance; ExecStart's fleetdaq is the
            # one the playbook installed in the host's prefix (verify needs it to exist).
            copy = tmp_path / unit.name.replace("@.", "@eth0.")
            copy.write_text(
                unit.read_text().replace("ExecStart=/opt/", f"ExecStart={host.fs}/opt/")
            )
            assert verify(analyze, copy) == "", f"{host.name}: {unit.name}"
            verified.append(f"{host.name}:{unit.name}")
            copy.unlink()
    assert sorted(verified) == [
        "bay2:fleetdaq-hub.service",
        "controller:fleetdaq-hub.service",
        "controller:phc2sys.service",
        "controller:ptp4l@.service",
        "shore-pi:fleetdaq-edge.service",
        "shore-pi:ptp4l@.service",
        "wec:fleetdaq-edge.service",
        "wec:ptp4l@.service",
    ]
    # The check can fail: a misspelt key is printed (systemd-analyze still exits 0).
    broken = tmp_path / "fleetdaq-edge.service"
    edge = deploy.host("wec").fs / "etc/systemd/system/fleetdaq-edge.service"
    broken.write_text(
        edge.read_text()
        .replace("ExecStart=/opt/", f"ExecStart={deploy.host('wec').fs}/opt/")
        .replace("WatchdogSec=", "WatchdogSecs=")
    )
    assert "WatchdogSecs" in verify(analyze, broken)


@pytest.mark.parametrize(
    ("partition", "shore_host_runs", "said"),
    [
        ("bay2", "ghost", ["host shore-pi runs node 'ghost'", "which is not in"]),
        ("bay9", "shore", ["host bay2 runs fleetdaq_partition 'bay9'", "(hub.partitions: bay2)"]),
    ],
    ids=["an edge runs no node of the site file", "a partition hub runs no partition of it"],
)
def test_an_inventory_that_does_not_fit_the_site_file_stops_before_any_host(
    deploy: Deploy, tmp_path: Path, partition: str, shore_host_runs: str, said: list[str]
):
    bad = write_inventory(
        deploy.lab,
        deploy.root,
        Path(deploy.env["HOME"]),
        tmp_path / "inventory.yml",
        partition=partition,
        **{"shore-pi": shore_host_runs},
    )
    r = deploy.playbook(bad)
    assert r.returncode != 0
    for line in said:
        assert line in r.stdout, r.stdout[-4000:]
    assert "PLAY [Hub]" not in r.stdout


def test_a_status_operator_the_site_file_does_not_list_stops_before_any_host(
    deploy: Deploy, tmp_path: Path
):
    """Its pair would be copied out and then refused by the hub's access control: fleet status
    would say the recorder cannot be asked, long after the run said nothing."""
    fleetdaq("pki", "issue", "nobody", "--operator", "--dir", str(deploy.root / "pki"))
    bad = write_inventory(
        deploy.lab,
        deploy.root,
        Path(deploy.env["HOME"]),
        tmp_path / "inventory.yml",
        status_operator="nobody",
        **{"shore-pi": "shore"},
    )
    r = deploy.playbook(bad)
    assert r.returncode != 0
    out = " ".join(r.stdout.split())  # Ansible folds long messages
    assert "fleetdaq_status_operator 'nobody' needs security.tls and an entry under" in out, (
        r.stdout[-4000:]
    )
    assert "(e.g. nobody: view)" in out
    assert "PLAY [Hub]" not in r.stdout


def test_a_certificate_the_site_ca_did_not_issue_stops_before_any_host(
    deploy: Deploy, tmp_path: Path
):
    """wec's and the hub's pairs from another CA (kept from before a `pki init --force`):
    copied out, every link they make would be refused while their units run on. The
    preflight verifies each pair with openssl and stops, saying which, why and the command
    that makes it again; a pair that ends soon is named and deployed all the same."""
    pki = tmp_path / "pki"
    shutil.copytree(deploy.root / "pki", pki)
    other = tmp_path / "other"
    fleetdaq(
        "pki", "init", "--site", "deploytest", "--hub-name", "10.233.0.10", "--dir", str(other)
    )
    fleetdaq("pki", "issue", "wec", "--dir", str(other))
    for name in ("nodes/wec.crt", "nodes/wec.key", "hub.crt", "hub.key"):
        shutil.copy(other / name, pki / name)
    fleetdaq("pki", "issue", "shore", "--days", "10", "--force", "--dir", str(pki))
    bad = write_inventory(
        deploy.lab,
        deploy.root,
        Path(deploy.env["HOME"]),
        tmp_path / "inventory.yml",
        pki=pki,
        **{"shore-pi": "shore"},
    )
    r = deploy.playbook(bad)
    assert r.returncode != 0
    out = " ".join(r.stdout.split())  # Ansible folds long messages
    assert f"{pki}/nodes/wec.crt: unable to get local issuer certificate against {pki}/ca.crt" in (
        out
    ), r.stdout[-4000:]
    assert "make it again: fleetdaq pki issue wec --force --config" in out
    assert f"{pki}/hub.crt: unable to get local issuer certificate" in out
    assert f"make it again: fleetdaq pki hub --force --dir {pki})" in out  # the same CA
    assert f"{pki}/nodes/shore.crt ends within 30 days" in out, r.stdout[-4000:]
    assert "nodes/shore.crt: unable" not in out  # only named, not a reason to stop
    assert "PLAY [Hub]" not in r.stdout
