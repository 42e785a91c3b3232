"""The partitions wing's factories. On the main hub of a partitioned site (`fleet`, `live`):
the partitions' reports, recorder requests passed on, snapshot triggers, and their streams
fetched across the mesh while watched. On a partition hub (`own`): its report to the main hub
and the snapshot triggers it takes."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

from fleetdaq.hub.context import HubContext
from fleetdaq.hub.live.foxglove.service import FoxgloveLive
from fleetdaq.hub.live.plots import LivePlots
from fleetdaq.hub.partitions.live import PartitionLive
from fleetdaq.hub.partitions.recorders import PartitionRecorders, recorder_key
from fleetdaq.hub.partitions.runtime import PartitionReport, partition_key
from fleetdaq.hub.partitions.snapshots import PartitionSnapshots, SnapshotTriggers
from fleetdaq.hub.partitions.watch import PartitionWatch
from fleetdaq.hub.recording.snapshots import SnapshotBuffer


@dataclass(frozen=True, slots=True)
class Partitions:
    """The main hub's view of its partition hubs."""

    watch: PartitionWatch
    recorders: PartitionRecorders
    triggers: SnapshotTriggers | None
    """With the main hub's snapshot buffer on: each partition hub keeps one of its slice,
    triggered with this one's."""


@dataclass(frozen=True, slots=True)
class OwnPartition:
    """A partition hub's own side of the mesh."""

    report: PartitionReport
    snapshot_requests: PartitionSnapshots | None
    recorder_key: str
    status_key: str


def fleet(ctx: HubContext) -> Partitions | None:
    """The main hub's, or None on a site without partitions."""
    site = ctx.site
    if not site.hub.partitions:
        return None
    recorders = PartitionRecorders(
        ctx.router,
        ctx.keys,
        list(site.hub.partitions),
        ctx.bus,
        snapshots_off=frozenset(
            name
            for name, part in site.hub.partitions.items()
            if not (part.snapshot or site.hub.snapshot).enabled
        ),
    )
    triggers = SnapshotTriggers(ctx.router, ctx.keys) if site.hub.snapshot.enabled else None
    return Partitions(PartitionWatch(ctx.router, site, ctx.bus, ctx.model), recorders, triggers)


def live(
    ctx: HubContext, plots: LivePlots | None, foxglove: Sequence[FoxgloveLive]
) -> PartitionLive | None:
    """A partition's streams, fetched across the mesh only while somebody looks at them (the
    plots, Foxglove), and always those whose channels the alarms, rules and interlocks here
    watch; None when nothing here could want one."""
    site = ctx.site
    watched = site.watched_partition_streams()
    if not site.hub.partitions:
        return None
    if plots is None and not foxglove and not watched:
        return None
    return PartitionLive(ctx.router, site, ctx.bus, plots=plots, foxglove=foxglove)


def own(ctx: HubContext, snapshots: SnapshotBuffer | None) -> OwnPartition:
    """A partition hub's (`ctx.partition` set)."""
    name = ctx.partition
    assert name is not None
    return OwnPartition(
        PartitionReport(ctx.router, ctx.keys, name, ctx.model, ctx.bus),
        PartitionSnapshots(ctx.router, ctx.keys, snapshots, ctx.bus)
        if snapshots is not None
        else None,
        recorder_key(ctx.keys, name),
        partition_key(ctx.keys, name, "status"),
    )
