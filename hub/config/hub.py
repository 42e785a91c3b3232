"""The site file's `hub:` section as the hub validates it: `HubConfig` narrows the contract's
`HubBase` (router endpoints, partitions, data folders, universal alarms: what every machine
reads) with what only the hub uses: the recorder, notifications (`fleetdaq.hub.config.notify`),
cross-node interlocks (`fleetdaq.hub.config.control`), the snapshot buffer and the dashboard
(`fleetdaq.hub.config.dashboard`)."""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import Field, model_validator

from fleetdaq.contract.config.hubs import HubBase, PartitionBase
from fleetdaq.contract.config.universal_alarms import Severity
from fleetdaq.contract.schema import Float, Int, Name, Strict
from fleetdaq.hub.config.control import InterlockConfig, RuleName
from fleetdaq.hub.config.dashboard import DashboardConfig
from fleetdaq.hub.config.notify import NotifyConfig


class RecorderConfig(Strict):
    """What the hub records and how files are split (MODAQ 2: fileDuration, loggedTopics)."""

    file_duration_s: Annotated[Float, Field(gt=0)] | None = 60.0
    max_file_bytes: Annotated[Int, Field(ge=1_000_000)] | None = None
    flush_interval_s: Annotated[Float, Field(gt=0, le=60)] = 1.0
    """Close the MCAP chunk in progress and fsync at least this often; acks follow flushes."""
    recover_on_start: bool = True
    """At start, turn ``*.mcap.active`` files left by a crash into valid ``*.mcap`` files."""
    include: Annotated[list[str], Field(min_length=1)] = ["*"]
    """Patterns on ``node/stream`` (fnmatch); a stream is recorded when any include matches..."""
    exclude: list[str] = []
    """...and no exclude does."""
    compression: Literal["zstd", "lz4", "none"] = "zstd"
    chunk_size: Annotated[Int, Field(ge=4096, le=64 * 1024 * 1024)] = 1024 * 1024

    @model_validator(mode="after")
    def _some_split(self) -> RecorderConfig:
        if self.file_duration_s is None and self.max_file_bytes is None:
            raise ValueError("set file_duration_s and/or max_file_bytes, or files never split")
        return self


class SnapshotConfig(Strict):
    """The snapshot buffer (rosbag2's snapshot mode): the last `seconds` of every stream, the
    events and the health, in bounded memory, written to ``<data_dir>/snapshots/`` on request
    (`fleetdaq rec snapshot`, the dashboard, a rule's ``record: snapshot``) or when an alarm of
    one of the `on_alarm` severities is raised while the recorder is stopped: the minute before
    an event is kept even when nobody was recording."""

    enabled: bool = True
    seconds: Annotated[Float, Field(gt=0, le=3600)] = 60.0
    max_bytes: Annotated[Int, Field(ge=1 << 20, le=64 << 30)] = 512 << 20
    """Memory bound: the oldest messages go first when the buffer holds more than this."""
    on_alarm: list[Severity] = ["critical", "major"]
    min_interval_s: Annotated[Float, Field(ge=0, le=86400)] = 30.0
    """Alarm-triggered snapshots closer together than this are one (requests are never
    merged)."""


class PartitionConfig(PartitionBase):
    """A partition hub (`fleetdaq hub --partition NAME`), with its own snapshot bounds."""

    snapshot: SnapshotConfig | None = None
    """This hub's snapshot buffer, when its machine needs other bounds than the main hub's
    (default: ``hub.snapshot``). Off here, a snapshot asked of the site is not asked of this hub
    (the reply says it keeps none; not a failure)."""


class HubConfig(HubBase):
    """The `hub:` section with the hub's own settings validated in full."""

    partitions: dict[Name, PartitionConfig] = {}
    """More hubs, each recording a slice of the nodes (`PartitionConfig`); nodes no partition
    names are the main hub's. Empty: one hub records everything."""
    recorder: RecorderConfig = RecorderConfig()
    notify: NotifyConfig = NotifyConfig()
    interlocks: dict[RuleName, InterlockConfig] = {}
    """Cross-node interlocks, evaluated on the hub (`fleetdaq.hub.config.control`)."""
    snapshot: SnapshotConfig = SnapshotConfig()
    dashboard: DashboardConfig = DashboardConfig()
    """The dashboard, /metrics and the Foxglove live view (`fleetdaq.hub.config.dashboard`)."""
