"""The whole site file: the hub and every node."""

from __future__ import annotations

from fnmatch import fnmatchcase
from importlib.resources import files
from pathlib import Path
from typing import Annotated, Any

import yaml
from pydantic import Field, model_validator

from fleetdaq.contract.config.node import NodeConfig
from fleetdaq.contract.config.node_control import CommandsConfig
from fleetdaq.contract.config.security import SecurityConfig
from fleetdaq.contract.schema import NAME, NodeName, Strict, ros_token, ros_token_collision
from fleetdaq.hub.config.alarms import AlarmName, AlarmSpec, alarm_names
from fleetdaq.hub.config.control import RuleConfig, RuleName, referenced
from fleetdaq.hub.config.hub import HubConfig


class SiteConfig(Strict):
    """The whole site file."""

    site: Annotated[str, Field(pattern=NAME)]
    description: str = ""
    hub: HubConfig = HubConfig()
    nodes: Annotated[dict[NodeName, NodeConfig], Field(min_length=1)]
    alarms: dict[AlarmName, AlarmSpec] = {}
    """The site's own alarms (`fleetdaq.hub.config.alarms`); universal ones:
    `hub.universal_alarms`."""
    rules: dict[RuleName, RuleConfig] = {}
    """Control rules evaluated on the hub (`fleetdaq.hub.config.control`)."""
    commands: CommandsConfig = CommandsConfig()
    """The site's ceiling on a command's age (`fleetdaq.contract.config.node_control`)."""
    security: SecurityConfig = SecurityConfig()
    """Mutual TLS and access control (`fleetdaq.contract.config.security`)."""

    @model_validator(mode="after")
    def _nodes_record_under_distinct_ros_names(self) -> SiteConfig:
        if pair := ros_token_collision(list(self.nodes)):
            a, b = pair
            raise ValueError(
                f"nodes.{b}: node name {b!r} is recorded as /{ros_token(b)}, like nodes.{a} "
                "('-' is recorded as '_' in ROS 2 topic names); rename one"
            )
        return self

    @model_validator(mode="after")
    def _partitions_slice_the_nodes(self) -> SiteConfig:
        parts = self.hub.partitions
        if not parts:
            return self
        owner: dict[str, str] = {}
        listened = {e: "hub.listen" for e in self.hub.listen}
        for name, part in parts.items():
            for i, pattern in enumerate(part.nodes):
                where = f"hub.partitions.{name}.nodes[{i}]"
                matched = [n for n in self.nodes if fnmatchcase(n, pattern)]
                if not matched:
                    raise ValueError(
                        f"{where}: {pattern!r} names no node (nodes: {', '.join(self.nodes)})"
                    )
                for node in matched:
                    if owner.get(node, name) != name:
                        raise ValueError(
                            f"{where}: node {node!r} is already recorded by partition "
                            f"{owner[node]!r} (a node belongs to exactly one hub)"
                        )
                    owner[node] = name
            for i, endpoint in enumerate(part.listen):
                if endpoint in listened:
                    raise ValueError(
                        f"hub.partitions.{name}.listen[{i}]: {endpoint!r} is also "
                        f"{listened[endpoint]} (every hub has a router of its own)"
                    )
                listened[endpoint] = f"hub.partitions.{name}.listen"
        return self

    @model_validator(mode="after")
    def _command_ages_under_the_ceiling(self) -> SiteConfig:
        ceiling = self.commands.max_age_s
        for node, cfg in self.nodes.items():
            control = cfg.control
            if "max_command_age_s" in control.model_fields_set and (
                control.max_command_age_s > ceiling
            ):
                raise ValueError(
                    f"nodes.{node}.control.max_command_age_s: {control.max_command_age_s:g} s is "
                    f"above the site's ceiling commands.max_age_s ({ceiling:g} s); lower it, or "
                    "raise the ceiling"
                )
        return self

    def command_age_limit_s(self, node: str) -> float:
        """The oldest a command to `node` may be (either way of its clock), in seconds: its
        `control.max_command_age_s`, never above the site's `commands.max_age_s`."""
        return min(self.nodes[node].control.max_command_age_s, self.commands.max_age_s)

    @model_validator(mode="after")
    def _tls_everywhere(self) -> SiteConfig:
        if not self.security.tls:
            return self
        links = [(f"hub.listen[{i}]", e) for i, e in enumerate(self.hub.listen)]
        for name, part in self.hub.partitions.items():
            links += [(f"hub.partitions.{name}.listen[{i}]", e) for i, e in enumerate(part.listen)]
        for node, cfg in self.nodes.items():
            links += [(f"nodes.{node}.connect[{i}]", e) for i, e in enumerate(cfg.connect or [])]
        for where, endpoint in links:
            if not endpoint.startswith("tls/"):
                raise ValueError(
                    f"{where}: {endpoint!r} is not tls/HOST:PORT, and security.tls is on "
                    f"(every link is mutual TLS: write tls/{endpoint.partition('/')[2]})"
                )
        return self

    @model_validator(mode="after")
    def _alarms_watch_what_exists(self) -> SiteConfig:
        for name, spec in self.alarms.items():
            problem = _unknown_target(self, spec)
            if problem:
                raise ValueError(f"alarms.{name}: {problem}")
        return self

    @model_validator(mode="after")
    def _control_names_what_exists(self) -> SiteConfig:
        names = alarm_names(self)
        for where, cond_trees, actions, named in _control_parts(self):
            outputs = list(named)
            for tree in cond_trees:
                channels, alarms, nodes, outs = referenced(tree)
                for ref in channels:
                    problem = _unknown_target(self, _Ref(channel=ref))
                    if problem:
                        raise ValueError(f"{where}: {problem}")
                for alarm in alarms:
                    if alarm not in names:
                        raise ValueError(f"{where}: no alarm named {alarm!r}")
                for node in nodes:
                    if node not in self.nodes:
                        raise ValueError(f"{where}: no node {node!r}")
                outputs += outs
            for action in actions:
                target = getattr(action, "set", None) or getattr(action, "pulse", None)
                if target:
                    outputs.append(target)
            for ref in outputs:
                node, output = ref.split("/")
                if node not in self.nodes:
                    raise ValueError(f"{where}: no node {node!r} (in {ref!r})")
                if output not in getattr(self.nodes[node], "outputs", {}):
                    raise ValueError(f"{where}: node {node!r} has no output {output!r}")
        return self

    def watched_partition_streams(self) -> frozenset[str]:
        """The partitions' streams (``node/stream``) whose channels a channel alarm, a rule or
        an interlock watches: they run on the main hub, which follows those streams across
        the mesh for as long as it runs (`fleetdaq.hub.partitions.live`)."""
        if not self.hub.partitions:
            return frozenset()
        channels = [getattr(spec, "channel", None) for spec in self.alarms.values()]
        for _, trees, _, _ in _control_parts(self):
            channels += [ch for tree in trees for ch in referenced(tree)[0]]
        return frozenset(
            "/".join(ch.split("/")[:2])
            for ch in channels
            if ch and self.partition_of(ch.split("/")[0]) is not None
        )

    def endpoints_for(self, node: str) -> list[str]:
        """The router a node connects to: its own `connect`, else its hub's `listen`."""
        if self.nodes[node].connect:
            return list(self.nodes[node].connect or [])
        part = self.partition_of(node)
        return list(self.hub.partitions[part].listen if part else self.hub.listen)

    def partition_of(self, node: str) -> str | None:
        """The partition hub that records `node`; None: the main hub."""
        for name, part in self.hub.partitions.items():
            if any(fnmatchcase(node, pattern) for pattern in part.nodes):
                return name
        return None

    def nodes_of(self, partition: str | None) -> list[str]:
        """The nodes whose streams a hub records and acks (None: the main hub), in file order."""
        return [n for n in self.nodes if self.partition_of(n) == partition]

    def mesh_connect(self, partition: str | None) -> list[str]:
        """The routers a hub's router connects to: every hub listed before it (the main hub
        first, then the partitions in file order), so each pair of routers has one link and the
        routers form a full mesh; Zenoh reconnects a link by itself when a router returns."""
        if partition is None:
            return []
        out = list(self.hub.listen)
        for name, part in self.hub.partitions.items():
            if name == partition:
                return out
            out += part.listen
        raise KeyError(partition)


def demo_config_path() -> Path:
    """The embedded default site (shipped in the package as `edge/config/demo.yaml`)."""
    return Path(str(files("fleetdaq.contract.config").joinpath("demo.yaml")))


def effective_yaml(cfg: SiteConfig) -> str:
    """The validated config with every default filled in: what the recorder attaches to files."""
    return yaml.safe_dump(cfg.model_dump(mode="json"), sort_keys=False)


def _unknown_target(site: SiteConfig, spec: Any) -> str | None:
    """What an alarm names that the site does not have (None: all there)."""
    target = getattr(spec, "channel", None) or getattr(spec, "stream", None)
    node = getattr(spec, "node", None)
    if target is not None:
        parts = target.split("/")
        node = parts[0]
    if node is None or node == "hub":  # the main hub's own machine
        return None
    if target is None and node.startswith("hub/"):  # a partition hub's machine
        name = node.removeprefix("hub/")
        named = ", ".join(site.hub.partitions) or "none"
        return None if name in site.hub.partitions else f"no partition hub {name!r} ({named})"
    if node not in site.nodes:
        return f"no node {node!r} (nodes: {', '.join(site.nodes)})"
    if target is None:
        return None
    streams = site.nodes[node].streams
    if parts[1] not in streams:
        return f"node {node!r} has no stream {parts[1]!r} (streams: {', '.join(streams)})"
    if len(parts) == 3 and parts[2] not in [c.name for c in streams[parts[1]].channels]:
        return f"stream {node}/{parts[1]} has no channel {parts[2]!r}"
    return None


class _Ref:
    """A reference to a channel, shaped like a channel alarm for `_unknown_target`."""

    def __init__(self, channel: str) -> None:
        self.channel = channel
        self.stream = None
        self.node = None


def _control_parts(site: SiteConfig) -> list[tuple[str, list[Any], list[Any], list[str]]]:
    """(where, condition trees, actions, output references) of every rule and interlock."""
    out: list[tuple[str, list[Any], list[Any], list[str]]] = []
    for name, rule in site.rules.items():
        trees = [rule.when] + ([rule.precondition] if rule.precondition is not None else [])
        out.append((f"rules.{name}", trees, [*rule.do, *rule.on_clear], []))
    for name, lock in site.hub.interlocks.items():
        out.append((f"hub.interlocks.{name}", [lock.when], [], list(lock.outputs)))
    return out
