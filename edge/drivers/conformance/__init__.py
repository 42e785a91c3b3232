"""The driver conformance suite: what every stream driver with a simulator must do, checked.

Like python-can's back-to-back tests, the suite ships in the package, so a driver that lives in
another distribution runs the same checks as the built-in ones. A driver is described once as
a `DriverCase` (a valid config with a `sim:` block, the faults its simulator can inject, configs
its schema must refuse); each `check_*` function builds the driver from the case, runs it on
its simulator and raises `NotConforming` (an AssertionError) saying what is wrong: open and
describe, read at rate, fault, unplug and replug, close, time fit, config errors; and for
output drivers (`OutputCase`) write and read back, a faulty device, close, config errors. The
checks need no test framework; `DriverConformance` and `OutputConformance` are the
pytest-friendly form, classes whose `test_*` methods a driver package's tests inherit by naming
their case.

Drivers whose simulated transport runs on the clock it is given run on a `VirtualTime` here, so
reads return at once and a fault window of seconds costs nothing; sims paced by the host's own
clock run in real time with short blocks. Every call on a driver is bounded: one that does not
return in time closes the driver and fails the check.
"""

from __future__ import annotations

from typing import Any, ClassVar

from fleetdaq.edge.drivers.conformance.case import (
    ENTRY_POINT_GROUP,
    DriverCase,
    DriverRun,
    FoundDriver,
    NotConforming,
    check_block,
    find_driver,
    lookup,
)
from fleetdaq.edge.drivers.conformance.checks import (
    GENERIC_BAD_CONFIGS,
    check_close,
    check_config_errors,
    check_fault,
    check_open_and_describe,
    check_reads_at_rate,
    check_time_fit,
    check_unplug_replug,
)
from fleetdaq.edge.drivers.conformance.outputs import (
    FoundOutput,
    OutputCase,
    OutputConformance,
    check_output_close,
    check_output_config_errors,
    check_output_fault,
    check_output_write_readback,
    find_output,
)

__all__ = [
    "ENTRY_POINT_GROUP",
    "GENERIC_BAD_CONFIGS",
    "DriverCase",
    "DriverConformance",
    "DriverRun",
    "FoundDriver",
    "FoundOutput",
    "NotConforming",
    "OutputCase",
    "OutputConformance",
    "check_block",
    "check_close",
    "check_config_errors",
    "check_fault",
    "check_open_and_describe",
    "check_output_close",
    "check_output_config_errors",
    "check_output_fault",
    "check_output_write_readback",
    "check_reads_at_rate",
    "check_time_fit",
    "check_unplug_replug",
    "find_driver",
    "find_output",
    "lookup",
]


class DriverConformance:
    """The suite as test methods: ``class TestMyDriver(DriverConformance): case = DriverCase(...)``
    in a driver package's tests, and pytest runs every check on it. Checks the case has nothing
    for (no faults, no unplug) are left out of the subclass, not skipped: a skip would read as
    a part missing from the machine."""

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
        """The driver under test (override to test one not registered by name)."""
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
