"""`fleetdaq pki`: a site CA, the hub's router certificate, node and operator certificates — keys
0600, never overwritten without --force, each checked with `cryptography` against the CA."""

from __future__ import annotations

import ipaddress
import stat
import subprocess
import sys
from pathlib import Path

import pytest
from cryptography import x509
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

from fleetdaq.runtime.security import SecretFileError, check_private_file
from tests.procs import REPO


def pki(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "fleetdaq", "pki", *args],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )


def cert(path: Path) -> x509.Certificate:
    return x509.load_pem_x509_certificate(path.read_bytes())


def cn(c: x509.Certificate) -> str:
    return str(c.subject.get_attributes_for_oid(NameOID.COMMON_NAME)[0].value)


def test_init_and_issue_make_a_working_chain(tmp_path: Path):
    d = tmp_path / "pki"
    r = pki("init", "--dir", str(d), "--site", "buoy", "--hub-name", "hub.buoy.lan",
            "--hub-name", "10.0.0.2")  # fmt: skip
    assert r.returncode == 0, r.stderr
    assert pki("issue", "wec", "--dir", str(d)).returncode == 0
    r = pki("issue", "ann", "--operator", "--role", "control", "--dir", str(d))
    assert r.returncode == 0, r.stderr
    assert "security: {operators: {ann: control}}" in r.stdout

    ca = cert(d / "ca.crt")
    assert ca.extensions.get_extension_for_class(x509.BasicConstraints).value.ca
    for path, name in (
        (d / "hub.crt", "hub"),
        (d / "nodes" / "wec.crt", "wec"),
        (d / "operators" / "ann.crt", "operator:ann"),
    ):
        c = cert(path)
        c.verify_directly_issued_by(ca)  # raises when the CA did not sign it
        assert cn(c) == name
        assert not c.extensions.get_extension_for_class(x509.BasicConstraints).value.ca
        usage = c.extensions.get_extension_for_class(x509.ExtendedKeyUsage).value
        assert ExtendedKeyUsageOID.CLIENT_AUTH in usage
        key = path.with_suffix(".key")
        assert stat.S_IMODE(key.stat().st_mode) == 0o600
        check_private_file(key)
    hub = cert(d / "hub.crt")
    san = hub.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    assert san.get_values_for_type(x509.DNSName) == ["hub.buoy.lan"]
    assert san.get_values_for_type(x509.IPAddress) == [ipaddress.ip_address("10.0.0.2")]
    ou = cert(d / "operators" / "ann.crt").subject.get_attributes_for_oid(
        NameOID.ORGANIZATIONAL_UNIT_NAME
    )
    assert ou[0].value == "role=control"
    listing = pki("list", "--dir", str(d)).stdout
    assert "operator:ann" in listing
    assert "NOT ISSUED" not in listing


def test_nothing_is_overwritten_without_force_and_bad_names_are_refused(tmp_path: Path):
    d = tmp_path / "pki"
    assert pki("init", "--dir", str(d), "--site", "buoy").returncode == 0
    assert pki("issue", "wec", "--dir", str(d)).returncode == 0
    before = (d / "nodes" / "wec.key").read_bytes()
    for args in (("init", "--site", "buoy"), ("issue", "wec")):
        r = pki(*args, "--dir", str(d))
        assert r.returncode == 2
        assert "exists" in r.stderr
        assert "--force" in r.stderr
        assert "Traceback" not in r.stderr
    assert (d / "nodes" / "wec.key").read_bytes() == before
    assert pki("issue", "wec", "--dir", str(d), "--force").returncode == 0
    assert (d / "nodes" / "wec.key").read_bytes() != before
    for bad in ("Wec", "hub", "a/b", ""):
        r = pki("issue", bad, "--dir", str(d))
        assert r.returncode == 2, bad
        assert len(r.stderr.strip().splitlines()) == 1
    r = pki("issue", "wec", "--dir", str(tmp_path / "empty"))
    assert r.returncode == 2
    assert "no site CA" in r.stderr


def test_a_ca_key_readable_by_others_is_refused(tmp_path: Path):
    d = tmp_path / "pki"
    assert pki("init", "--dir", str(d), "--site", "buoy").returncode == 0
    (d / "ca.key").chmod(0o644)
    r = pki("issue", "wec", "--dir", str(d))
    assert r.returncode == 2
    assert "chmod 600" in r.stderr
    with pytest.raises(SecretFileError, match="group or others"):
        check_private_file(d / "ca.key")


def test_the_acl_grants_each_node_its_own_keys_only(tmp_path: Path):
    import json

    r = pki("acl", "--config", str(REPO / "config" / "site.example.yaml"))
    assert r.returncode == 0, r.stderr
    acl = json.loads(r.stdout)
    assert acl["default_permission"] == "deny"
    rules = {x["id"]: x for x in acl["rules"]}
    publish = rules["wec-t8:publish"]
    assert publish["flows"] == ["ingress"]
    assert all(k.startswith("fleetdaq/wave-test-site/wec-t8/") for k in publish["key_exprs"])
    subjects = {s["id"]: s["cert_common_names"] for s in acl["subjects"]}
    assert subjects["node:wec-t8"] == ["wec-t8"]
    assert subjects["operator:ann"] == ["operator:ann"]
    ann = rules["operator:ann:ask"]
    assert ann["messages"] == ["query"]
    assert all(k.endswith("/by/ann") for k in ann["key_exprs"])
    for policy in acl["policies"]:
        (subject,) = policy["subjects"]
        name = subject.split(":", 1)[1]
        assert all(rid.startswith(f"{name}:") or rid.startswith(subject) for rid in policy["rules"])


PARTITIONED = """\
site: parts
security: {{tls: true, pki_dir: {pki}}}
hub:
  listen: [tls/10.0.0.1:7447]
  partitions:
    bay2: {{listen: ["tls/bay2.lan:7447", "tls/0.0.0.0:7448"], nodes: ["cell-*"]}}
nodes:
  wec: {{streams: {{t8: {{driver: wave_sim, rate_hz: 100, channels: [{{name: heave}}]}}}}}}
  cell-a:
    streams: {{t: {{driver: wave_sim, rate_hz: 100, channels: [{{name: temp}}]}}}}
    outputs: {{lamp: {{driver: pcf8574, address: 0x20, pin: 1, safe: 0, sim: {{}}}}}}
"""


def test_a_partition_hub_gets_its_own_pair_and_rights_over_its_own_nodes_only(tmp_path: Path):
    """`pki issue NAME --partition`: CN ``hub:NAME``, server and client, valid for the hosts
    of its listen; the ACL grants that name bay2's keys only; a partition hub without its
    pair stops at start with one line saying how to make it."""
    import json

    d = tmp_path / "pki"
    site = tmp_path / "site.yaml"
    site.write_text(PARTITIONED.format(pki=d))
    assert pki("init", "--dir", str(d), "--config", str(site)).returncode == 0
    r = subprocess.run(
        [sys.executable, "-m", "fleetdaq", "hub", "--config", str(site), "--partition", "bay2"],
        cwd=REPO, capture_output=True, text=True, timeout=60, check=False,
    )  # fmt: skip
    assert r.returncode == 2, r.stderr
    assert len(r.stderr.strip().splitlines()) == 1, r.stderr
    assert "fleetdaq pki issue bay2 --partition" in r.stderr

    r = pki("issue", "bay2", "--partition", "--dir", str(d), "--config", str(site))
    assert r.returncode == 0, r.stderr
    c = cert(d / "partitions" / "bay2.crt")
    c.verify_directly_issued_by(cert(d / "ca.crt"))
    assert cn(c) == "hub:bay2"
    usage = c.extensions.get_extension_for_class(x509.ExtendedKeyUsage).value
    assert {ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH} <= set(usage)
    san = c.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    assert san.get_values_for_type(x509.DNSName) == ["bay2.lan", "localhost"]
    assert san.get_values_for_type(x509.IPAddress) == [ipaddress.ip_address("127.0.0.1")]
    check_private_file(d / "partitions" / "bay2.key")
    assert "hub:bay2" in pki("list", "--dir", str(d)).stdout
    r = pki("issue", "bay2", "--partition", "--dir", str(d), "--hub-name", "10.0.0.2", "--force")
    assert r.returncode == 0, r.stderr
    san = cert(d / "partitions" / "bay2.crt").extensions.get_extension_for_class(
        x509.SubjectAlternativeName
    )
    assert san.value.get_values_for_type(x509.IPAddress) == [ipaddress.ip_address("10.0.0.2")]

    for args, why in (
        (
            ("bay9", "--partition", "--config", str(site)),
            "no partition 'bay9' (hub.partitions: bay2)",
        ),
        (("bay3", "--partition"), "give --config SITE_FILE or --hub-name HOST"),
        (("wec", "--hub-name", "x"), "--hub-name is for a partition hub's pair"),
        (("ann", "--partition", "--operator", "--hub-name", "x"), "not both"),
    ):
        r = pki("issue", *args, "--dir", str(d))
        assert r.returncode == 2, args
        assert why in r.stderr, r.stderr
        assert len(r.stderr.strip().splitlines()) == 1, r.stderr

    acl = json.loads(pki("acl", "--config", str(site)).stdout)
    subjects = {s["id"]: s["cert_common_names"] for s in acl["subjects"]}
    assert subjects["partition:bay2"] == ["hub:bay2"]
    assert subjects["hub"] == ["hub"]
    rules = {x["id"]: x for x in acl["rules"]}
    (policy,) = [p for p in acl["policies"] if p["subjects"] == ["partition:bay2"]]
    granted = [rules[rid] for rid in policy["rules"]]
    mine = ("fleetdaq/parts/cell-a/", "fleetdaq/parts/hub/partition/bay2/")
    hears = ("fleetdaq/parts/hub/heartbeat", "fleetdaq/parts/hub/snapshot/trigger")
    for rule in granted:
        declarations = {"declare_subscriber", "declare_liveliness_subscriber", "liveliness_query"}
        if rule["flows"] == ["egress"] and set(rule["messages"]) <= declarations:
            continue  # what the main hub subscribes to: told to bay2's router
        for key in rule["key_exprs"]:
            assert key.startswith(mine) or key in hears, (rule["id"], key)
        if set(rule["key_exprs"]) & set(hears):
            assert rule["messages"] in (["declare_subscriber"], ["put"]), rule
            assert rule["messages"] == ["put"] or rule["flows"] == ["ingress"], rule
    # The main hub's node is no part of it: not its data, acks, outputs or liveliness.
    assert not any("/wec/" in k for r in granted for k in r["key_exprs"])
    assert not any("/ack/" in k for r in granted for k in r["key_exprs"])


def test_the_hubs_pair_again_keeps_its_ca_and_its_names(tmp_path: Path):
    """`pki hub`: the hub's router pair issued again with the CA already there (the nodes'
    pairs and ca.crt stay valid): the names of the pair it replaces unless given, never over
    an existing pair without --force."""
    d = tmp_path / "pki"
    assert pki("init", "--dir", str(d), "--site", "buoy", "--hub-name", "hub.buoy.lan",
               "--hub-name", "10.0.0.2").returncode == 0  # fmt: skip
    assert pki("issue", "wec", "--dir", str(d)).returncode == 0
    ca_before, old = (d / "ca.crt").read_bytes(), cert(d / "hub.crt")
    r = pki("hub", "--dir", str(d))
    assert r.returncode == 2
    assert r.stderr == f"pki hub: {d}/hub.crt exists (use --force to replace it)\n"

    r = pki("hub", "--dir", str(d), "--force", "--days", "400")
    assert r.returncode == 0, r.stderr
    assert "for hub.buoy.lan, 10.0.0.2;" in r.stdout
    assert "the nodes keep their pairs" in r.stdout
    new = cert(d / "hub.crt")
    assert (d / "ca.crt").read_bytes() == ca_before
    new.verify_directly_issued_by(cert(d / "ca.crt"))
    cert(d / "nodes" / "wec.crt").verify_directly_issued_by(cert(d / "ca.crt"))
    assert new.serial_number != old.serial_number
    assert cn(new) == "hub"
    assert 399 <= (new.not_valid_after_utc - new.not_valid_before_utc).days <= 400
    san = new.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    assert san.get_values_for_type(x509.DNSName) == ["hub.buoy.lan"]
    assert san.get_values_for_type(x509.IPAddress) == [ipaddress.ip_address("10.0.0.2")]
    usage = new.extensions.get_extension_for_class(x509.ExtendedKeyUsage).value
    assert ExtendedKeyUsageOID.SERVER_AUTH in usage
    check_private_file(d / "hub.key")

    r = pki("hub", "--dir", str(d), "--force", "--hub-name", "hub2.buoy.lan")  # it moved
    assert r.returncode == 0, r.stderr
    san = cert(d / "hub.crt").extensions.get_extension_for_class(x509.SubjectAlternativeName)
    assert san.value.get_values_for_type(x509.DNSName) == ["hub2.buoy.lan"]
    r = pki("hub", "--dir", str(tmp_path / "empty"), "--force")
    assert (r.returncode, r.stderr) == (2, f"pki hub: no site CA in {tmp_path}/empty (run "
                                           "`fleetdaq pki init` first)\n")  # fmt: skip
