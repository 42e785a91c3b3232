"""The site file's `hub:` section as every machine reads it: where the hubs' routers listen and
which nodes each partition hub records (so a node finds its router), where they keep their data,
and the universal alarms (a node warns of its certificate as the hub does).

The hub's own settings (recorder, notify, dashboard, interlocks, snapshot) are keys here too, so
a misspelt key is an error on every machine, but their contents are only checked to be
mappings: the hub's schema (`fleetdaq.hub.config.hub.HubConfig`, a subclass of `HubBase`)
validates them in full.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Annotated

from pydantic import BeforeValidator, Field

from fleetdaq.contract.config.universal_alarms import UniversalAlarms
from fleetdaq.contract.schema import Endpoints, Name, Strict


def _a_mapping(value: object) -> object:
    if not isinstance(value, dict):
        shown = "null" if value is None else "a list" if isinstance(value, list) else repr(value)
        raise ValueError(f"expected a mapping of keys, got {shown}")
    return value


HubOnly = Annotated[object, BeforeValidator(_a_mapping)]
"""A section only the hub reads: here a mapping of anything; the hub's schema narrows it."""

NodePattern = Annotated[str, Field(pattern=r"^[a-z0-9_*?\[\]!-]{1,63}$")]
"""A node name or an fnmatch pattern over node names."""


class PartitionBase(Strict):
    """A partition hub (`fleetdaq hub --partition NAME`): its own router, meshed with the main
    hub's and the other partitions', recording and acking only the streams of its nodes."""

    listen: Endpoints
    """Its router's endpoints: its nodes connect here, and so do the routers of the hubs listed
    after it (the main hub first, then the partitions in file order)."""
    nodes: Annotated[list[NodePattern], Field(min_length=1)]
    """Node names or fnmatch patterns (``cell-*``); every node they match is this hub's."""
    data_dir: str | None = None
    """Recording root of this hub (default: ``<the main hub's data_dir>/<partition name>``, so
    two hubs on one machine never share a session folder; `fleetdaq hub --data` overrides)."""
    snapshot: HubOnly | None = None
    """This hub's snapshot buffer (`fleetdaq.hub.config.hub.PartitionConfig`)."""


class HubBase(Strict):
    """The `hub:` section: the parts every machine reads, and the hub's own keys."""

    listen: Endpoints = ["tcp/127.0.0.1:7447"]
    """The embedded router's endpoints; edges connect to these unless a node says otherwise."""
    partitions: Mapping[Name, PartitionBase] = {}
    """More hubs, each recording a slice of the nodes (`PartitionBase`); nodes no partition
    names are the main hub's. Empty: one hub records everything."""
    data_dir: str | None = None
    """Recording root. Default: the per-system location of
    `fleetdaq.runtime.paths.default_data_dir` (never the current directory); `fleetdaq hub
    --data` overrides."""
    recorder: HubOnly = {}
    universal_alarms: UniversalAlarms = UniversalAlarms()
    """Alarms every site gets without config; tune or switch off (`false`) each."""
    notify: HubOnly = {}
    interlocks: Mapping[str, object] = {}
    snapshot: HubOnly = {}
    dashboard: HubOnly = {}
    alarm_journal: str | None = None
    """Where alarm states and the ack/shelve audit are kept across restarts (default:
    `<data_dir>/alarms.journal`)."""
