"""``fleetdaq pki check``: the certificates one machine holds, from pairs `fleetdaq pki` makes —
fine, ending soon, ended, not started by this clock, issued by another CA (a pair not
re-issued after a rotation), missing — each with the command that fixes it, and the exit code a
script reads. `fleetdaq fleet status` runs it on every host (tests/fleet/test_over_ssh.py)."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

from fleetdaq.certificate_check import check
from fleetdaq.fleet.probe import parse_certificates
from fleetdaq.hub.config.load import parse_config
from fleetdaq.pki import init, issue_node, issue_partition
from fleetdaq.runtime.certificate_dates import DAY_NS
from tests.procs import REPO

SITE = """\
site: checks
hub:
  listen: [tls/127.0.0.1:7447]
  partitions: {{bay2: {{nodes: [env], listen: [tls/127.0.0.1:7448]}}}}
  universal_alarms: {{certificate_expiring: {{threshold: {days}}}}}
security: {{tls: {tls}, pki_dir: {pki}}}
nodes:
  wec:
    streams:
      s: {{driver: environment_sim, rate_hz: 1, channels: [{{name: air, unit: degC}}]}}
  env:
    streams:
      s: {{driver: environment_sim, rate_hz: 1, channels: [{{name: air, unit: degC}}]}}
"""


def site_file(tmp_path: Path, pki: Path, tls: bool = True, days: int = 30) -> Path:
    path = tmp_path / f"site-{tls}-{days}.yaml"
    path.write_text(SITE.format(pki=pki, tls=str(tls).lower(), days=days))
    return path


def pki_check(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "fleetdaq", "pki", "check", *args],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )


def by_which(found: dict[str, object]) -> dict[str, dict[str, object]]:
    certs = found["certificates"]
    assert isinstance(certs, list)
    return {c["which"]: c for c in certs}


def test_fine_pairs_exit_0_and_one_ending_within_the_days_exits_1_with_its_fix(tmp_path: Path):
    pki = tmp_path / "pki"
    init(pki, "checks", ["127.0.0.1"])
    issue_node(pki, "wec", days=10)
    issue_node(pki, "env")
    site = site_file(tmp_path, pki)

    r = pki_check("--config", str(site), "--node", "env", "--json")
    assert r.returncode == 0, r.stdout + r.stderr
    found = json.loads(r.stdout)
    assert found["problems"] == []
    assert list(by_which(found)) == ["ca", "node env"]
    env = by_which(found)["node env"]
    assert env["state"] == "ok"
    assert env["cn"] == "env"
    assert 824 < float(env["days_left"]) <= 825  # type: ignore[arg-type]
    view = parse_certificates(r.stdout)
    assert view.tls
    assert view.worst == "ok"
    assert view.first_not_after_ns == env["not_after_ns"]
    assert view.ca_fingerprint == by_which(found)["ca"]["fingerprint"]
    assert len(view.ca_fingerprint) == 64

    r = pki_check("--config", str(site), "--node", "wec")
    assert r.returncode == 1, r.stdout + r.stderr
    assert "node wec" in r.stdout
    assert "expiring" in r.stdout
    (problem,) = [line for line in r.stdout.splitlines() if line.startswith("✗")]
    assert f"node wec {pki}/nodes/wec.crt: expires on" in problem
    assert "in 10.0 days" in problem or "in 9.9 days" in problem
    assert "fleetdaq pki issue wec --force" in problem

    # The days come from the site's certificate_expiring threshold.
    quiet = site_file(tmp_path, pki, days=5)
    assert pki_check("--config", str(quiet), "--node", "wec").returncode == 0

    # Nothing named: every pair in the folder (a control machine's, or a hub's).
    r = pki_check("--config", str(site), "--json")
    assert r.returncode == 1
    assert list(by_which(json.loads(r.stdout))) == ["ca", "hub", "node env", "node wec"]


def test_ended_not_started_foreign_and_missing_pairs_each_say_what_to_do(tmp_path: Path):
    pki = tmp_path / "pki"
    init(pki, "checks", ["127.0.0.1"])
    issue_node(pki, "wec")
    issue_partition(pki, "bay2", ["127.0.0.1"])
    site = parse_config(site_file(tmp_path, pki).read_text(), "site.yaml")
    wec_ends = by_which(check(site, ("wec",)))["node wec"]["not_after_ns"]
    assert isinstance(wec_ends, int)

    ended = check(site, ("wec",), now_ns=wec_ends + DAY_NS)
    assert by_which(ended)["node wec"]["state"] == "expired"
    assert by_which(ended)["node wec"]["days_left"] == -1.0
    assert any("expired on" in p and "pki issue wec --force" in p for p in ended["problems"])

    # The hub's own pair ended while the CA goes on: that pair again, not a rotation.
    hub = by_which(check(site, hub=True, now_ns=wec_ends + DAY_NS))["hub"]
    assert hub["state"] == "expired"
    assert "fleetdaq pki hub --force" in str(hub["message"])
    assert "pki init" not in str(hub["message"])

    early = check(site, partitions=("bay2",), now_ns=wec_ends - 900 * DAY_NS)
    bay2 = by_which(early)["partition bay2"]
    assert bay2["state"] == "not_yet_valid"
    assert "this machine's clock says" in str(bay2["message"])

    missing = check(site, ("env",))
    env = by_which(missing)["node env"]
    assert env["state"] == "unreadable"
    assert "fleetdaq pki issue env --force" in str(env["message"])

    # A rotation (a new CA) that did not reach this machine's pair: issued by another CA.
    old = tmp_path / "old-wec.crt"
    shutil.copy(pki / "nodes/wec.crt", old)
    init(pki, "checks", ["127.0.0.1"], force=True)
    shutil.copy(old, pki / "nodes/wec.crt")
    foreign = check(site, ("wec",))
    wec = by_which(foreign)["node wec"]
    assert wec["state"] == "foreign"
    assert f"not issued by the site CA {pki}/ca.crt" in str(wec["message"])
    assert parse_certificates(json.dumps(foreign)).worst == "foreign"


def test_without_tls_there_is_nothing_to_check_and_bad_names_are_one_line(tmp_path: Path):
    plain = site_file(tmp_path, tmp_path / "nowhere", tls=False)
    r = pki_check("--config", str(plain), "--node", "wec", "--json")
    assert (r.returncode, json.loads(r.stdout)) == (0, {"tls": False})
    assert not parse_certificates(r.stdout).tls
    r = pki_check("--config", str(plain))
    assert r.returncode == 0
    assert r.stdout == f"security.tls is off in {plain}: the links use no certificates\n"

    r = pki_check("--config", str(plain), "--node", "nope")
    assert (r.returncode, r.stdout) == (2, "")
    assert r.stderr == f"pki check: the site file {plain} has no node 'nope'\n"
    r = pki_check("--config", str(plain), "--partition", "bay9")
    assert r.returncode == 2
    assert r.stderr == f"pki check: the site file {plain} has no partition hub 'bay9'\n"

    # A CA that is not there: the pair cannot be judged, and the fix is to copy the CA.
    site = parse_config(site_file(tmp_path, tmp_path / "empty").read_text(), "site.yaml")
    found = check(site, ("wec",))
    ca = by_which(found)["ca"]
    assert ca["state"] == "unreadable"
    assert "copy the site's ca.crt here" in str(ca["message"])
    assert found["first_not_after_ns"] == 0
    # Nothing named and no pair in the folder: that is a problem too.
    assert any("no certificate pair in" in p for p in check(site)["problems"])


def test_a_pki_folder_this_user_may_not_read_is_not_checked_and_not_held_against_it(
    tmp_path: Path,
):
    """The folder is the services' own (0750, Ansible's); whoever runs the check over SSH may
    not be in their group. As root, without the capabilities that pass over file modes."""
    pki = tmp_path / "pki"
    init(pki, "checks", ["127.0.0.1"])
    issue_node(pki, "wec")
    site = site_file(tmp_path, pki)
    args = [sys.executable, "-m", "fleetdaq", "pki", "check", "--config", str(site)]
    if os.geteuid() == 0:
        for p in [pki, *pki.rglob("*")]:
            os.chown(p, 65534, 65534)
        drop = "-dac_override,-dac_read_search"
        args = ["setpriv", f"--inh-caps={drop}", f"--bounding-set={drop}", *args]
    pki.chmod(0o700 if os.geteuid() == 0 else 0o000)
    try:
        r = subprocess.run(
            [*args, "--node", "wec", "--json"],
            cwd=REPO, capture_output=True, text=True, timeout=60, check=False,
        )  # fmt: skip
    finally:
        pki.chmod(0o700)
    assert r.returncode == 1, r.stdout + r.stderr
    found = json.loads(r.stdout)
    assert found["problems"] == []
    assert [c["state"] for c in found["certificates"]] == ["not_permitted", "not_permitted"]
    assert any("this user may not read it" in u for u in found["unchecked"])
    view = parse_certificates(r.stdout)
    assert view.worst == "not_permitted"
    assert len(view.unchecked) == 2
    assert view.problems == ()


def test_with_a_root_the_site_files_pki_dir_is_read_under_it(tmp_path: Path):
    """A chroot's site file names its PKI folder as its services see it; `--root` checks it from
    outside (fleet status passes a host's fleetdaq_prefix)."""
    root = tmp_path / "chroot"
    pki = root / "etc" / "fleetdaq" / "pki"
    init(pki, "checks", ["127.0.0.1"])
    issue_node(pki, "env")
    site = site_file(tmp_path, Path("/etc/fleetdaq/pki"))

    r = pki_check("--config", str(site), "--node", "env", "--json", "--root", str(root))
    assert r.returncode == 0, r.stdout + r.stderr
    found = json.loads(r.stdout)
    assert found["pki_dir"] == str(pki)
    assert {c["state"] for c in found["certificates"]} == {"ok"}

    # Without it, the path as it is: not this machine's PKI folder.
    r = pki_check("--config", str(site), "--node", "env", "--json")
    assert json.loads(r.stdout)["pki_dir"] == "/etc/fleetdaq/pki", r.stderr
