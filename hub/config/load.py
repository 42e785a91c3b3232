"""Reading a site file as the hub does: every section validated in full
(`fleetdaq.hub.config.site.SiteConfig`), with the contract's one-line messages
(`fleetdaq.contract.config.load`). The hub, `fleetdaq check`, `fleetdaq demo` and the commands
that ask the hub load the site file through here."""

from __future__ import annotations

from pathlib import Path

from fleetdaq.contract.config.load import load_site, parse_site
from fleetdaq.hub.config.site import SiteConfig


def parse_config(text: str, source: str) -> SiteConfig:
    """Validate the text of a site file. `source` names it in errors.

    Raises:
        ConfigError: one line: file, key path, problem.
    """
    return parse_site(text, source, SiteConfig)


def load_config(path: str | Path) -> SiteConfig:
    """Read and validate a site file.

    Raises:
        ConfigError: one line: file, key path, problem.
    """
    return load_site(path, SiteConfig)
