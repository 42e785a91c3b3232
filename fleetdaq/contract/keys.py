"""The Zenoh key space: every key fleetdaq uses is built and parsed here, nowhere else.

``fleetdaq/<site>/<node>/...``:

| key                          | what                                          | direction  |
|------------------------------|-----------------------------------------------|------------|
| ``<node>/data/<stream>``     | sample batches (SampleBatch)                  | edge → hub |
| ``<node>/health``            | node health (NodeHealth), ~1 Hz               | edge → hub |
| ``<node>/events``            | system messages (Event)                       | edge → hub |
| ``<node>/alive``             | liveliness token                              | edge       |
| ``<node>/ack/<stream>``      | highest sequence durably recorded (uint64)    | hub → edge |
|                              | (``ack/events``: of the node's event spool)   |            |
| ``<node>/out/<output>``      | commands to an output (request/reply)         | hub → edge |
| ``hub/<what>``               | heartbeat, status and the hub's services      | hub        |
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import Enum
from typing import Final

ROOT: Final = "fleetdaq"
HUB: Final = "hub"
"""The node name reserved for the hub's own keys."""


EVENTS_STREAM: Final = "events"
"""A node's events as a spooled pseudo-stream: its acks come on ``<node>/ack/events`` and its
spool is the folder ``events`` beside the streams' (a name no stream may take:
`fleetdaq.contract.schema.RESERVED_STREAM_NAMES`)."""


class Kind(Enum):
    DATA = "data"
    HEALTH = "health"
    EVENTS = "events"
    ALIVE = "alive"
    ACK = "ack"
    OUT = "out"
    HUB = "hub"


_WITH_NAME = {Kind.DATA, Kind.ACK, Kind.OUT}


@dataclass(frozen=True, slots=True)
class Key:
    """A parsed key: whose it is and what it carries."""

    site: str
    node: str
    """The node (``hub`` for the hub's keys)."""
    kind: Kind
    name: str = ""
    """The stream (data, ack), the output (out) or the hub service (hub); "" otherwise."""


class SiteKeys:
    """The keys of one site."""

    def __init__(self, site: str) -> None:
        self.site = site
        self.prefix = f"{ROOT}/{site}"

    def data(self, node: str, stream: str) -> str:
        return f"{self.prefix}/{node}/data/{stream}"

    def health(self, node: str) -> str:
        return f"{self.prefix}/{node}/health"

    def events(self, node: str) -> str:
        return f"{self.prefix}/{node}/events"

    def alive(self, node: str) -> str:
        return f"{self.prefix}/{node}/alive"

    def ack(self, node: str, stream: str) -> str:
        return f"{self.prefix}/{node}/ack/{stream}"

    def out(self, node: str, output: str) -> str:
        return f"{self.prefix}/{node}/out/{output}"

    def hub(self, what: str) -> str:
        return f"{self.prefix}/{HUB}/{what}"

    # Selectors (key expressions matching many keys)

    @property
    def all_data(self) -> str:
        return f"{self.prefix}/*/data/*"

    @property
    def all_health(self) -> str:
        return f"{self.prefix}/*/health"

    @property
    def all_events(self) -> str:
        return f"{self.prefix}/*/events"

    @property
    def all_alive(self) -> str:
        return f"{self.prefix}/*/alive"

    @property
    def everything(self) -> str:
        return f"{self.prefix}/**"

    def acks_of(self, node: str) -> str:
        return f"{self.prefix}/{node}/ack/*"

    def outs_of(self, node: str) -> str:
        return f"{self.prefix}/{node}/out/*"

    def parse(self, key: str) -> Key | None:
        """What a key of this site is, or None for anything that is not one of ours."""
        parts = key.split("/")
        if len(parts) < 4 or parts[0] != ROOT or parts[1] != self.site or not parts[2]:
            return None
        node = parts[2]
        if node == HUB:
            return Key(self.site, node, Kind.HUB, "/".join(parts[3:]))
        try:
            kind = Kind(parts[3])
        except ValueError:
            return None
        if kind is Kind.HUB:
            return None
        if kind in _WITH_NAME:
            if len(parts) != 5 or not parts[4]:
                return None
            return Key(self.site, node, kind, parts[4])
        if len(parts) != 4:
            return None
        return Key(self.site, node, kind)
