"""The inventory against the site file: every edge host runs a node of the site, and every node
of the site has a host. Each mismatch is one line."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

from fleetdaq.fleet.inventory import Inventory

if TYPE_CHECKING:
    from fleetdaq.contract.config.site import SiteConfig


def mismatches(inventory: Inventory, site: SiteConfig, site_path: str | Path) -> list[str]:
    """One line per mismatch (empty: they agree), the inventory's first."""
    out: list[str] = []
    nodes = list(site.nodes)
    for host in inventory.edges:
        if host.node not in site.nodes:
            how = "fleetdaq_node" if host.node != host.name else "its name (no fleetdaq_node)"
            out.append(
                f"{inventory.path}: {host.where}: node {host.node!r} (from {how}) is not in "
                f"{site_path} (nodes: {', '.join(nodes)})"
            )
    hosted = {h.node for h in inventory.edges}
    for node in nodes:
        if node not in hosted:
            out.append(
                f"{site_path}: nodes.{node}: no host of {inventory.path} runs it (add one to "
                f"the edges group with fleetdaq_node: {node})"
            )
    return out
