"""What the recording wing needs of other wings, as small protocols: the composition root
(`fleetdaq.hub.composition`) hands in the real objects, so this wing imports none of theirs.

- `Refusals`: traffic on keys the site file does not define, counted where it arrives (the
  nodes wing's `fleetdaq.hub.nodes.refused.RefusedKeys`);
- `EventAcks`: the nodes' spooled events, acked once recorded and logged (the nodes wing's
  `fleetdaq.hub.nodes.event_delivery.EventDelivery`);
- `OtherHubs`: the partition hubs a main hub passes its recorder requests on to (the partitions
  wing's `fleetdaq.hub.partitions.recorders.PartitionRecorders`)."""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any, Protocol

from fleetdaq.contract.messages import Event

FORWARDED = ("start", "stop", "split", "snapshot")
"""The recorder actions a main hub passes on to its partition hubs (`status` is each
partition's report)."""

Collect = Callable[[], dict[str, dict[str, Any]]]
"""Waits for the partition hubs' answers: {partition: {ok, result, error}}."""


class Refusals(Protocol):
    @property
    def total(self) -> int: ...

    @property
    def counts(self) -> Mapping[str, int]: ...

    def refuse(self, key: str, what: str, why: str = ...) -> None:
        """Count one message refused on `key` (on Zenoh's threads: cheap, never blocks)."""
        ...


class EventAcks(Protocol):
    def recorded(self, e: Event) -> None:
        """The recorder has written `e`, or owes nothing for it (recording stopped)."""
        ...

    def flushed(self) -> None:
        """The recorder's flush succeeded with no write error pending."""
        ...

    def acks(self) -> list[tuple[str, int, int]]:
        """(node, sequence, epoch) to ack now."""
        ...

    def summary(self) -> dict[str, object]: ...


class OtherHubs(Protocol):
    def ask(self, request: dict[str, str]) -> Collect:
        """Send `request` to every partition hub now; the returned call waits for answers."""
        ...
