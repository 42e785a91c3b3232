"""Snapshots on a partitioned site: each partition hub keeps a snapshot buffer of its own slice
(the main hub's holds only the main hub's), and takes a snapshot whenever the main hub takes
one for a rule or sees an alarm that may take one. (A snapshot an operator asks the main hub
for reaches the partitions as a recorder request instead, so the reply can name every file:
`fleetdaq.hub.partitions.recorders`.)

The main hub puts each trigger on ``fleetdaq/<site>/hub/snapshot/trigger`` (`SnapshotTriggers`,
told by its `SnapshotBuffer`); every partition hub takes it (`PartitionSnapshots`) and acts as
its own buffer would: a request (a rule's) is written at once, an alarm only while its recorder
is not writing and not within `min_interval_s` of the last. Each snapshot is an event of the
hub that wrote it (a partition's reach the main hub's event log like all its events), so an
operator sees where every file went.

A trigger is a small JSON object; anything else on the key is counted, raised as an event (the
first, then every 1000th) and dropped.
"""

from __future__ import annotations

import json
import logging
from typing import Any

from fleetdaq.contract.keys import SiteKeys
from fleetdaq.contract.requester_text import text_problem
from fleetdaq.hub.bus import EventBus
from fleetdaq.hub.recording.snapshots import SnapshotBuffer
from fleetdaq.hub.requests import json_object
from fleetdaq.hub.routing.router import Router

MAX_TRIGGER_BYTES = 4096
MAX_TEXT = 1000


def trigger_key(keys: SiteKeys) -> str:
    return keys.hub("snapshot/trigger")


class SnapshotTriggers:
    """The main hub's side: every trigger its snapshot buffer is told of (`send`, its
    `on_trigger`), to the partitions."""

    name = "snapshot-triggers"

    def __init__(self, router: Router, keys: SiteKeys) -> None:
        self.router = router
        self.key = trigger_key(keys)
        self.sent = 0

    def start(self) -> None:
        pass

    def stop(self) -> None:
        pass

    def failure(self) -> str | None:
        return None

    def send(self, trigger: dict[str, str]) -> None:
        self.router.session.put(self.key, json.dumps(trigger).encode())
        self.sent += 1


def parse_trigger(raw: bytes) -> dict[str, str]:
    """A trigger as sent by `SnapshotTriggers`, checked in full; ValueError says what is wrong."""
    obj = json_object(raw, MAX_TRIGGER_BYTES)
    allowed = {"alarm": {"kind", "alarm"}, "request": {"kind", "who", "note"}}
    kind = obj.get("kind")
    if kind not in allowed:
        raise ValueError(f"kind {kind!r} is not alarm or request")
    unknown = set(obj) - allowed[kind]
    if unknown:
        raise ValueError(f"unknown keys {sorted(unknown)}")
    for k, v in obj.items():
        if not isinstance(v, str) or len(v) > MAX_TEXT:
            raise ValueError(f"{k} is not a string of at most {MAX_TEXT} characters")
        why = text_problem(v, MAX_TEXT)  # who and note are written into the snapshot's file
        if why is not None:
            raise ValueError(f"{k} {why}")
    needed = allowed[kind] - {"note"}
    if not needed <= set(obj):
        raise ValueError(f"missing {sorted(needed - set(obj))}")
    return dict(obj)


class PartitionSnapshots:
    """A partition hub's side: the main hub's triggers, to this hub's own snapshot buffer."""

    name = "partition-snapshots"

    def __init__(
        self, router: Router, keys: SiteKeys, snapshots: SnapshotBuffer, bus: EventBus
    ) -> None:
        self.router = router
        self.key = trigger_key(keys)
        self.snapshots = snapshots
        self.bus = bus
        self.taken = 0
        self.malformed = 0
        self._sub: Any = None

    def start(self) -> None:
        self._sub = self.router.session.declare_subscriber(self.key, self._on_trigger)

    def stop(self) -> None:
        if self._sub is not None:
            self._sub.undeclare()
            self._sub = None

    def failure(self) -> str | None:
        return None

    def _on_trigger(self, sample: Any) -> None:
        try:
            trigger = parse_trigger(sample.payload.to_bytes())
        except ValueError as err:
            self.malformed += 1
            self.bus.emit_counted(
                self.malformed,
                logging.WARNING,
                "snapshots",
                "malformed_trigger",
                f"refused a snapshot trigger that is not one ({err})",
            )
            return
        self.taken += 1
        self.snapshots.remote(trigger)
