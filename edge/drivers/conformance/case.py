"""What the conformance checks run on: the driver looked up by name (`find_driver`), the case
describing it (`DriverCase`), one driver made from a config with bounded calls (`DriverRun`),
and the Block contract every read must keep (`check_block`)."""

from __future__ import annotations

import contextlib
import re
import threading
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Literal, Protocol, TypeVar

import numpy as np
from pydantic import BaseModel, ValidationError

from fleetdaq.contract.schema import StreamBase
from fleetdaq.edge.drivers.base import Block, Driver, DriverEvent
from fleetdaq.edge.drivers.pacing import SYSTEM_TIME, TimeSource, VirtualTime
from fleetdaq.edge.drivers.shared import SharedDevices

T = TypeVar("T")

ENTRY_POINT_GROUP = "fleetdaq.drivers"


class NotConforming(AssertionError):
    """A driver does not do what the contract says: the message says what and where."""


def expect(ok: bool, message: str) -> None:
    """Raise NotConforming(`message`) unless `ok` (a check that `python -O` keeps)."""
    if not ok:
        raise NotConforming(message)


class Factory(Protocol):
    def __call__(self, cfg: StreamBase, clock: TimeSource, shared: SharedDevices) -> Driver: ...


@dataclass(frozen=True, slots=True)
class FoundDriver:
    """A stream driver as the suite builds it: its config schema and how to create it."""

    name: str
    schema: type[StreamBase]
    create: Factory
    """``create(cfg, clock, shared)``: the driver, on its simulated transport when `cfg` has
    `sim:` (the contract of `fleetdaq.edge.drivers.table.create_driver`)."""


def lookup(name: str, kind: Literal["stream", "output"]) -> tuple[Any, Callable[..., Any]]:
    """The schema and the factory (``create(cfg, clock, shared)``) of the `kind` driver that a
    config's `driver: name` selects, from the driver registry (`fleetdaq.contract.drivers`:
    the `fleetdaq.drivers` entry points, built-in drivers and a driver package's alike).

    Raises:
        NotConforming: no such driver, or the registry refused it (the reason).
    """
    from fleetdaq.contract.drivers import DriverKind, driver_registry
    from fleetdaq.contract.errors import DriverError
    from fleetdaq.edge.drivers import table

    try:
        plugin = driver_registry().plugin(
            name, DriverKind.STREAM if kind == "stream" else DriverKind.OUTPUT
        )
    except DriverError as err:
        raise NotConforming(f"{kind} driver {name!r}: {err}") from err
    return plugin.schema, table.create_driver if kind == "stream" else table.create_output


def find_driver(name: str) -> FoundDriver:
    """The stream driver a config's `driver: name` selects (see `lookup`)."""
    schema, create = lookup(name, "stream")
    return FoundDriver(name, schema, create)


@dataclass(frozen=True)
class DriverCase:
    """A driver as the suite runs it.

    Fault entries go into the config's `sim.faults` list; each needs `at_s` and `for_s`
    (seconds after the device opened), so the checks see the fault start and end.
    """

    config: Mapping[str, Any]
    """A valid stream config, as a site file's mapping under `streams:`, `driver:` included;
    with a `sim:` block when the driver reaches hardware through a transport."""
    faults: Sequence[Mapping[str, Any]] = ()
    """Faults that make readings bad for a while (an open thermocouple, a CRC error, a skipped
    scan, a stream error): flagged samples or a typed DeviceError, then good data again."""
    unplug: Mapping[str, Any] | None = None
    """A fault that unplugs the device for a while: DeviceDisconnected, the device not found
    until it is back, then reopening works (or, for a polled chip that cannot tell an unplug
    from a silent bus, every sample flagged until it answers again)."""
    bad_configs: Sequence[tuple[Mapping[str, Any], str]] = ()
    """(keys to change in `config`, the key path the error must name), beyond the suite's own
    (a zero rate, no channels, duplicate channel names, an unknown key)."""
    virtual_time: bool = True
    """The driver and its simulator run on the clock they are given (a `VirtualTime` here);
    False for sims paced by the host's real clock (then short blocks keep the checks short)."""
    reads: int = 40
    """Blocks to read in the rate and time-fit checks."""
    drift_ppm: float | None = None
    """The device clock's drift the simulator is set to (positive: fast), if the time fit must
    find it, within `drift_tolerance_ppm`."""
    drift_tolerance_ppm: float = 5.0
    read_timeout_s: float = 10.0
    """Longest any one call on the driver may take (host seconds), on top of a real-time
    block's own duration."""

    @property
    def driver(self) -> str:
        return str(self.config["driver"])

    def with_changes(self, changes: Mapping[str, Any]) -> dict[str, Any]:
        return with_changes(self.config, changes)

    def with_fault(self, fault: Mapping[str, Any]) -> dict[str, Any]:
        return with_fault(self.config, fault)


def with_changes(config: Mapping[str, Any], changes: Mapping[str, Any]) -> dict[str, Any]:
    """`config` with top-level keys replaced (a value of None removes the key)."""
    out = {**config, **changes}
    return {k: v for k, v in out.items() if v is not None}


def with_fault(config: Mapping[str, Any], fault: Mapping[str, Any]) -> dict[str, Any]:
    """`config` with `fault` as its simulator's only fault."""
    sim = dict(config.get("sim") or {})
    sim["faults"] = [dict(fault)]
    return with_changes(config, {"sim": sim})


def check_refused(schema: type[BaseModel], config: Mapping[str, Any], path: str, name: str) -> None:
    """`schema` refuses `config` with an error naming the key path `path`: at that location, or
    from a check of a mapping that holds it whose message names its key (the site loader puts
    such an error at that key)."""
    try:
        schema.model_validate(dict(config))
    except ValidationError as err:
        key = re.compile(rf"\b{re.escape(path.rsplit('.', 1)[-1])}\b")
        locs = []
        for e in err.errors():
            loc = ".".join(str(p) for p in e["loc"])
            locs.append(loc)
            if loc == path or loc.startswith(path + "."):
                return
            if (not loc or path.startswith(loc + ".")) and key.search(e["msg"]):
                return
        raise NotConforming(f"{name}: {dict(config)} refused at {locs}, not at {path!r}") from err
    raise NotConforming(f"{name}: {dict(config)} was accepted")


class DriverRun:
    """One driver made from a case's config (or another), on a `VirtualTime` or the host's
    clock as the case says, with every call bounded; a context manager that closes it."""

    def __init__(
        self, case: DriverCase, found: FoundDriver, config: Mapping[str, Any] | None = None
    ) -> None:
        self.case = case
        self.cfg = found.schema.model_validate(dict(config or case.config))
        self.clock: TimeSource = VirtualTime() if case.virtual_time else SYSTEM_TIME
        self.driver = found.create(self.cfg, self.clock, SharedDevices())
        self.block_s = self.cfg.batch_scans / self.cfg.rate_hz
        self.timeout_s = case.read_timeout_s + (0 if case.virtual_time else 3 * self.block_s)
        self.opened_ns = 0

    def __enter__(self) -> DriverRun:
        return self

    def __exit__(self, kind: type[BaseException] | None, *exc: object) -> None:
        if kind is None:
            self.call("close()", self.driver.close)
            return
        with contextlib.suppress(Exception):  # the failure in flight says more
            self.call("close()", self.driver.close)

    def since_open_s(self) -> float:
        """Seconds on the driver's clock since `open()`."""
        return (self.clock.monotonic_ns() - self.opened_ns) / 1e9

    def advance(self, seconds: float) -> None:
        """Let device time pass without reading (virtual time only)."""
        if isinstance(self.clock, VirtualTime):
            self.clock.advance(round(seconds * 1e9))

    def call(self, what: str, fn: Callable[[], T]) -> T:
        """`fn()`, bounded (`call_within`); closing the driver ends a call that hangs."""
        return call_within(self.timeout_s, f"{self.case.driver}: {what}", fn, self.driver.close)

    def open(self) -> None:
        self.opened_ns = self.clock.monotonic_ns()
        self.call("open()", self.driver.open)

    def read(self) -> Block:
        """One block, checked against the Block contract (`check_block`)."""
        block = self.call("read()", self.driver.read)
        check_block(block, self.cfg)
        return block


def call_within(seconds: float, what: str, fn: Callable[[], T], stop: Callable[[], None]) -> T:
    """`fn()` in a worker thread: its result, or its exception raised here. If it does not
    return within `seconds`: `stop()` (which must end it: a driver's close), then NotConforming.
    """
    result: list[T] = []
    error: list[BaseException] = []

    def run() -> None:
        try:
            result.append(fn())
        except BaseException as err:
            error.append(err)

    worker = threading.Thread(target=run, name=f"conformance {what}", daemon=True)
    worker.start()
    worker.join(seconds)
    if worker.is_alive():
        if fn != stop:  # a hanging close() is not closed again
            stop()
            worker.join(seconds)
        raise NotConforming(f"{what} did not return in {seconds:g} s")
    if error:
        raise error[0]
    return result[0]


def check_block(block: Block, cfg: StreamBase) -> None:
    """One block keeps the Block contract for its config: (scans, channels) float64, at most a
    batch of scans, a uint8 status of the same shape or None, int ns times, typed events; and
    no made-up values: every sample marked valid is a finite number."""
    name = cfg.driver
    expect(isinstance(block, Block), f"{name}: read() returned a {type(block).__name__}")
    raw = block.raw
    expect(
        isinstance(raw, np.ndarray) and raw.dtype == np.float64 and raw.ndim == 2,
        f"{name}: raw must be a 2-D float64 array, got {type(raw).__name__} "
        f"{getattr(raw, 'dtype', '')} {getattr(raw, 'shape', '')}",
    )
    expect(
        raw.shape[1] == len(cfg.channels),
        f"{name}: {raw.shape[1]} columns for {len(cfg.channels)} configured channels",
    )
    expect(
        1 <= raw.shape[0] <= cfg.batch_scans,
        f"{name}: {raw.shape[0]} scans in a block of at most {cfg.batch_scans}",
    )
    status = block.status
    if status is not None:
        expect(
            status.dtype == np.uint8 and status.shape == raw.shape,
            f"{name}: status must be uint8 {raw.shape}, got {status.dtype} {status.shape}",
        )
    valid = raw if status is None else raw[status == 0]
    expect(bool(np.isfinite(valid).all()), f"{name}: a sample marked valid is not a number")
    expect(type(block.host_ns) is int, f"{name}: host_ns must be int ns")
    expect(
        block.device_ns is None or type(block.device_ns) is int,
        f"{name}: device_ns must be int ns or None",
    )
    expect(
        type(block.late_polls) is int and block.late_polls >= 0,
        f"{name}: late_polls must be an int >= 0",
    )
    expect(
        isinstance(block.events, tuple) and all(isinstance(e, DriverEvent) for e in block.events),
        f"{name}: events must be a tuple of DriverEvent",
    )


def all_valid(block: Block) -> bool:
    """Every sample of the block is valid."""
    return block.status is None or not block.status.any()
