"""The fleet inventory: read as Ansible reads it (checked against ``ansible-inventory`` itself),
checked against a site file, and every mistake one line naming the file and key path."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from fleetdaq.fleet.errors import InventoryError
from fleetdaq.fleet.inventory import Host, load_inventory
from fleetdaq.fleet.layout import layout_for
from fleetdaq.fleet.site_match import mismatches
from fleetdaq.hub.config.load import load_config
from tests.procs import REPO

# Nested children, vars at every level, a host in two groups at one depth (priority decides),
# a host var over them all, connection vars from `all`.
TRICKY = """\
all:
  vars:
    ansible_user: ops
    fleetdaq_venv: /opt/fleetdaq/venv
    fleetdaq_site_file: /etc/fleetdaq/site.yaml
    fleetdaq_state_dir: /var/lib/fleetdaq
  children:
    hub:
      hosts:
        ctl:
          ansible_host: 10.1.0.1
          ansible_port: 2200
    ptp_grandmaster:
      vars:
        fleetdaq_ptp_interface: eth1
      hosts:
        ctl: {}
    edges:
      vars:
        fleetdaq_venv: /srv/venv
        fleetdaq_ptp_interface: eth0
      children:
        sea:
          vars:
            ansible_user: sea
            fleetdaq_state_dir: /data/fleetdaq
          hosts:
            buoy-1:
              ansible_host: 10.1.0.11
              fleetdaq_node: wec
            buoy-2:
              ansible_host: 10.1.0.12
              ansible_user: special
        lab:
          vars:
            ansible_group_priority: 5
            ansible_user: lab
            fleetdaq_state_dir: /lab/fleetdaq
          hosts:
            buoy-2: {}
            cell:
              ansible_host: 10.1.0.21
              fleetdaq_node: am-cell
              fleetdaq_ptp_timestamping: hardware
    others:
      hosts:
        nas:
          ansible_host: 10.1.0.99
"""

_COMPARED = {
    "ansible_host": "address",
    "ansible_port": "port",
    "ansible_user": "user",
    "fleetdaq_node": "node",
    "fleetdaq_venv": "venv",
    "fleetdaq_site_file": "site_file",
    "fleetdaq_state_dir": "state_dir",
    "fleetdaq_ptp_interface": "ptp_interface",
    "fleetdaq_ptp_timestamping": "ptp_timestamping",
}


def _ansible_hostvars(inventory: Path, tmp_path: Path) -> dict[str, dict[str, object]]:
    env = {k: v for k, v in os.environ.items() if not k.startswith("ANSIBLE_")}
    env.update(HOME=str(tmp_path), ANSIBLE_LOCAL_TEMP=str(tmp_path / "ansible-tmp"))
    r = subprocess.run(
        [str(Path(sys.executable).parent / "ansible-inventory"), "-i", str(inventory), "--list"],
        capture_output=True,
        text=True,
        env=env,
        timeout=120,
        check=False,
    )
    assert r.returncode == 0, r.stderr
    out: dict[str, dict[str, object]] = json.loads(r.stdout)["_meta"]["hostvars"]
    return out


def _ours(host: Host) -> dict[str, object]:
    return {var: getattr(host, attr) for var, attr in _COMPARED.items()}


def test_variables_resolve_as_ansible_resolves_them(tmp_path: Path):
    path = tmp_path / "inventory.yml"
    path.write_text(TRICKY)
    inv = load_inventory(path)
    theirs = _ansible_hostvars(path, tmp_path)
    assert [h.name for h in inv.hosts] == ["ctl", "buoy-1", "buoy-2", "cell"]  # not the nas
    for host in inv.hosts:
        ansible = theirs[host.name]
        expected = {var: ansible[var] for var in _COMPARED if var in ansible}
        ours = {var: value for var, value in _ours(host).items() if var in expected}
        assert ours == expected, host.name
    by = {h.name: h for h in inv.hosts}
    assert by["buoy-2"].user == "special"  # the host var over every group
    assert by["buoy-2"].state_dir == "/lab/fleetdaq"  # lab's priority 5 over sea's 1
    assert by["buoy-1"].state_dir == "/data/fleetdaq"
    assert by["ctl"].ptp_interface == "eth1"
    assert by["ctl"].is_hub
    assert by["ctl"].is_grandmaster
    assert by["cell"].node == "am-cell"
    assert by["buoy-2"].node == "buoy-2"
    assert inv.hub.name == "ctl"
    assert inv.find("wec") is by["buoy-1"]


def test_the_example_inventory_is_valid_for_ansible_and_matches_the_example_site(
    tmp_path: Path,
):
    path = REPO / "ansible" / "inventory.example.yml"
    inv = load_inventory(path)
    theirs = _ansible_hostvars(path, tmp_path)
    assert set(theirs) == {h.name for h in inv.hosts}
    for host in inv.hosts:
        expected = {var: theirs[host.name][var] for var in _COMPARED if var in theirs[host.name]}
        assert {v: x for v, x in _ours(host).items() if v in expected} == expected
    site_path = REPO / "config" / "site.example.yaml"
    assert mismatches(inv, load_config(site_path), site_path) == []


def test_the_layout_follows_the_inventory_then_the_site_then_the_defaults(tmp_path: Path):
    path = tmp_path / "inventory.yml"
    path.write_text(TRICKY.replace("fleetdaq_state_dir: /data/fleetdaq", "fleetdaq_prefix: /x"))
    inv = load_inventory(path)
    by = {h.name: h for h in inv.hosts}
    hub = layout_for(by["ctl"], None)
    assert hub.fleetdaq == "/opt/fleetdaq/venv/bin/fleetdaq"
    assert hub.data_dir == "/var/lib/fleetdaq/data"
    assert hub.spool_dir is None
    assert hub.units == ("fleetdaq-hub", "ptp4l@eth1")
    assert hub.ptp_expected
    buoy = layout_for(by["buoy-1"], None)
    assert buoy.fleetdaq == "/x/srv/venv/bin/fleetdaq"
    assert buoy.site_file == "/x/etc/fleetdaq/site.yaml"
    assert buoy.spool_dir == "/x/var/lib/fleetdaq/spool/wec"
    cell = layout_for(by["cell"], None)
    assert cell.units == ("fleetdaq-edge", "ptp4l@eth0", "phc2sys")
    site = tmp_path / "site.yaml"
    site.write_text(
        "site: s\nhub: {data_dir: /rec}\nnodes:\n  wec:\n    spool: {dir: /spool}\n"
        "    clock: {source: chrony}\n"
        "    streams: {env: {driver: environment_sim, rate_hz: 1,"
        " channels: [{name: air, unit: degC}]}}\n"
    )
    cfg = load_config(site)
    assert layout_for(by["buoy-1"], cfg).spool_dir == "/x/spool/wec"
    assert layout_for(by["buoy-1"], cfg).ptp_source == "chrony"
    assert layout_for(by["ctl"], cfg).data_dir == "/rec"


def test_a_partition_hub_host_records_under_its_own_folder_and_is_not_the_main_hub(
    tmp_path: Path,
):
    path = tmp_path / "inventory.yml"
    path.write_text(
        "all:\n  children:\n    hub:\n      hosts:\n        ctl: {}\n"
        "        ctl2: {fleetdaq_partition: bay2}\n"
    )
    inv = load_inventory(path)
    assert inv.hub.name == "ctl"
    by = {h.name: h for h in inv.hosts}
    assert by["ctl2"].partition == "bay2"
    site = tmp_path / "site.yaml"
    site.write_text(
        "site: s\nhub:\n  partitions:\n    bay2: {listen: [tcp/10.0.0.2:7447], nodes: [b]}\n"
        "nodes:\n  a: &n\n    streams: {env: {driver: environment_sim, rate_hz: 1,"
        " channels: [{name: air, unit: degC}]}}\n  b: *n\n"
    )
    cfg = load_config(site)
    assert layout_for(by["ctl"], cfg).data_dir == "/var/lib/fleetdaq/data"
    assert layout_for(by["ctl2"], cfg).data_dir == "/var/lib/fleetdaq/data/bay2"
    assert layout_for(by["ctl2"], cfg).units == ("fleetdaq-hub",)


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("", "empty inventory"),
        ("- a\n- b\n", "not a YAML inventory"),
        ("all:\n  children:\n    hub:\n      hosts:\n        h: {ansible_port: 70000}\n",
         "all.children.hub.hosts.h.ansible_port: '70000' is not a port number"),
        ("all:\n  children:\n    hub:\n      host:\n        h: {}\n",
         "all.children.hub.host: unknown key"),
        ("all:\n  children:\n    hub:\n      hosts:\n        a: {}\n        b: {}\n",
         "all.children.hub.hosts: the hub group has one main hub (found: a, b)"),
        ("all:\n  children:\n    hub:\n      hosts:\n        a: {}\n"
         "        b: {fleetdaq_partition: p}\n        c: {fleetdaq_partition: p}\n",
         "all.children.hub.hosts.c: partition 'p' is already run by b"),
        ("all:\n  children:\n    edges:\n      hosts:\n        a: {}\n",
         "the hub group has one main hub (found: none)"),
        ("all:\n  children:\n    hub:\n      hosts:\n        h: {}\n        h: {}\n",
         ":6: duplicate key 'h' (first on line 5)"),
        ("all:\n  vars:\n    fleetdaq_venv: '{{ venv }}'\n  children:\n    hub:\n"
         "      hosts:\n        h: {}\n",
         "all.vars.fleetdaq_venv: templates are Ansible's"),
        ("all:\n  children:\n    hub:\n      hosts:\n        h: {fleetdaq_venv: opt/v}\n",
         "all.children.hub.hosts.h.fleetdaq_venv: 'opt/v' is not an absolute path"),
        ("all:\n  children:\n    hub:\n      hosts:\n        h: {}\n    edges:\n      hosts:\n"
         "        e1: {fleetdaq_node: n}\n        e2: {fleetdaq_node: n}\n",
         "all.children.edges.hosts.e2: node 'n' is already run by host e1"),
        ("all:\n  children:\n    hub:\n      hosts:\n        h: {}\n    ptp_grandmaster:\n"
         "      hosts:\n        h: {}\n",
         "all.children.hub.hosts.h: a ptp_grandmaster host needs fleetdaq_ptp_interface"),
        ("all:\n  children:\n    hub:\n      hosts:\n        pi-[1:3]: {}\n",
         "all.children.hub.hosts.pi-[1:3]: host ranges are not read here"),
        ("all:\n  children:\n    hub:\n      hosts:\n        h: {ansible_connection: local}\n",
         "all.children.hub.hosts.h.ansible_connection: 'local': fleetdaq fleet reaches hosts"),
        ("all:\n  children:\n    a:\n      children:\n        b:\n          children:\n"
         "            a: {}\n", "groups contain each other: a -> b -> a"),
        ("all:\n  children: [hub]\n", "all.children: expected a mapping, got list"),
        ("all:\n  children:\n    hub:\n      hosts:\n        h: {\n", ":6: "),
    ],
)  # fmt: skip
def test_a_bad_inventory_is_one_line_naming_the_file_and_key_path(
    tmp_path: Path, text: str, expected: str
):
    path = tmp_path / "inventory.yml"
    path.write_text(text)
    with pytest.raises(InventoryError) as caught:
        load_inventory(path)
    message = str(caught.value)
    assert message.startswith(str(path)), message
    assert expected in message
    assert "\n" not in message


def test_a_missing_inventory_says_so(tmp_path: Path):
    with pytest.raises(InventoryError, match="cannot read the inventory"):
        load_inventory(tmp_path / "nope.yml")


def test_every_mismatch_with_the_site_file_is_one_line(tmp_path: Path):
    path = tmp_path / "inventory.yml"
    path.write_text(TRICKY)
    site = tmp_path / "site.yaml"
    site.write_text(
        "site: s\nnodes:\n"
        + "".join(
            f"  {n}:\n    streams: {{env: {{driver: environment_sim, rate_hz: 1,"
            " channels: [{name: air, unit: degC}]}}\n"
            for n in ("wec", "am-cell", "shore")
        )
    )
    lines = mismatches(load_inventory(path), load_config(site), site)
    assert lines == [
        f"{path}: all.children.edges.children.sea.hosts.buoy-2: node 'buoy-2' (from its name "
        f"(no fleetdaq_node)) is not in {site} (nodes: wec, am-cell, shore)",
        f"{site}: nodes.shore: no host of {path} runs it (add one to the edges group with "
        "fleetdaq_node: shore)",
    ]
