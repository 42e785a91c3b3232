"""fleetdaq: data acquisition and supervisory control for test rigs (edges -> Zenoh -> hub ->
MCAP). One import name: `fleetdaq.edge` (the agent), `fleetdaq.hub`, `fleetdaq.ptp`, the shared
`fleetdaq.contract` and `fleetdaq.runtime`, and on top the CLI (`fleetdaq.cli`), analysis
(`fleetdaq.analysis`, `fleetdaq.read`) and fleet over SSH (`fleetdaq.fleet`).

`fleetdaq/edge`, `fleetdaq/hub` and `fleetdaq/ptp` are links to the repository's top-level
folders: the build, mypy, import-linter and editable installs all see one package tree."""

from __future__ import annotations

__version__ = "0.1.0"
