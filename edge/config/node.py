"""An edge machine in the site file: its spool, its clock, its streams and displays.

Each stream's schema comes from its driver's module through `edge.drivers.table`.
"""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import Field, model_validator

from edge.display_text import parse_line
from edge.drivers.hd44780 import LcdDisplay
from edge.drivers.table import StreamConfig
from edge.schema import Endpoints, Float, Int, StreamName, Strict


class SpoolConfig(Strict):
    """The edge's disk spool: batches stay on disk until the hub acks them."""

    dir: str | None = None
    """Root of the spool; each node and stream gets its own folder below it. Default: the
    per-system location of `edge.paths.default_spool_dir` (never the current directory)."""
    max_bytes: Annotated[Int, Field(ge=1_000_000)] = 2_000_000_000
    """Per stream. Past it the oldest batches are dropped (counted, raised as an event)."""
    max_age_s: Annotated[Float, Field(gt=0)] = 7 * 24 * 3600.0
    """Per stream. Batches older than this are dropped even if not acked (counted, event)."""
    segment_bytes: Annotated[Int, Field(ge=65536)] = 16 * 1024 * 1024
    fsync_interval_s: Annotated[Float, Field(ge=0)] = 1.0
    """How often the open segment is fsynced (a crash loses nothing; power loss up to this)."""
    replay_after_s: Annotated[Float, Field(gt=0)] = 3.0
    """Replay from the last ack when the oldest unacked batch is older than this."""
    replay_mb_per_s: Annotated[Float, Field(gt=0)] = 40.0
    """Replay rate limit, so live data keeps flowing while a backlog drains."""


class ClockConfig(Strict):
    """Where the node's time quality comes from, and the thresholds it is graded with.

    Offsets are integer ns; unset offset limits default by `timestamping` (software: warn
    250 µs / fail 1 ms, as Meta's ptpcheck; hardware: 10 µs / 100 µs)."""

    source: Literal["ptp4l", "chrony", "none"] = "none"
    uds: str = "/var/run/ptp4l"
    """ptp4l's management socket (its `uds_address`)."""
    domain: Annotated[Int, Field(ge=0, le=255)] = 0
    interface: str | None = None
    """The PTP interface; default: the one ptp4l reports for its first port."""
    timestamping: Literal["software", "hardware"] = "software"
    offset_warn_ns: Annotated[Int, Field(gt=0)] | None = None
    offset_fail_ns: Annotated[Int, Field(gt=0)] | None = None
    last_sync_warn_s: Annotated[Float, Field(gt=0)] = 1.0
    last_sync_fail_s: Annotated[Float, Field(gt=0)] = 5.0
    holdover_s: Annotated[Float, Field(ge=0)] = 5.0
    """After losing lock, HOLDOVER this long after the last sync, then FREERUN."""
    poll_s: Annotated[Float, Field(ge=0.1, le=10)] = 0.5
    ignore_checks: list[str] = []
    """Checks reported but left out of the level (e.g. kernel_sync where nothing may set it)."""

    @model_validator(mode="after")
    def _warn_below_fail(self) -> ClockConfig:
        warn, fail = self.offset_warn_ns, self.offset_fail_ns
        if warn is not None and fail is not None and warn > fail:
            raise ValueError(f"offset_warn_ns ({warn}) is above offset_fail_ns ({fail})")
        if self.last_sync_warn_s > self.last_sync_fail_s:
            raise ValueError(
                f"last_sync_warn_s ({self.last_sync_warn_s:g}) is above "
                f"last_sync_fail_s ({self.last_sync_fail_s:g})"
            )
        return self


class NodeConfig(Strict):
    """One edge machine."""

    connect: Endpoints | None = None
    """Zenoh endpoints of the hub's router; default: the hub's listen endpoints."""
    spool: SpoolConfig = SpoolConfig()
    clock: ClockConfig = ClockConfig()
    streams: Annotated[dict[StreamName, StreamConfig], Field(min_length=1)]
    displays: dict[StreamName, LcdDisplay] = {}
    """Character displays on this node showing its live values (edge/display.py)."""

    @model_validator(mode="after")
    def _displays_show_known_channels(self) -> NodeConfig:
        for name, display in self.displays.items():
            for i, line in enumerate(display.lines):
                for stream, channel in parse_line(line).references:
                    cfg = self.streams.get(stream)
                    if cfg is None:
                        raise ValueError(
                            f"displays.{name}.lines[{i}]: no stream {stream!r} on this node"
                            f" (streams: {', '.join(self.streams)})"
                        )
                    if channel not in [ch.name for ch in cfg.channels]:
                        raise ValueError(
                            f"displays.{name}.lines[{i}]: stream {stream!r} has no channel"
                            f" {channel!r}"
                        )
        return self
