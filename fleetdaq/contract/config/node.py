"""An edge machine in the site file: its spool, its clock, its streams, displays, outputs,
interlocks and control settings.

Each stream's, output's and display's schema comes from its driver's module through the driver
registry (`fleetdaq.contract.drivers`): `StreamConfig`, `OutputConfig` and `DisplayConfig` are
the unions of what is installed, picked by the config's `driver:` value.
"""

from __future__ import annotations

import functools
import operator
from typing import TYPE_CHECKING, Annotated, Literal

from pydantic import BaseModel, BeforeValidator, Field, model_validator

from fleetdaq.contract.config.node_control import ControlConfig, EdgeInterlockConfig
from fleetdaq.contract.display_text import parse_line
from fleetdaq.contract.drivers import DriverKind, driver_registry
from fleetdaq.contract.schema import (
    Endpoints,
    Float,
    Int,
    Name,
    OutputBase,
    StreamBase,
    StreamName,
    Strict,
    ros_token,
    ros_token_collision,
)


def _union(kind: DriverKind) -> object:
    """The schemas of one kind as one type: pydantic picks the schema by its `driver:` value
    (a single schema stands alone, so its own error for a wrong name is kept)."""
    schemas = [p.schema for p in driver_registry().of_kind(kind).values()]
    if not schemas:
        return Annotated[object, BeforeValidator(functools.partial(_none_installed, kind))]
    if len(schemas) == 1:
        return schemas[0]
    return Annotated[functools.reduce(operator.or_, schemas), Field(discriminator="driver")]


def _none_installed(kind: DriverKind, value: object) -> object:
    raise ValueError(
        f"no {kind} driver is installed (none registers in the fleetdaq.drivers entry points: "
        "is fleetdaq itself installed, e.g. pip install -e .?)"
    )


if TYPE_CHECKING:
    StreamConfig = StreamBase
    OutputConfig = OutputBase
    DisplayConfig = BaseModel
else:
    StreamConfig = _union(DriverKind.STREAM)
    """Any stream's config."""
    OutputConfig = _union(DriverKind.OUTPUT)
    """Any output's config."""
    DisplayConfig = _union(DriverKind.DISPLAY)
    """Any display's config."""


class SpoolConfig(Strict):
    """The edge's disk spool: batches stay on disk until the hub acks them."""

    dir: str | None = None
    """Root of the spool; each node and stream gets its own folder below it. Default: the
    per-system location of `fleetdaq.runtime.paths.default_spool_dir` (never the current
    directory)."""
    max_bytes: Annotated[Int, Field(ge=1_000_000)] = 2_000_000_000
    """Per stream, and for the node's event spool. Past it the oldest batches (events) are
    dropped (counted, raised as an event)."""
    max_age_s: Annotated[Float, Field(gt=0)] = 7 * 24 * 3600.0
    """Per stream, and for the node's event spool. Batches (events) older than this are dropped
    even if not acked (counted, event)."""
    segment_bytes: Annotated[Int, Field(ge=65536)] = 16 * 1024 * 1024
    fsync_interval_s: Annotated[Float, Field(ge=0)] = 1.0
    """How often the open segment is fsynced (a crash loses nothing; power loss up to this)."""
    replay_after_s: Annotated[Float, Field(gt=0)] = 3.0
    """Replay from the last ack when the oldest unacked batch (event) is older than this."""
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
    displays: dict[StreamName, DisplayConfig] = {}
    """Character displays on this node showing its live values (edge/display.py)."""
    outputs: dict[Name, OutputConfig] = {}
    """Analog and digital outputs commanded through the hub (edge/outputs.py)."""
    interlocks: dict[Name, EdgeInterlockConfig] = {}
    """Limits on this node's own channels that block or force its outputs safe, on the edge."""
    control: ControlConfig = ControlConfig()

    @model_validator(mode="after")
    def _streams_record_under_distinct_ros_names(self) -> NodeConfig:
        if pair := ros_token_collision(list(self.streams)):
            a, b = pair
            raise ValueError(
                f"streams.{b}: stream name {b!r} is recorded as {ros_token(b)!r}, like "
                f"streams.{a} ('-' is recorded as '_' in ROS 2 topic names); rename one"
            )
        return self

    @model_validator(mode="after")
    def _displays_show_known_channels(self) -> NodeConfig:
        for name, display in self.displays.items():
            for i, line in enumerate(getattr(display, "lines", ())):
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

    @model_validator(mode="after")
    def _interlocks_watch_this_node(self) -> NodeConfig:
        for name, lock in self.interlocks.items():
            cfg = self.streams.get(lock.stream)
            if cfg is None:
                raise ValueError(
                    f"interlocks.{name}.channel: no stream {lock.stream!r} on this node (an "
                    f"edge interlock watches this node's own channels; streams: "
                    f"{', '.join(self.streams)})"
                )
            if lock.channel_name not in [ch.name for ch in cfg.channels]:
                raise ValueError(
                    f"interlocks.{name}.channel: stream {lock.stream!r} has no channel "
                    f"{lock.channel_name!r}"
                )
            for i, out in enumerate(lock.outputs):
                if out not in self.outputs:
                    known = ", ".join(self.outputs) or "none"
                    raise ValueError(
                        f"interlocks.{name}.outputs[{i}]: no output {out!r} on this node "
                        f"(outputs: {known})"
                    )
        return self

    @model_validator(mode="after")
    def _one_output_per_pin(self) -> NodeConfig:
        seen: dict[str, str] = {}
        for name, out in self.outputs.items():
            what = out.resource
            if what in seen:
                raise ValueError(f"outputs.{name}: drives {what}, like outputs.{seen[what]}")
            seen[what] = name
        return self

    @model_validator(mode="after")
    def _weld_cells_exist(self) -> NodeConfig:
        robots: dict[str, str] = {}
        for name, cfg in self.streams.items():
            cell = getattr(cfg, "cell", None)
            if cfg.driver == "weld_robot_sim" and isinstance(cell, str):
                if cell in robots:
                    raise ValueError(
                        f"streams.{name}.cell: cell {cell!r} already has its robot in "
                        f"streams.{robots[cell]}"
                    )
                robots[cell] = name
        named = [
            (f"streams.{n}.sim.cell", getattr(getattr(c, "sim", None), "cell", None))
            for n, c in self.streams.items()
        ] + [(f"outputs.{n}.cell", getattr(o, "cell", None)) for n, o in self.outputs.items()]
        for where, cell in named:
            if isinstance(cell, str) and cell not in robots:
                known = ", ".join(robots) or "none"
                raise ValueError(
                    f"{where}: no weld_robot_sim stream with cell {cell!r} on this node "
                    f"(cells: {known})"
                )
        return self

    @model_validator(mode="after")
    def _one_t8_is_real_or_simulated(self) -> NodeConfig:
        kinds: dict[str, tuple[str, bool]] = {}
        items: list[tuple[str, StreamBase | OutputBase]] = [
            (f"streams.{n}", c) for n, c in self.streams.items()
        ]
        items += [(f"outputs.{n}", o) for n, o in self.outputs.items()]
        for where, cfg in items:
            if not cfg.driver.startswith("labjack_t8"):
                continue
            ident = str(getattr(cfg, "identifier", "ANY"))
            simulated = getattr(cfg, "sim", None) is not None
            first = kinds.setdefault(ident, (where, simulated))
            if first[1] != simulated:
                which = "simulated" if first[1] else "real"
                raise ValueError(
                    f"{where}: the T8 {ident!r} is {which} in {first[0]}: one device is either "
                    f"simulated (sim:) everywhere or nowhere"
                )
        return self
