"""The fleet's Ansible YAML inventory, read into typed hosts.

The same file Ansible deploys with (``ansible-playbook -i``): groups ``hub`` (one host, plus
one per partition hub, each with ``fleetdaq_partition: NAME``),
``edges`` and ``ptp_grandmaster``, connection variables (``ansible_host``, ``ansible_port``,
``ansible_user``, ``ansible_ssh_private_key_file``) and fleetdaq's own (``fleetdaq_node``,
``fleetdaq_site_file``, ``fleetdaq_venv``, ...; see `Host`). Variables are resolved as Ansible
resolves them for plain values: ``all.vars``, then each group's vars from the shallowest group
to the deepest (groups at one depth by ``ansible_group_priority``, then name), then host vars.
Templates (``{{ ... }}``), host ranges (``pi-[1:4]``) and variable files beside the inventory
(``group_vars/``) are Ansible's alone: the first two are refused with a clear line, put
fleetdaq's variables in the inventory itself.

Hosts in none of the three groups are left out (an inventory may describe more than the
fleet). Every mistake is one line: ``file: key.path: problem``.
"""

from __future__ import annotations

import re
from collections.abc import Hashable, Iterable
from dataclasses import dataclass, field
from pathlib import Path

import yaml

from fleetdaq.fleet.errors import InventoryError

HUB, EDGES, GRANDMASTER = "hub", "edges", "ptp_grandmaster"
FLEET_GROUPS = (HUB, EDGES, GRANDMASTER)
DEFAULT_SITE_FILE = "/etc/fleetdaq/site.yaml"
DEFAULT_VENV = "/opt/fleetdaq/venv"
DEFAULT_STATE_DIR = "/var/lib/fleetdaq"
"""Where the services keep their files: systemd's ``StateDirectory=fleetdaq``."""

_GROUP_KEYS = ("hosts", "vars", "children")
_SSH_CONNECTIONS = ("ssh", "paramiko", "smart")
_PATH_VARS = (
    "fleetdaq_site_file",
    "fleetdaq_venv",
    "fleetdaq_state_dir",
    "fleetdaq_spool_dir",
    "fleetdaq_data_dir",
)


@dataclass(frozen=True, slots=True)
class Host:
    """One machine of the fleet, as the inventory describes it (every default filled in)."""

    name: str
    """The inventory hostname."""
    where: str
    """Key path of its first definition in the inventory (for messages)."""
    address: str
    """``ansible_host`` (default: the name)."""
    port: int = 22
    """``ansible_port``."""
    user: str | None = None
    """``ansible_user`` (default: the user running fleetdaq, as ssh)."""
    identity: str | None = None
    """``ansible_ssh_private_key_file``."""
    groups: frozenset[str] = frozenset()
    """Every fleet group the host is in (directly or through a child group)."""
    node: str = ""
    """``fleetdaq_node``: the node it runs in the site file (default: the name)."""
    site_file: str = DEFAULT_SITE_FILE
    """``fleetdaq_site_file``: the site file on the host."""
    venv: str = DEFAULT_VENV
    """``fleetdaq_venv``: the virtualenv fleetdaq is installed in on the host."""
    prefix: str = ""
    """``fleetdaq_prefix``: a root every fleetdaq path on the host is under (tests, chroots)."""
    state_dir: str = DEFAULT_STATE_DIR
    """``fleetdaq_state_dir``: the services' state directory (spool and recordings below)."""
    spool_dir: str | None = None
    """``fleetdaq_spool_dir``: the spool root, when neither the site file nor the default."""
    data_dir: str | None = None
    """``fleetdaq_data_dir``: the hub's recording root, likewise."""
    partition: str | None = None
    """``fleetdaq_partition``: on a host of the hub group, the partition hub it runs (the site
    file's ``hub.partitions``); None: the main hub."""
    ptp_interface: str | None = None
    """``fleetdaq_ptp_interface``: the host runs ``ptp4l@<interface>``."""
    ptp_timestamping: str = "software"
    """``fleetdaq_ptp_timestamping``: ``hardware`` adds ``phc2sys``."""

    @property
    def is_hub(self) -> bool:
        return HUB in self.groups

    @property
    def is_edge(self) -> bool:
        return EDGES in self.groups

    @property
    def is_grandmaster(self) -> bool:
        return GRANDMASTER in self.groups

    @property
    def roles(self) -> tuple[str, ...]:
        """The fleet groups it is in, in a fixed order."""
        return tuple(g for g in FLEET_GROUPS if g in self.groups)

    def on_host(self, path: str) -> str:
        """An absolute path on the host, under `prefix`."""
        return self.prefix.rstrip("/") + path if self.prefix else path


@dataclass(frozen=True, slots=True)
class Inventory:
    path: Path
    hosts: tuple[Host, ...]
    """The fleet's hosts, in the order the file first names them."""

    @property
    def hub(self) -> Host:
        """The main hub."""
        return next(h for h in self.hosts if h.is_hub and h.partition is None)

    @property
    def edges(self) -> tuple[Host, ...]:
        return tuple(h for h in self.hosts if h.is_edge)

    def find(self, name: str) -> Host | None:
        """A host by inventory name, else the edge running node `name`."""
        for h in self.hosts:
            if h.name == name:
                return h
        return next((h for h in self.edges if h.node == name), None)


# --- reading --------------------------------------------------------------------------------


class _UniqueKeyLoader(yaml.SafeLoader):
    """PyYAML keeps the last of two equal keys: two hosts named alike would quietly be one."""

    def construct_mapping(
        self, node: yaml.MappingNode, deep: bool = False
    ) -> dict[Hashable, object]:
        seen: dict[str | int, int] = {}
        for key_node, _ in node.value:
            key = self.construct_object(key_node, deep=True)
            line = key_node.start_mark.line + 1
            if isinstance(key, str | int) and key in seen:
                raise yaml.constructor.ConstructorError(
                    None,
                    None,
                    f"duplicate key {key!r} (first on line {seen[key]})",
                    key_node.start_mark,
                )
            if isinstance(key, str | int):
                seen[key] = line
        return super().construct_mapping(node, deep)


@dataclass
class _Group:
    name: str
    depth: int = 0
    priority: int = 1
    parents: set[str] = field(default_factory=set)
    vars: dict[str, tuple[object, str]] = field(default_factory=dict)


@dataclass
class _HostDef:
    name: str
    where: str
    groups: set[str] = field(default_factory=set)
    vars: dict[str, tuple[object, str]] = field(default_factory=dict)


class _Reader:
    def __init__(self, path: Path) -> None:
        self.path = path
        self.groups: dict[str, _Group] = {"all": _Group("all")}
        self.hosts: dict[str, _HostDef] = {}

    def fail(self, where: str, problem: str) -> InventoryError:
        return InventoryError(
            f"{self.path}: {where}: {problem}" if where else f"{self.path}: {problem}"
        )

    def read(self, doc: object) -> None:
        if doc is None:
            raise self.fail("", "empty inventory (expected `all:` with `children:` hub, edges)")
        if not isinstance(doc, dict):
            raise self.fail("", "not a YAML inventory (expected a mapping of groups, `all:` first)")
        for name, body in doc.items():
            self.group(str(name), body, str(name), parent=None if name == "all" else "all")

    def group(self, name: str, body: object, where: str, parent: str | None) -> None:
        group = self.groups.setdefault(name, _Group(name))
        if parent is not None:
            if name == "all":
                raise self.fail(where, "`all` cannot be a child group")
            group.parents.add(parent)
        if body is None:
            return
        if not isinstance(body, dict):
            raise self.fail(where, f"a group is a mapping of {', '.join(_GROUP_KEYS)}")
        for key in body:
            if key not in _GROUP_KEYS:
                raise self.fail(
                    f"{where}.{key}", f"unknown key (a group has {', '.join(_GROUP_KEYS)})"
                )
        group_vars = body.get("vars")
        if group_vars is not None:
            for var, value in self.mapping(group_vars, f"{where}.vars").items():
                group.vars[var] = (value, f"{where}.vars.{var}")
        hosts = body.get("hosts")
        if hosts is not None:
            for host_name, host_vars in self.mapping(hosts, f"{where}.hosts").items():
                self.host(host_name, host_vars, f"{where}.hosts.{host_name}", name)
        children = body.get("children")
        if children is not None:
            for child, child_body in self.mapping(children, f"{where}.children").items():
                self.group(child, child_body, f"{where}.children.{child}", parent=name)

    def host(self, name: str, host_vars: object, where: str, group: str) -> None:
        if re.search(r"\[[^\]]*:[^\]]*\]", name):
            raise self.fail(where, "host ranges are not read here: list each host")
        if re.fullmatch(r"[^:\[\]]+:\d+", name):
            raise self.fail(where, "give the port as ansible_port, not in the host name")
        host = self.hosts.setdefault(name, _HostDef(name, where))
        host.groups.add(group)
        if host_vars is not None:
            for var, value in self.mapping(host_vars, where).items():
                host.vars[var] = (value, f"{where}.{var}")

    def mapping(self, value: object, where: str) -> dict[str, object]:
        if not isinstance(value, dict):
            raise self.fail(where, f"expected a mapping, got {type(value).__name__}")
        for key in value:
            if not isinstance(key, str):
                raise self.fail(f"{where}.{key}", "names are strings (quote it)")
        return value

    def resolve_depths(self) -> None:
        """Depth = the longest chain of parents up to ``all`` (Ansible's group depth)."""
        done: dict[str, int] = {"all": 0}

        def depth(name: str, chain: tuple[str, ...]) -> int:
            if name in done:
                return done[name]
            if name in chain:
                cycle = " -> ".join((*chain[chain.index(name) :], name))
                raise self.fail("", f"groups contain each other: {cycle}")
            parents = self.groups[name].parents or {"all"}
            d = 1 + max(depth(p, (*chain, name)) for p in parents)
            done[name] = d
            return d

        for name, group in self.groups.items():
            group.depth = depth(name, ())
            prio, where = group.vars.get("ansible_group_priority", (1, ""))
            if isinstance(prio, bool) or not isinstance(prio, int):
                raise self.fail(where, "ansible_group_priority is an integer")
            group.priority = prio

    def ancestors(self, names: Iterable[str]) -> set[str]:
        out: set[str] = set()
        todo = list(names)
        while todo:
            name = todo.pop()
            if name not in out:
                out.add(name)
                todo.extend(self.groups[name].parents)
        return out | {"all"}

    def host_vars(self, host: _HostDef) -> tuple[set[str], dict[str, tuple[object, str]]]:
        groups = self.ancestors(host.groups)
        merged: dict[str, tuple[object, str]] = {}
        order = sorted(
            (self.groups[g] for g in groups), key=lambda g: (g.depth, g.priority, g.name)
        )
        for group in order:
            merged.update(group.vars)
        merged.update(host.vars)
        return groups, merged


def _text(reader: _Reader, vars_: dict[str, tuple[object, str]], name: str) -> str | None:
    if name not in vars_:
        return None
    value, where = vars_[name]
    if isinstance(value, bool) or not isinstance(value, str | int | float):
        raise reader.fail(where, f"expected a string, got {type(value).__name__}")
    text = str(value)
    if "{{" in text or "{%" in text:
        raise reader.fail(where, "templates are Ansible's: fleetdaq reads plain values")
    return text


def _path(reader: _Reader, vars_: dict[str, tuple[object, str]], name: str) -> str | None:
    text = _text(reader, vars_, name)
    if text is not None and not text.startswith("/"):
        raise reader.fail(vars_[name][1], f"{text!r} is not an absolute path")
    return text


def _build(reader: _Reader, hd: _HostDef) -> Host | None:
    groups, vars_ = reader.host_vars(hd)
    fleet = frozenset(groups) & frozenset(FLEET_GROUPS)
    if not fleet:
        return None
    connection = _text(reader, vars_, "ansible_connection")
    if connection is not None and connection not in _SSH_CONNECTIONS:
        raise reader.fail(
            vars_["ansible_connection"][1],
            f"{connection!r}: fleetdaq fleet reaches hosts over SSH only",
        )
    port_text = _text(reader, vars_, "ansible_port") or "22"
    if not port_text.isdigit() or not 0 < int(port_text) < 65536:
        raise reader.fail(vars_["ansible_port"][1], f"{port_text!r} is not a port number")
    timestamping = _text(reader, vars_, "fleetdaq_ptp_timestamping") or "software"
    if timestamping not in ("software", "hardware"):
        raise reader.fail(
            vars_["fleetdaq_ptp_timestamping"][1],
            f"{timestamping!r}: expected software or hardware",
        )
    interface = _text(reader, vars_, "fleetdaq_ptp_interface")
    if GRANDMASTER in fleet and not interface:
        raise reader.fail(hd.where, "a ptp_grandmaster host needs fleetdaq_ptp_interface")
    paths = {name: _path(reader, vars_, name) for name in _PATH_VARS}
    prefix = _path(reader, vars_, "fleetdaq_prefix") or ""
    return Host(
        name=hd.name,
        where=hd.where,
        address=_text(reader, vars_, "ansible_host") or hd.name,
        port=int(port_text),
        user=_text(reader, vars_, "ansible_user"),
        identity=_text(reader, vars_, "ansible_ssh_private_key_file")
        or _text(reader, vars_, "ansible_private_key_file"),
        groups=fleet,
        node=_text(reader, vars_, "fleetdaq_node") or hd.name,
        site_file=paths["fleetdaq_site_file"] or DEFAULT_SITE_FILE,
        venv=paths["fleetdaq_venv"] or DEFAULT_VENV,
        prefix=prefix,
        state_dir=paths["fleetdaq_state_dir"] or DEFAULT_STATE_DIR,
        spool_dir=paths["fleetdaq_spool_dir"],
        data_dir=paths["fleetdaq_data_dir"],
        partition=_text(reader, vars_, "fleetdaq_partition") if HUB in fleet else None,
        ptp_interface=interface,
        ptp_timestamping=timestamping,
    )


def load_inventory(path: str | Path) -> Inventory:
    """Read and check an inventory.

    Raises:
        InventoryError: unreadable, not YAML, not an inventory, a bad value, no hub or more
            than one, two edges running one node. One line: ``file: key.path: problem``.
    """
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as err:
        raise InventoryError(f"{path}: cannot read the inventory: {err.strerror or err}") from err
    try:
        doc = yaml.load(text, Loader=_UniqueKeyLoader)  # a SafeLoader
    except yaml.MarkedYAMLError as err:
        mark = err.problem_mark
        line = f":{mark.line + 1}" if mark is not None else ""
        raise InventoryError(f"{path}{line}: {err.problem or err}") from err
    except yaml.YAMLError as err:
        raise InventoryError(f"{path}: not YAML: {err}") from err
    reader = _Reader(path)
    reader.read(doc)
    reader.resolve_depths()
    hosts = [h for h in (_build(reader, hd) for hd in reader.hosts.values()) if h is not None]
    hubs = [h for h in hosts if h.is_hub and h.partition is None]
    if len(hubs) != 1:
        found = ", ".join(h.name for h in hubs) or "none"
        raise reader.fail(
            _group_where(reader, HUB),
            f"the hub group has one main hub (found: {found}); any other hub host names the "
            "partition it runs (fleetdaq_partition)",
        )
    partitions: dict[str, Host] = {}
    for h in hosts:
        if h.partition is not None:
            if h.partition in partitions:
                other = partitions[h.partition].name
                raise reader.fail(h.where, f"partition {h.partition!r} is already run by {other}")
            partitions[h.partition] = h
    nodes: dict[str, Host] = {}
    for h in hosts:
        if h.is_edge:
            if h.node in nodes:
                raise reader.fail(
                    h.where, f"node {h.node!r} is already run by host {nodes[h.node].name}"
                )
            nodes[h.node] = h
    return Inventory(path, tuple(hosts))


def _group_where(reader: _Reader, name: str) -> str:
    return f"all.children.{name}.hosts" if name in reader.groups else f"all.children.{name}"
