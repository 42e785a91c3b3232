"""The conformance checks of output drivers: write, read back what the device holds, fail with a
typed DeviceError while the device is faulty and work again after a reopen, close idempotent,
bad configs refused with their key path. All in virtual time, every call bounded."""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, ClassVar, TypeVar

from fleetdaq.contract.errors import DeviceError
from fleetdaq.contract.schema import OutputBase
from fleetdaq.edge.drivers.base import OutputDriver
from fleetdaq.edge.drivers.conformance.case import (
    NotConforming,
    call_within,
    check_refused,
    expect,
    lookup,
    with_changes,
    with_fault,
)
from fleetdaq.edge.drivers.pacing import VirtualTime
from fleetdaq.edge.drivers.shared import SharedDevices

T = TypeVar("T")


@dataclass(frozen=True, slots=True)
class FoundOutput:
    """An output driver as the suite builds it: its config schema and how to create it."""

    name: str
    schema: type[OutputBase]
    create: Callable[[OutputBase, VirtualTime, SharedDevices], OutputDriver]


def find_output(name: str) -> FoundOutput:
    """The output driver a config's `driver: name` selects (see `lookup`)."""
    schema, create = lookup(name, "output")
    return FoundOutput(name, schema, create)


@dataclass(frozen=True)
class OutputCase:
    """An output driver as the suite runs it."""

    config: Mapping[str, Any]
    """A valid output config, as a site file's mapping under `outputs:`, `driver:` included;
    with a `sim:` block when the driver reaches hardware through a transport."""
    tolerance: float = 0.0
    """How far a readback may be from the value written (a DAC's step); 0 for digital."""
    fault: Mapping[str, Any] | None = None
    """A `sim.faults` entry (`at_s`, `for_s` after the first write) that makes the device fail
    for a while (a NACK, an unplug)."""
    bad_configs: Sequence[tuple[Mapping[str, Any], str]] = ()
    """(keys to change in `config`, the key path the error must name), beyond the suite's own
    (an unknown key, no safe value, a safe value outside the limits)."""
    call_timeout_s: float = 10.0

    @property
    def driver(self) -> str:
        return str(self.config["driver"])


class _OutputRun:
    """One output driver made from a config on a VirtualTime; calls bounded, closed on exit."""

    def __init__(
        self, case: OutputCase, found: FoundOutput, config: Mapping[str, Any] | None = None
    ) -> None:
        self.case = case
        self.cfg = found.schema.model_validate(dict(config or case.config))
        self.clock = VirtualTime()
        self.driver = found.create(self.cfg, self.clock, SharedDevices())

    def __enter__(self) -> _OutputRun:
        return self

    def __exit__(self, kind: type[BaseException] | None, *exc: object) -> None:
        if kind is None:
            self.close()
            return
        with contextlib.suppress(Exception):  # the failure in flight says more
            self.close()

    def call(self, what: str, fn: Callable[[], T]) -> T:
        """`fn()`, bounded (`call_within`); closing the driver ends a call that hangs."""
        return call_within(
            self.case.call_timeout_s, f"{self.case.driver}: {what}", fn, self.driver.close
        )

    def open(self) -> None:
        self.call("open()", self.driver.open)

    def close(self) -> None:
        self.call("close()", self.driver.close)

    def write(self, value: float) -> None:
        self.call(f"write({value:g})", lambda: self.driver.write(value))

    def read(self) -> float:
        return self.call("read()", self.driver.read)

    def values(self) -> list[float]:
        """Values to write: both limits, the middle, then the safe value."""
        low, high = self.cfg.low, self.cfg.high
        if self.cfg.kind == "digital":
            return [1.0, 0.0, 1.0, self.cfg.safe]
        return [low, high, (low + high) / 2, self.cfg.safe]

    def write_and_read_back(self, value: float) -> None:
        name = self.case.driver
        self.write(value)
        got = self.read()
        expect(isinstance(got, float), f"{name}: read() returned {got!r}, not a float")
        expect(
            abs(got - value) <= self.case.tolerance,
            f"{name}: wrote {value:g}, read back {got:g} (tolerance {self.case.tolerance:g})",
        )


def check_output_write_readback(case: OutputCase, found: FoundOutput | None = None) -> None:
    """The output says where it is; opened, every value written between its limits reads back
    (within the case's tolerance; exactly 0 or 1 for a digital output)."""
    found = found or find_output(case.driver)
    with _OutputRun(case, found) as run:
        where = run.driver.where
        expect(isinstance(where, str) and bool(where), f"{found.name}: `where` is {where!r}")
        run.open()
        for value in run.values():
            run.write_and_read_back(value)


def check_output_close(case: OutputCase, found: FoundOutput | None = None) -> None:
    """close() is idempotent and harmless before open(); a closed output opens again and
    writes."""
    found = found or find_output(case.driver)
    with _OutputRun(case, found) as run:
        run.close()
        run.open()
        run.write_and_read_back(run.values()[0])
        run.close()
        run.close()
        run.open()
        run.write_and_read_back(run.values()[1])


def check_output_fault(case: OutputCase, found: FoundOutput | None = None) -> None:
    """While the device is faulty a write or a readback fails with a typed DeviceError, never
    another exception; once the fault is over, a reopened output writes and reads back."""
    found = found or find_output(case.driver)
    name = found.name
    expect(case.fault is not None, f"{name}: the case has no fault")
    fault = case.fault or {}
    at_s, for_s = float(fault.get("at_s", 0.0)), fault.get("for_s")
    expect(for_s is not None, f"{name}: fault {dict(fault)} needs its for_s (when it ends)")
    with _OutputRun(case, found, with_fault(case.config, fault)) as run:
        first, second = run.values()[:2]
        run.open()
        run.write_and_read_back(first)  # before the fault; its schedule starts by now
        run.clock.advance(round((at_s + 0.01) * 1e9))
        failed: list[DeviceError] = []
        for call in (lambda: run.write(second), run.read):
            try:
                call()
            except DeviceError as err:
                failed.append(err)
            except Exception as err:
                raise NotConforming(
                    f"{name}: a faulty device raised {type(err).__name__}: {err}"
                ) from err
        expect(bool(failed), f"{name}: writes and reads went on during fault {dict(fault)}")
        run.clock.advance(round(float(for_s or 0.0) * 1e9))
        run.close()
        run.open()
        run.write_and_read_back(second)


def check_output_config_errors(case: OutputCase, found: FoundOutput | None = None) -> None:
    """The case's config is valid; an unknown key, a missing safe value, a safe value outside
    the limits and the case's own bad configs are refused, naming their key path."""
    found = found or find_output(case.driver)
    cfg = found.schema.model_validate(dict(case.config))
    outside = 2.0 if cfg.kind == "digital" else cfg.high + (cfg.high - cfg.low)
    generic: list[tuple[Mapping[str, Any], str]] = [
        ({"no_such_key": 1}, "no_such_key"),
        ({"safe": None}, "safe"),
        ({"safe": outside, "initial": None}, "safe"),
    ]
    for changes, path in (*generic, *case.bad_configs):
        check_refused(found.schema, with_changes(case.config, changes), path, found.name)


class OutputConformance:
    """The output checks as test methods: ``class TestMyOutput(OutputConformance): case =
    OutputCase(...)``. Without a fault in the case, its check is left out, not skipped."""

    case: ClassVar[OutputCase]

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        case = cls.__dict__.get("case")
        if case is not None and case.fault is None:
            cls.test_a_faulty_device_is_a_typed_error_then_reopens = None  # type: ignore[assignment]

    def found(self) -> FoundOutput:
        """The output driver under test (override to test one not registered by name)."""
        return find_output(self.case.driver)

    def test_writes_and_reads_back_between_its_limits(self) -> None:
        check_output_write_readback(self.case, self.found())

    def test_close_is_idempotent_and_it_reopens(self) -> None:
        check_output_close(self.case, self.found())

    def test_a_faulty_device_is_a_typed_error_then_reopens(self) -> None:
        check_output_fault(self.case, self.found())

    def test_bad_configs_name_their_key_path(self) -> None:
        check_output_config_errors(self.case, self.found())
