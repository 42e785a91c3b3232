"""The whole site file: the hub and every node."""

from __future__ import annotations

from importlib.resources import files
from pathlib import Path
from typing import Annotated

import yaml
from pydantic import Field

from edge.config.hub import HubConfig
from edge.config.node import NodeConfig
from edge.schema import NAME, NodeName, Strict


class SiteConfig(Strict):
    """The whole site file."""

    site: Annotated[str, Field(pattern=NAME)]
    description: str = ""
    hub: HubConfig = HubConfig()
    nodes: Annotated[dict[NodeName, NodeConfig], Field(min_length=1)]

    def endpoints_for(self, node: str) -> list[str]:
        return self.nodes[node].connect or list(self.hub.listen)


def demo_config_path() -> Path:
    """The embedded default site (shipped in the package as `edge/config/demo.yaml`)."""
    return Path(str(files("edge.config").joinpath("demo.yaml")))


def effective_yaml(cfg: SiteConfig) -> str:
    """The validated config with every default filled in: what the recorder attaches to files."""
    return yaml.safe_dump(cfg.model_dump(mode="json"), sort_keys=False)
