"""The recording wing's factory: the batch feed, the recorder and the snapshot buffer of one
hub, and its recorder requests.

What it needs of other wings comes in as arguments typed by `fleetdaq.hub.recording.seams`
(refused keys and event acks of the nodes wing, the partition hubs a main hub asks), so this
wing imports none of theirs."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from fleetdaq.hub.config.hub import SnapshotConfig
from fleetdaq.hub.context import HubContext
from fleetdaq.hub.read_model import HubView
from fleetdaq.hub.recording.batch_feed import BatchFeed
from fleetdaq.hub.recording.recorder import Recorder
from fleetdaq.hub.recording.requests import RecorderRequests
from fleetdaq.hub.recording.seams import EventAcks, OtherHubs, Refusals
from fleetdaq.hub.recording.snapshots import SnapshotBuffer


@dataclass(frozen=True, slots=True)
class RecordingWing:
    feed: BatchFeed
    """Every accepted batch, to the services that look at data (alarms, rules, plots, ...)."""
    recorder: Recorder
    snapshots: SnapshotBuffer | None
    """None when this hub keeps no snapshot buffer (its `snapshot.enabled`)."""


def snapshot_config(ctx: HubContext) -> SnapshotConfig:
    """`hub.snapshot`, or a partition hub's own (`hub.partitions.<name>.snapshot`) if set."""
    site = ctx.site
    own = site.hub.partitions[ctx.partition].snapshot if ctx.partition is not None else None
    return own or site.hub.snapshot


def build(
    ctx: HubContext,
    refused: Refusals,
    events: EventAcks,
    on_trigger: Callable[[dict[str, str]], None] | None = None,
) -> RecordingWing:
    """`on_trigger`: told of every snapshot request and alarm that may take one (the main hub
    of a partitioned site passes them on)."""
    feed = BatchFeed()
    cfg = snapshot_config(ctx)
    snapshots = None
    if cfg.enabled:
        # The buffer holds what the recorder takes (its tap) and asks whether it records: the
        # recorder is made just below, before the buffer is ever asked (only once running).
        snapshots = SnapshotBuffer(
            ctx.site,
            ctx.paths.data_dir,
            ctx.bus,
            ctx.model,
            feed,
            lambda: recorder.recording,
            cfg,
            on_trigger=on_trigger,
        )
    recorder = Recorder(
        ctx.router,
        ctx.site,
        ctx.paths.data_dir,
        ctx.bus,
        ctx.model,
        refused,
        events,
        feed,
        partition=ctx.partition,
        tap=snapshots.offer if snapshots is not None else None,
    )
    return RecordingWing(feed, recorder, snapshots)


def requests(
    ctx: HubContext,
    wing: RecordingWing,
    view: Callable[[], HubView],
    key: str | None = None,
    others: OtherHubs | None = None,
) -> RecorderRequests:
    """`key`: a partition hub's own (None: ``hub/recorder``). `others`: the partition hubs the
    main hub passes its requests on to."""
    site, buffer = ctx.site, wing.snapshots
    snapshot = None
    if buffer is not None:
        tell = not site.hub.partitions  # the partitions are asked as recorder requests instead

        def snapshot(who: str, note: str) -> tuple[bool, str]:
            assert buffer is not None
            return buffer.snapshot(who, note, tell=tell)

    own = ctx.partition is not None and site.hub.partitions[ctx.partition].snapshot is not None
    return RecorderRequests(
        ctx.router,
        ctx.keys,
        wing.recorder,
        view,
        snapshot,
        site.security,
        key=key,
        partitions=others,
        snapshot_setting=(
            f"hub.partitions.{ctx.partition}.snapshot.enabled" if own else "hub.snapshot.enabled"
        ),
    )
