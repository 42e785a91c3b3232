"""The driver conformance suite: what every stream driver with a simulator must do, checked.

Like python-can's back-to-back tests, the suite ships in the package, so a driver that lives in
another distribution runs the same checks as the built-in ones. A driver is described once as
a `DriverCase` (a valid config with a `sim:` block, the faults its simulator can inject, configs
its schema must refuse); each `check_*` function builds the driver from the case, runs it on
its simulator and raises AssertionError saying what is wrong. The checks need no test
framework; `DriverConformance` is the pytest-friendly form: a class whose `test_*` methods a
driver package's tests inherit by naming their case.

Drivers whose simulated transport runs on the clock it is given run on a `VirtualTime` here, so
reads return at once and a fault window of seconds costs nothing; sims paced by the host's own
clock (`PacedSim`) run in real time with short batches. Every call on a driver is bounded: a
call that does not return in time closes the driver and fails the check.
"""

from __future__ import annotations

import contextlib
import json
import math
import threading
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from importlib.metadata import entry_points
from typing import Any, ClassVar, Protocol, TypeVar

import numpy as np
from pydantic import ValidationError

from fleetdaq.contract.errors import DeviceDisconnected, DeviceError
from fleetdaq.contract.schema import StreamBase
from fleetdaq.edge.device_time import DeviceTimeFit
from fleetdaq.edge.drivers.base import Block, Driver, DriverEvent, DriverHealth
from fleetdaq.edge.drivers.pacing import SYSTEM_TIME, TimeSource, VirtualTime
from fleetdaq.edge.drivers.shared import SharedDevices

T = TypeVar("T")

ENTRY_POINT_GROUP = "fleetdaq.drivers"


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


def find_driver(name: str) -> FoundDriver:
    """The stream driver a config's `driver: name` selects: a `fleetdaq.drivers` entry point of
    that name (a driver package's plugin object: `kind`, `schema`, `driver`, `sim`, `shared`,
    as a row of the driver table), else the built-in driver table.

    The one place the suite looks a driver up: with a registry of entry points for every
    driver, built-in ones included, this becomes that registry's lookup.
    """
    from fleetdaq.edge.drivers.table import DRIVERS, create_driver, load_sim

    for ep in entry_points(group=ENTRY_POINT_GROUP, name=name):
        plugin = ep.load()
        if plugin.kind != "stream":
            raise AssertionError(f"{ep.value}: a {plugin.kind!r} driver, not a stream driver")

        def create(cfg: StreamBase, clock: TimeSource, shared: SharedDevices) -> Driver:
            if plugin.sim is not None and getattr(cfg, "sim", None) is not None:
                transport = load_sim(plugin.sim)(cfg, clock, shared)
                made: Driver = plugin.driver(cfg, transport=transport, clock=clock)
            elif plugin.shared:
                made = plugin.driver(cfg, clock=clock, shared=shared)
            else:
                made = plugin.driver(cfg)
            return made

        return FoundDriver(name, plugin.schema, create)
    spec = DRIVERS.get(name)
    if spec is None:
        raise AssertionError(f"no driver {name!r}: no {ENTRY_POINT_GROUP} entry point, not built in")
    return FoundDriver(name, spec.schema, create_driver)


@dataclass(frozen=True)
class DriverCase:
    """A driver as the suite runs it.

    Fault entries go into the config's `sim.faults` list; each needs `at_s` and `for_s`
    (seconds after the device opened), so the check sees the fault start and end.
    """

    config: Mapping[str, Any]
    """A valid stream config, as a site file's mapping under `streams:`, `driver:` included;
    with a `sim:` block when the driver reaches hardware through a transport."""
    faults: Sequence[Mapping[str, Any]] = ()
    """Faults that make readings bad for a while (an open thermocouple, a CRC error, a skipped
    scan, a stream error): flagged samples or a typed DeviceError, then good data again."""
    unplug: Mapping[str, Any] | None = None
    """A fault that unplugs the device for a while: DeviceDisconnected, the device not found
    until it is back, then reopening works (or, for a polled chip, every sample flagged until
    it answers again)."""
    bad_configs: Sequence[tuple[Mapping[str, Any], str]] = ()
    """(keys to change in `config`, the key path the error must name), beyond the suite's own
    (a zero rate, no channels, duplicate channel names, an unknown key)."""
    virtual_time: bool = True
    """The driver and its simulator run on the clock they are given (a `VirtualTime` here);
    False for sims paced by the host's real clock."""
    reads: int = 40
    """Blocks to read in the rate and time-fit checks."""
    drift_ppm: float | None = None
    """The device clock's drift the simulator is set to (positive: fast), if the time fit must
    find it; within `drift_tolerance_ppm`."""
    drift_tolerance_ppm: float = 5.0
    read_timeout_s: float = 10.0
    """Longest any one call on the driver may take (host seconds), on top of a real-time
    block's own duration."""

    @property
    def driver(self) -> str:
        return str(self.config["driver"])

    def with_changes(self, changes: Mapping[str, Any]) -> dict[str, Any]:
        """The config with top-level keys replaced (a value of None removes the key)."""
        out = {**self.config, **changes}
        return {k: v for k, v in out.items() if v is not None}

    def with_fault(self, fault: Mapping[str, Any]) -> dict[str, Any]:
        """The config with `fault` as its simulator's only fault."""
        sim = dict(self.config.get("sim") or {})
        sim["faults"] = [dict(fault)]
        return self.with_changes({"sim": sim})


# --- one driver, bounded --------------------------------------------------------------------


class _Run:
    """One driver made from a config, its clock, and bounded calls on it; closes on exit."""

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

    def __enter__(self) -> _Run:
        return self

    def __exit__(self, kind: type[BaseException] | None, *exc: object) -> None:
        if kind is None:
            self.call("close()", self.driver.close)
            return
        with contextlib.suppress(Exception):  # the failure in flight says more
            self.call("close()", self.driver.close)

    def since_open_s(self) -> float:
        return (self.clock.monotonic_ns() - self.opened_ns) / 1e9

    def advance(self, seconds: float) -> None:
        """Let device time pass without reading (virtual time only)."""
        assert isinstance(self.clock, VirtualTime), "advancing needs virtual time"
        self.clock.advance(round(seconds * 1e9))

    def call(self, what: str, fn: Callable[[], T]) -> T:
        """`fn()` in a worker thread, its result or its exception; AssertionError (after closing
        the driver, which must end any blocking call) if it does not return in time."""
        result: list[T] = []
        error: list[BaseException] = []

        def run() -> None:
            try:
                result.append(fn())
            except BaseException as err:
                error.append(err)

        worker = threading.Thread(target=run, name=f"conformance {what}", daemon=True)
        worker.start()
        worker.join(self.timeout_s)
        if worker.is_alive():
            if what != "close()":
                self.driver.close()
                worker.join(self.timeout_s)
            raise AssertionError(f"{self.case.driver}: {what} did not return in {self.timeout_s} s")
        if error:
            raise error[0]
        return result[0]

    def open(self) -> None:
        self.opened_ns = self.clock.monotonic_ns()
        self.call("open()", self.driver.open)

    def read(self) -> Block:
        block = self.call("read()", self.driver.read)
        check_block(block, self.cfg)
        return block


def check_block(block: Block, cfg: StreamBase) -> None:
    """One block keeps the Block contract for its config: (scans, channels) float64, at most a
    batch of scans, a uint8 status of the same shape or None, int ns times, typed events; and
    no made-up values: every sample marked valid is a finite number."""
    raw, name = block.raw, cfg.driver
    assert isinstance(block, Block), f"{name}: read() returned a {type(block).__name__}"
    assert isinstance(raw, np.ndarray) and raw.dtype == np.float64 and raw.ndim == 2, (
        f"{name}: raw must be a 2-D float64 array, got {type(raw).__name__} "
        f"{getattr(raw, 'dtype', '')} {getattr(raw, 'shape', '')}"
    )
    assert raw.shape[1] == len(cfg.channels), (
        f"{name}: {raw.shape[1]} columns for {len(cfg.channels)} configured channels"
    )
    assert 1 <= raw.shape[0] <= cfg.batch_scans, (
        f"{name}: {raw.shape[0]} scans in a block of at most {cfg.batch_scans}"
    )
    status = block.status
    if status is not None:
        assert status.dtype == np.uint8 and status.shape == raw.shape, (
            f"{name}: status must be uint8 {raw.shape}, got {status.dtype} {status.shape}"
        )
    valid = raw if status is None else raw[status == 0]
    assert np.isfinite(valid).all(), f"{name}: a sample marked valid is not a finite number"
    assert type(block.host_ns) is int, f"{name}: host_ns must be int ns"
    assert block.device_ns is None or type(block.device_ns) is int, (
        f"{name}: device_ns must be int ns or None"
    )
    assert type(block.late_polls) is int and block.late_polls >= 0, f"{name}: late_polls"
    assert isinstance(block.events, tuple) and all(
        isinstance(e, DriverEvent) for e in block.events
    ), f"{name}: events must be a tuple of DriverEvent"


def _all_valid(block: Block) -> bool:
    return block.status is None or not block.status.any()


# --- the checks -----------------------------------------------------------------------------


def check_open_and_describe(case: DriverCase, found: FoundDriver | None = None) -> None:
    """The config validates into the driver's schema with the channels, units and rate it was
    given; the driver opens; its blocks have one column per channel; its health (if it has
    one) is a JSON-able mapping."""
    found = found or find_driver(case.driver)
    with _Run(case, found) as run:
        cfg, raw = run.cfg, case.config
        assert cfg.driver == found.name, f"schema gave driver {cfg.driver!r}"
        got = [(ch.name, ch.unit) for ch in cfg.channels]
        want = [(ch["name"], ch.get("unit", "")) for ch in raw["channels"]]
        assert got == want, f"{found.name}: channels {got}, configured {want}"
        assert math.isclose(cfg.rate_hz, float(raw["rate_hz"])), f"rate {cfg.rate_hz}"
        assert len(cfg.resolutions()) == len(cfg.channels), "one resolution per channel"
        run.open()
        run.read()
        if isinstance(run.driver, DriverHealth):
            health = run.call("health()", run.driver.health)
            assert isinstance(health, dict) and all(isinstance(k, str) for k in health)
            json.dumps(health)


def check_reads_at_rate(case: DriverCase, found: FoundDriver | None = None) -> None:
    """Reads block until their scans exist: over `case.reads` blocks the scans (and the polls
    the host was late for) span the time they should at the configured rate, on the device
    clock when blocks carry one and on the clock the driver was given; times only increase."""
    found = found or find_driver(case.driver)
    with _Run(case, found) as run:
        run.open()
        start = run.clock.monotonic_ns()
        blocks = [run.read() for _ in range(case.reads)]
        elapsed_s = (run.clock.monotonic_ns() - start) / 1e9
    name, rate = found.name, run.cfg.rate_hz
    hosts = [b.host_ns for b in blocks]
    assert all(b > a for a, b in zip(hosts, hosts[1:], strict=False)), f"{name}: host_ns goes back"
    devices = [b.device_ns for b in blocks]
    has_clock = {d is not None for d in devices}
    assert len(has_clock) == 1, f"{name}: device_ns is set in some blocks only"
    # Scans after the first block's last one: the time the later blocks span.
    spanned = sum(b.raw.shape[0] + b.late_polls for b in blocks[1:]) / rate
    total = sum(b.raw.shape[0] + b.late_polls for b in blocks) / rate
    if has_clock == {True}:
        dev = [d for d in devices if d is not None]
        assert all(b > a for a, b in zip(dev, dev[1:], strict=False)), f"{name}: device_ns back"
        measured = (dev[-1] - dev[0]) / 1e9
        assert math.isclose(measured, spanned, rel_tol=0.01), (
            f"{name}: the device clock spans {measured:.6f} s over scans worth {spanned:.6f} s"
        )
    if case.virtual_time:
        host_s = (hosts[-1] - hosts[0]) / 1e9
        assert math.isclose(host_s, spanned, rel_tol=0.02, abs_tol=0.5 / rate), (
            f"{name}: reads returned {host_s:.6f} s apart for scans worth {spanned:.6f} s"
        )
        assert elapsed_s >= 0.98 * total - 1.0 / rate, (
            f"{name}: {total:.3f} s of scans read in {elapsed_s:.3f} s: reads did not wait"
        )
    else:
        # Real time on a shared host: never faster than the device, later only by scheduling.
        assert elapsed_s >= 0.9 * spanned, (
            f"{name}: {total:.3f} s of scans read in {elapsed_s:.3f} s: reads did not block"
        )
        assert elapsed_s <= 1.5 * total + 0.5, f"{name}: {total:.3f} s took {elapsed_s:.3f} s"


def check_time_fit(case: DriverCase, found: FoundDriver | None = None) -> None:
    """The agent's device-time fit (`fleetdaq.edge.device_time`), fed as the stream loop feeds
    it, holds on the driver's clock: no restart, batches in order and contiguous, never stamped
    after the read that returned them, the fitted period within 1 % of nominal (and the drift
    the simulator is set to, when the case names it)."""
    found = found or find_driver(case.driver)
    with _Run(case, found) as run:
        fit = DeviceTimeFit(run.cfg.rate_hz)
        run.open()
        index, prev_end, name = 0, None, found.name
        for k in range(case.reads):
            block = run.read()
            scans = block.raw.shape[0]
            index += block.late_polls
            fit.observe(index + scans - 1, block.host_ns, block.device_ns)
            t0, period = fit.stamp(index, scans)
            last = t0 + round(period * (scans - 1))
            assert last <= block.host_ns, (
                f"{name}: block {k} stamped {(last - block.host_ns) / 1e6:.3f} ms after its read"
            )
            if prev_end is not None and not block.late_polls:
                gap_ms = (t0 - prev_end) / 1e6
                assert abs(gap_ms) <= max(2.0, 1e3 * run.block_s * 0.05), (
                    f"{name}: block {k} starts {gap_ms:.3f} ms from where block {k - 1} ended"
                )
            prev_end = t0 + round(period * scans)
            index += scans
    nominal = 1e9 / run.cfg.rate_hz
    assert fit.restarts == 0, f"{name}: the time fit restarted {fit.restarts} time(s)"
    assert math.isclose(fit.period_ns, nominal, rel_tol=0.01), (
        f"{name}: fitted period {fit.period_ns:.1f} ns, nominal {nominal:.1f} ns"
    )
    if case.drift_ppm is not None:
        assert abs(fit.drift_ppm - case.drift_ppm) <= case.drift_tolerance_ppm, (
            f"{name}: fitted drift {fit.drift_ppm:.2f} ppm, simulated {case.drift_ppm:g} ppm"
        )


def _window(fault: Mapping[str, Any]) -> tuple[float, float]:
    at_s, for_s = float(fault.get("at_s", 0.0)), fault.get("for_s")
    assert for_s is not None, f"fault {dict(fault)}: the suite needs its for_s (when it ends)"
    return at_s, at_s + float(for_s)


def _reopen(run: _Run, until_s: float, what: str) -> None:
    """Close, then open again until it works (a typed DeviceError meanwhile), device time
    moving on, at most until `until_s` after the first open."""
    run.call("close()", run.driver.close)
    step = max(run.block_s, 0.05)
    while True:
        try:
            run.call("open()", run.driver.open)
            return
        except DeviceError as err:
            if run.since_open_s() > until_s:
                raise AssertionError(f"{run.case.driver}: {what}: reopening fails: {err}") from err
        run.advance(step)


def check_fault(case: DriverCase, fault: Mapping[str, Any], found: FoundDriver | None = None) -> None:
    """An injected fault shows as flagged samples (a SampleStatus, never a made-up value) or a
    typed DeviceError, never another exception; nothing is flagged before it starts; after it
    ends (and a reopen, if it raised) the samples are valid again."""
    found = found or find_driver(case.driver)
    assert case.virtual_time, f"{found.name}: faults are injected in virtual time only"
    at_s, end_s = _window(fault)
    kind = fault.get("kind", "?")
    with _Run(case, found, case.with_fault(fault)) as run:
        margin_s = 3 * run.block_s + 0.5
        run.open()
        flagged = raised = 0
        reads = 0
        limit = 10 * math.ceil((end_s + margin_s) / run.block_s) + 100
        while run.since_open_s() < end_s + margin_s:
            reads += 1
            assert reads < limit, f"{found.name}: {limit} reads without reaching {end_s} s"
            try:
                block = run.read()
            except DeviceError as err:
                assert run.since_open_s() >= at_s, f"{found.name}: {err} before the fault"
                raised += 1
                _reopen(run, end_s + margin_s, f"after {kind}")
                continue
            except AssertionError:
                raise
            except Exception as err:
                raise AssertionError(
                    f"{found.name}: fault {kind} crashed a read: {type(err).__name__}: {err}"
                ) from err
            if not _all_valid(block):
                assert run.since_open_s() >= at_s, f"{found.name}: samples flagged before {kind}"
                flagged += 1
        assert flagged or raised, f"{found.name}: fault {kind} left no flagged sample nor error"
        after = run.read()
        assert _all_valid(after), f"{found.name}: samples still flagged after {kind} ended"


def check_unplug_replug(case: DriverCase, found: FoundDriver | None = None) -> None:
    """Unplugged: a read raises DeviceDisconnected and opening fails with a typed DeviceError
    until the device is back; then reopening works and reads valid data. A polled chip that
    cannot tell an unplug from a silent bus flags every sample instead, and reads valid data
    again once it answers."""
    found = found or find_driver(case.driver)
    assert case.unplug is not None, f"{found.name}: the case has no unplug fault"
    assert case.virtual_time, f"{found.name}: unplugging is simulated in virtual time only"
    at_s, end_s = _window(case.unplug)
    with _Run(case, found, case.with_fault(case.unplug)) as run:
        margin_s = 3 * run.block_s + 0.5
        run.open()
        limit = 10 * math.ceil((end_s + margin_s) / run.block_s) + 100
        raised = False
        for _ in range(limit):
            try:
                block = run.read()
            except DeviceError as err:
                raised = True
                assert isinstance(err, DeviceDisconnected), (
                    f"{found.name}: unplugged, a read raised {type(err).__name__} ({err}), "
                    "not DeviceDisconnected"
                )
                assert run.since_open_s() >= at_s, f"{found.name}: disconnected before unplug"
                break
            if block.status is not None and block.status.all():
                break
        else:
            raise AssertionError(f"{found.name}: unplugged, reads went on as if nothing happened")
        if raised:
            _reopen(run, end_s + margin_s, "replugged")
        while run.since_open_s() < end_s + run.block_s:
            run.read()
        assert _all_valid(run.read()), f"{found.name}: replugged, samples are still flagged"


def check_close(case: DriverCase, found: FoundDriver | None = None) -> None:
    """close() is idempotent and harmless before open(); a read after close() ends with
    InterruptedError; a read that close() interrupts ends with InterruptedError or its block;
    a closed driver opens again and reads."""
    found = found or find_driver(case.driver)
    with _Run(case, found) as run:
        name = found.name
        run.call("close() before open()", run.driver.close)
        run.open()
        run.read()
        run.call("close()", run.driver.close)
        run.call("close() again", run.driver.close)
        try:
            run.call("read() after close()", run.driver.read)
        except InterruptedError:
            pass
        else:
            raise AssertionError(f"{name}: read() after close() returned instead of raising")
        run.open()
        run.read()
        ended: list[object] = []
        reader = threading.Thread(target=lambda: ended.append(_outcome(run.driver.read)))
        reader.start()
        run.call("close() during read()", run.driver.close)
        reader.join(run.timeout_s)
        assert not reader.is_alive(), f"{name}: close() did not end a read in progress"
        assert isinstance(ended[0], Block | InterruptedError), (
            f"{name}: a read ended by close() raised {ended[0]!r}"
        )
        run.open()
        run.read()


def _outcome(fn: Callable[[], T]) -> T | BaseException:
    try:
        return fn()
    except BaseException as err:
        return err


GENERIC_BAD_CONFIGS: tuple[tuple[Mapping[str, Any], str], ...] = (
    ({"rate_hz": 0}, "rate_hz"),
    ({"channels": []}, "channels"),
    ({"channels": [{"name": "a", "unit": "V"}, {"name": "a", "unit": "V"}]}, "channels"),
    ({"no_such_key": 1}, "no_such_key"),
)
"""Configs every stream schema refuses, with the key path its error names."""


def check_config_errors(case: DriverCase, found: FoundDriver | None = None) -> None:
    """The case's config is valid; each bad one (the suite's and the case's) is refused by the
    driver's schema with an error naming the key path."""
    found = found or find_driver(case.driver)
    found.schema.model_validate(dict(case.config))
    for changes, path in (*GENERIC_BAD_CONFIGS, *case.bad_configs):
        try:
            found.schema.model_validate(case.with_changes(changes))
        except ValidationError as err:
            locs = [".".join(str(p) for p in e["loc"]) for e in err.errors()]
            assert any(loc == path or loc.startswith(path + ".") for loc in locs), (
                f"{found.name}: {dict(changes)} refused at {locs}, expected at {path!r}"
            )
        else:
            raise AssertionError(f"{found.name}: {dict(changes)} was accepted")


# --- pytest -----------------------------------------------------------------------------------


class DriverConformance:
    """The suite as test methods: ``class TestMyDriver(DriverConformance): case = DriverCase(...)``
    in a driver package's tests, and pytest runs every check. Checks the case has nothing for
    (no faults, no unplug) are left out of the subclass, not skipped."""

    case: ClassVar[DriverCase]

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        case = cls.__dict__.get("case")
        if case is None:
            return
        if not case.faults:
            cls.test_an_injected_fault_is_flagged_or_a_typed_error = None  # type: ignore[assignment]
        if case.unplug is None:
            cls.test_unplug_is_a_disconnect_and_replug_reopens = None  # type: ignore[assignment]

    def found(self) -> FoundDriver:
        """The driver under test (override to test a driver not registered by name)."""
        return find_driver(self.case.driver)

    def test_opens_and_describes_its_config(self) -> None:
        check_open_and_describe(self.case, self.found())

    def test_reads_block_at_the_configured_rate(self) -> None:
        check_reads_at_rate(self.case, self.found())

    def test_an_injected_fault_is_flagged_or_a_typed_error(self) -> None:
        for fault in self.case.faults:
            check_fault(self.case, fault, self.found())

    def test_unplug_is_a_disconnect_and_replug_reopens(self) -> None:
        check_unplug_replug(self.case, self.found())

    def test_close_is_idempotent_and_ends_reads(self) -> None:
        check_close(self.case, self.found())

    def test_the_time_fit_holds_on_its_clock(self) -> None:
        check_time_fit(self.case, self.found())

    def test_bad_configs_name_their_key_path(self) -> None:
        check_config_errors(self.case, self.found())

