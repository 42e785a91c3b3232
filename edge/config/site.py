"""The whole site file: the hub and every node."""

from __future__ import annotations

from importlib.resources import files
from pathlib import Path
from typing import Annotated, Any

import yaml
from pydantic import Field, model_validator

from edge.config.alarms import AlarmName, AlarmSpec
from edge.config.hub import HubConfig
from edge.config.node import NodeConfig
from edge.schema import NAME, NodeName, Strict


class SiteConfig(Strict):
    """The whole site file."""

    site: Annotated[str, Field(pattern=NAME)]
    description: str = ""
    hub: HubConfig = HubConfig()
    nodes: Annotated[dict[NodeName, NodeConfig], Field(min_length=1)]
    alarms: dict[AlarmName, AlarmSpec] = {}
    """The site's own alarms (`edge.config.alarms`); universal ones: `hub.universal_alarms`."""

    @model_validator(mode="after")
    def _alarms_watch_what_exists(self) -> SiteConfig:
        for name, spec in self.alarms.items():
            problem = _unknown_target(self, spec)
            if problem:
                raise ValueError(f"alarms.{name}: {problem}")
        return self

    def endpoints_for(self, node: str) -> list[str]:
        return self.nodes[node].connect or list(self.hub.listen)


def demo_config_path() -> Path:
    """The embedded default site (shipped in the package as `edge/config/demo.yaml`)."""
    return Path(str(files("edge.config").joinpath("demo.yaml")))


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
    if node is None:
        return None
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
