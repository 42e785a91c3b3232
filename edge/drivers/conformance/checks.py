"""The conformance checks: each builds the driver from a `DriverCase`, runs it on its simulator
and raises NotConforming (an AssertionError) saying what is wrong."""

from __future__ import annotations

import itertools
import json
import math
import threading
from collections.abc import Callable, Mapping
from typing import Any, TypeVar

from fleetdaq.contract.errors import DeviceDisconnected, DeviceError
from fleetdaq.edge.device_time import DeviceTimeFit
from fleetdaq.edge.drivers.base import Block, DriverHealth
from fleetdaq.edge.drivers.conformance.case import (
    DriverCase,
    DriverRun,
    FoundDriver,
    NotConforming,
    all_valid,
    check_refused,
    expect,
    find_driver,
)

T = TypeVar("T")


def check_open_and_describe(case: DriverCase, found: FoundDriver | None = None) -> None:
    """The config validates into the driver's schema with the channels, units and rate it was
    given; the driver opens; its blocks have one column per channel; its health (if it has
    one) is a JSON-able mapping."""
    found = found or find_driver(case.driver)
    with DriverRun(case, found) as run:
        cfg, raw, name = run.cfg, case.config, found.name
        expect(cfg.driver == name, f"{name}: the schema gave driver {cfg.driver!r}")
        got = [(ch.name, ch.unit) for ch in cfg.channels]
        want = [(ch["name"], ch.get("unit", "")) for ch in raw["channels"]]
        expect(got == want, f"{name}: channels {got}, configured {want}")
        expect(math.isclose(cfg.rate_hz, float(raw["rate_hz"])), f"{name}: rate {cfg.rate_hz}")
        expect(len(cfg.resolutions()) == len(cfg.channels), f"{name}: a resolution per channel")
        run.open()
        run.read()
        if isinstance(run.driver, DriverHealth):
            health = run.call("health()", run.driver.health)
            expect(
                isinstance(health, dict) and all(isinstance(k, str) for k in health),
                f"{name}: health() must be a mapping of names, got {health!r}",
            )
            json.dumps(health)


def check_reads_at_rate(case: DriverCase, found: FoundDriver | None = None) -> None:
    """Reads block until their scans exist: over `case.reads` blocks the scans (and the polls
    the host was late for) span the time they should at the configured rate, on the device
    clock when blocks carry one and on the clock the driver was given; times only increase."""
    found = found or find_driver(case.driver)
    with DriverRun(case, found) as run:
        start = run.clock.monotonic_ns()  # before open: the device counts from there
        run.open()
        blocks = [run.read() for _ in range(case.reads)]
        elapsed_s = (run.clock.monotonic_ns() - start) / 1e9
    name, rate = found.name, run.cfg.rate_hz
    hosts = [b.host_ns for b in blocks]
    expect(all(b > a for a, b in itertools.pairwise(hosts)), f"{name}: host_ns went back")
    devices = [b.device_ns for b in blocks]
    has_clock = {d is not None for d in devices}
    expect(len(has_clock) == 1, f"{name}: device_ns is set in some blocks only")
    # The time the blocks after the first span: their scans and the polls the host missed.
    spanned = sum(b.raw.shape[0] + b.late_polls for b in blocks[1:]) / rate
    total = sum(b.raw.shape[0] + b.late_polls for b in blocks) / rate
    if has_clock == {True}:
        dev = [d for d in devices if d is not None]
        expect(all(b > a for a, b in itertools.pairwise(dev)), f"{name}: device_ns went back")
        measured = (dev[-1] - dev[0]) / 1e9
        expect(
            math.isclose(measured, spanned, rel_tol=0.01),
            f"{name}: the device clock spans {measured:.6f} s over scans worth {spanned:.6f} s",
        )
    expect(
        elapsed_s >= 0.98 * total - 1.0 / rate,
        f"{name}: {total:.3f} s of scans read in {elapsed_s:.3f} s: reads did not wait for them",
    )
    if case.virtual_time:
        host_s = (hosts[-1] - hosts[0]) / 1e9
        expect(
            math.isclose(host_s, spanned, rel_tol=0.02, abs_tol=0.5 / rate),
            f"{name}: reads returned {host_s:.6f} s apart for scans worth {spanned:.6f} s",
        )
    else:  # real time on a shared host: later than the scans only by scheduling
        expect(elapsed_s <= 1.5 * total + 0.5, f"{name}: {total:.3f} s took {elapsed_s:.3f} s")


def check_time_fit(case: DriverCase, found: FoundDriver | None = None) -> None:
    """The agent's device-time fit (`fleetdaq.edge.device_time`), fed as the stream loop feeds
    it, holds on the driver's clock: no restart, sample times only increasing, batches
    contiguous (in virtual time), none stamped after the read that returned it, the fitted
    period within 1 % of nominal (and the drift the simulator is set to, if the case says)."""
    found = found or find_driver(case.driver)
    name = found.name
    with DriverRun(case, found) as run:
        # A read that comes late on a busy host (the first one, often) puts the first line
        # above later reads; only more than a second below it is taken for a clock step.
        fit = DeviceTimeFit(run.cfg.rate_hz, step_back_ns=10**7 if case.virtual_time else 10**9)
        run.open()
        index, prev_end, prev_last = 0, None, 0
        clock: list[tuple[int, int]] = []  # (scan index, device ns) of each block's last scan
        for k in range(case.reads):
            block = run.read()
            scans = block.raw.shape[0]
            index += block.late_polls
            fit.observe(index + scans - 1, block.host_ns, block.device_ns)
            t0, period = fit.stamp(index, scans)
            last = t0 + round(period * (scans - 1))
            expect(
                last <= block.host_ns,
                f"{name}: block {k} stamped {(last - block.host_ns) / 1e6:.3f} ms after its read",
            )
            if prev_end is not None:
                expect(t0 > prev_last, f"{name}: block {k} starts before block {k - 1} ended")
            if prev_end is not None and not block.late_polls and case.virtual_time:
                # In real time the host's scheduling moves the fit (and the stamps) by itself.
                gap_ms = (t0 - prev_end) / 1e6
                expect(
                    abs(gap_ms) <= max(2.0, 1e3 * run.block_s * 0.05),
                    f"{name}: block {k} starts {gap_ms:.3f} ms from where block {k - 1} ended",
                )
            prev_end, prev_last = t0 + round(period * scans), last
            if block.device_ns is not None:
                clock.append((index + scans - 1, block.device_ns))
            index += scans
    nominal = 1e9 / run.cfg.rate_hz
    if len(clock) >= 2:
        device_period = (clock[-1][1] - clock[0][1]) / (clock[-1][0] - clock[0][0])
        expect(
            math.isclose(device_period, nominal, rel_tol=0.01),
            f"{name}: the device clock puts scans {device_period:.1f} ns apart, nominal "
            f"{nominal:.1f} ns: more than the 1 % of drift the fit follows",
        )
    expect(fit.restarts == 0, f"{name}: the time fit restarted {fit.restarts} time(s)")
    expect(
        math.isclose(fit.period_ns, nominal, rel_tol=0.01),
        f"{name}: fitted period {fit.period_ns:.1f} ns, nominal {nominal:.1f} ns",
    )
    if case.drift_ppm is not None:
        expect(
            abs(fit.drift_ppm - case.drift_ppm) <= case.drift_tolerance_ppm,
            f"{name}: fitted drift {fit.drift_ppm:.2f} ppm, simulated {case.drift_ppm:g} ppm",
        )


def _window(fault: Mapping[str, Any]) -> tuple[float, float]:
    at_s, for_s = float(fault.get("at_s", 0.0)), fault.get("for_s")
    expect(for_s is not None, f"fault {dict(fault)}: the suite needs its for_s (when it ends)")
    return at_s, at_s + float(for_s or 0.0)


def _reopen(run: DriverRun, until_s: float, what: str) -> None:
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
                raise NotConforming(f"{run.case.driver}: {what}: reopening fails: {err}") from err
        run.advance(step)


def check_fault(
    case: DriverCase, fault: Mapping[str, Any], found: FoundDriver | None = None
) -> None:
    """An injected fault shows as flagged samples (a SampleStatus, never a made-up value) or a
    typed DeviceError, never another exception; nothing is flagged before it starts; after it
    ends (and a reopen, if it raised) the samples are valid again."""
    found = found or find_driver(case.driver)
    name, kind = found.name, fault.get("kind", "?")
    expect(case.virtual_time, f"{name}: faults are injected in virtual time only")
    at_s, end_s = _window(fault)
    with DriverRun(case, found, case.with_fault(fault)) as run:
        margin_s = 3 * run.block_s + 0.5
        limit = 10 * math.ceil((end_s + margin_s) / run.block_s) + 100
        flagged = raised = reads = 0
        run.open()
        while run.since_open_s() < end_s + margin_s:
            reads += 1
            expect(reads < limit, f"{name}: {limit} reads without reaching {end_s} s")
            try:
                block = run.read()
            except DeviceError as err:
                if run.since_open_s() < at_s:
                    raise NotConforming(f"{name}: {err} before the fault") from err
                raised += 1
                _reopen(run, end_s + margin_s, f"after {kind}")
                continue
            except AssertionError:
                raise
            except Exception as err:
                raise NotConforming(
                    f"{name}: fault {kind} crashed a read: {type(err).__name__}: {err}"
                ) from err
            if not all_valid(block):
                expect(run.since_open_s() >= at_s, f"{name}: samples flagged before {kind}")
                flagged += 1
        expect(bool(flagged or raised), f"{name}: fault {kind} left no flagged sample nor error")
        expect(all_valid(run.read()), f"{name}: samples still flagged after {kind} ended")


def check_unplug_replug(case: DriverCase, found: FoundDriver | None = None) -> None:
    """Unplugged: a read raises DeviceDisconnected and opening fails with a typed DeviceError
    until the device is back; then reopening works and reads valid data. A polled chip that
    cannot tell an unplug from a silent bus flags every sample instead, and reads valid data
    again once it answers."""
    found = found or find_driver(case.driver)
    name = found.name
    expect(case.unplug is not None, f"{name}: the case has no unplug fault")
    expect(case.virtual_time, f"{name}: unplugging is simulated in virtual time only")
    at_s, end_s = _window(case.unplug or {})
    with DriverRun(case, found, case.with_fault(case.unplug or {})) as run:
        margin_s = 3 * run.block_s + 0.5
        limit = 10 * math.ceil((end_s + margin_s) / run.block_s) + 100
        raised = False
        run.open()
        for _ in range(limit):
            try:
                block = run.read()
            except DeviceError as err:
                if not isinstance(err, DeviceDisconnected) or run.since_open_s() < at_s:
                    raise NotConforming(
                        f"{name}: {run.since_open_s():.3f} s after opening (unplugged at "
                        f"{at_s:g} s) a read raised {type(err).__name__} ({err}), "
                        "not DeviceDisconnected"
                    ) from err
                raised = True
                break
            if block.status is not None and block.status.all():
                break
        else:
            raise NotConforming(f"{name}: unplugged, reads went on as if nothing happened")
        if raised:
            run.call("close()", run.driver.close)
            if run.since_open_s() < end_s:
                try:
                    run.call("open() while unplugged", run.driver.open)
                except DeviceError:
                    pass
                else:
                    raise NotConforming(f"{name}: opened while the device was unplugged")
            _reopen(run, end_s + margin_s, "replugged")
        while run.since_open_s() < end_s + run.block_s:
            run.read()
        expect(all_valid(run.read()), f"{name}: replugged, samples are still flagged")


def _outcome(fn: Callable[[], T]) -> T | BaseException:
    try:
        return fn()
    except BaseException as err:
        return err


def check_close(case: DriverCase, found: FoundDriver | None = None) -> None:
    """close() is idempotent and harmless before open(); a read after close() ends with
    InterruptedError; a read that close() interrupts ends with InterruptedError or its block;
    a closed driver opens again and reads."""
    found = found or find_driver(case.driver)
    name = found.name
    with DriverRun(case, found) as run:
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
            raise NotConforming(f"{name}: read() after close() returned instead of raising")
        run.open()
        run.read()
        ended: list[object] = []
        reader = threading.Thread(target=lambda: ended.append(_outcome(run.driver.read)))
        reader.start()
        run.call("close() during read()", run.driver.close)
        reader.join(run.timeout_s)
        expect(not reader.is_alive(), f"{name}: close() did not end a read in progress")
        expect(
            isinstance(ended[0], Block | InterruptedError),
            f"{name}: a read ended by close() raised {ended[0]!r}",
        )
        run.open()
        run.read()


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
        check_refused(found.schema, case.with_changes(changes), path, found.name)
