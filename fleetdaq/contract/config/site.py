"""The whole site file as every machine reads it: the site, every node, the routers they connect
to, security and the commands' ceiling (`SiteConfig`).

The hub-only sections (the site's `alarms:` and `rules:`, and the hub's own keys in `hub:`) are
known keys here, so a misspelt key is an error on any machine, but only the hub's schema,
`fleetdaq.hub.config.site.SiteConfig` (a subclass), checks their contents and what they name."""

from __future__ import annotations

from collections.abc import Mapping
from fnmatch import fnmatchcase
from importlib.resources import files
from pathlib import Path
from typing import Annotated

import yaml
from pydantic import Field, model_validator

from fleetdaq.contract.config.hubs import HubBase
from fleetdaq.contract.config.node import NodeConfig
from fleetdaq.contract.config.node_control import CommandsConfig
from fleetdaq.contract.config.security import SecurityConfig
from fleetdaq.contract.drivers import driver_registry
from fleetdaq.contract.schema import NAME, NodeName, Strict, ros_token, ros_token_collision


class SiteConfig(Strict):
    """The whole site file, as a node reads it."""

    site: Annotated[str, Field(pattern=NAME)]
    description: str = ""
    hub: HubBase = HubBase()
    nodes: Annotated[dict[NodeName, NodeConfig], Field(min_length=1)]
    alarms: Mapping[str, object] = {}
    """The site's own alarms (`fleetdaq.hub.config.alarms`; the hub checks them); universal
    ones: `hub.universal_alarms`."""
    rules: Mapping[str, object] = {}
    """Control rules evaluated on the hub (`fleetdaq.hub.config.control`; the hub checks
    them)."""
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

    @classmethod
    def union_tag_at(cls, loc: tuple[int | str, ...], i: int) -> bool:
        """Whether `loc[i]`, in a validation error's location, is the tag of a union pydantic
        put there (the user never wrote it): a stream's or output's driver name. The hub's
        schema adds its own unions (alarm kinds, conditions and actions)."""
        if i == 4 and loc[0] == "nodes" and loc[2] in ("streams", "outputs", "displays"):
            return loc[i] in driver_registry().found
        return False

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
    """The embedded default site (shipped in the package as
    `fleetdaq/contract/config/demo.yaml`; `config/demo.yaml` links to it)."""
    return Path(str(files("fleetdaq.contract.config").joinpath("demo.yaml")))


def effective_yaml(cfg: SiteConfig) -> str:
    """The validated config with every default filled in: what the recorder attaches to files."""
    return yaml.safe_dump(cfg.model_dump(mode="json"), sort_keys=False)
