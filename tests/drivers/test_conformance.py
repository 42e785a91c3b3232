"""Every built-in driver, stream and output, passes the driver conformance suite on its
simulator (`fleetdaq.edge.drivers.conformance`), and the suite fails drivers that break the
contract."""

from __future__ import annotations

import contextlib
from typing import Any

import numpy as np
import pytest
from pydantic import ConfigDict

from fleetdaq.contract.drivers import DriverKind, driver_registry
from fleetdaq.contract.errors import DeviceDisconnected, DeviceError
from fleetdaq.contract.schema import OutputBase, StreamBase
from fleetdaq.edge.drivers.base import Block, Driver, OutputDriver
from fleetdaq.edge.drivers.conformance import (
    DriverCase,
    DriverConformance,
    FoundDriver,
    FoundOutput,
    OutputCase,
    OutputConformance,
    check_close,
    check_config_errors,
    check_fault,
    check_output_fault,
    check_output_write_readback,
    check_reads_at_rate,
    check_time_fit,
    check_unplug_replug,
    find_driver,
    find_output,
)
from fleetdaq.edge.drivers.pacing import TimeSource, VirtualTime
from fleetdaq.edge.drivers.shared import SharedDevices
from fleetdaq.edge.drivers.wave_sim import WaveSimStream


def _channels(*names_units: tuple[str, str]) -> list[dict[str, str]]:
    return [{"name": n, "unit": u} for n, u in names_units]


VOLTS = _channels(("a", "V"), ("b", "V"), ("c", "V"))

# --- sims paced by the host's clock: real time, short blocks -------------------------------


class TestWaveSim(DriverConformance):
    case = DriverCase(
        {"driver": "wave_sim", "rate_hz": 1000, "scans_per_batch": 20, "channels": VOLTS},
        virtual_time=False,
        reads=15,
        bad_configs=(({"wave_period_s": 0}, "wave_period_s"), ({"noise_v": -1}, "noise_v")),
    )


class TestThermocoupleSim(DriverConformance):
    case = DriverCase(
        {
            "driver": "thermocouple_sim",
            "rate_hz": 200,
            "scans_per_batch": 4,
            "channels": _channels(("tc", "degC"), ("cj", "degC")),
        },
        virtual_time=False,
        reads=15,
        bad_configs=(({"layer_s": 0}, "layer_s"),),
    )


class TestEnvironmentSim(DriverConformance):
    case = DriverCase(
        {
            "driver": "environment_sim",
            "rate_hz": 200,
            "scans_per_batch": 4,
            "channels": _channels(("air", "degC"), ("rh", "%"), ("p", "hPa")),
        },
        virtual_time=False,
        reads=15,
    )


# --- real drivers on their simulated transports, in virtual time ----------------------------


class TestLabJackT8(DriverConformance):
    case = DriverCase(
        {
            "driver": "labjack_t8",
            "rate_hz": 10_000,
            "scans_per_batch": 1000,
            "channels": VOLTS,
            "sim": {"seed": 3, "drift_ppm": 40, "read_latency_ms": 0},
        },
        faults=(
            {"kind": "skipped_scans", "at_s": 0.55, "for_s": 0.01, "scans": 30},
            {"kind": "stream_error", "at_s": 0.5, "for_s": 0.1},
        ),
        unplug={"kind": "unplug", "at_s": 1.05, "for_s": 2},
        drift_ppm=40,
        drift_tolerance_ppm=1,
        bad_configs=(
            ({"rate_hz": 40_001}, "rate_hz"),
            ({"channels": [{"name": "x", "unit": "V", "range": 3}]}, "channels.0.range"),
            ({"buffer_bytes": 3000}, ""),
        ),
    )


class TestLabJackT8Poll(DriverConformance):
    case = DriverCase(
        {
            "driver": "labjack_t8_poll",
            "rate_hz": 10,
            "scans_per_batch": 2,
            "channels": [
                {"name": "v", "unit": "V", "source": "AIN2", "range": 4.8},
                {"name": "door", "source": "FIO3"},
            ],
            "sim": {"seed": 11, "drift_ppm": 40, "read_latency_ms": 0},
        },
        unplug={"kind": "unplug", "at_s": 1.05, "for_s": 2},
        drift_ppm=40,
        drift_tolerance_ppm=1,
        bad_configs=(
            ({"rate_hz": 101}, "rate_hz"),
            ({"channels": [{"name": "x", "source": "AIN9"}]}, "channels.0.source"),
        ),
    )


class TestMax31855(DriverConformance):
    case = DriverCase(
        {
            "driver": "max31855",
            "rate_hz": 4,
            "scans_per_batch": 2,
            "channels": _channels(("tc", "degC"), ("cj", "degC")),
            "sim": {"seed": 5},
        },
        faults=(
            {"kind": "open_circuit", "at_s": 2, "for_s": 1},
            {"kind": "short_gnd", "at_s": 2, "for_s": 1},
        ),
        unplug={"kind": "no_response", "at_s": 2, "for_s": 2},
        bad_configs=(({"rate_hz": 11}, "rate_hz"), ({"channels": VOLTS}, "channels")),
    )


class TestMax31856(DriverConformance):
    case = DriverCase(
        {
            "driver": "max31856",
            "rate_hz": 4,
            "scans_per_batch": 2,
            "channels": _channels(("tc", "degC"), ("cj", "degC")),
            "sim": {"seed": 6},
        },
        faults=(
            {"kind": "open_circuit", "at_s": 2, "for_s": 1},
            {"kind": "tc_range", "at_s": 2, "for_s": 1},
        ),
        unplug={"kind": "no_response", "at_s": 2, "for_s": 2},
        bad_configs=(({"thermocouple": "Q"}, "thermocouple"), ({"averaging": 3}, "averaging")),
    )


class TestSht3x(DriverConformance):
    case = DriverCase(
        {
            "driver": "sht3x",
            "rate_hz": 2,
            "scans_per_batch": 2,
            "channels": _channels(("t", "degC"), ("rh", "%")),
            "sim": {"seed": 7},
        },
        faults=({"kind": "crc_error", "at_s": 3, "for_s": 1},),
        unplug={"kind": "nack", "at_s": 3, "for_s": 2},
        bad_configs=(({"address": 0x40}, "address"), ({"retries": 11}, "retries")),
    )


class TestWeldRobotSim(DriverConformance):
    case = DriverCase(
        {
            "driver": "weld_robot_sim",
            "rate_hz": 10,
            "scans_per_batch": 5,
            "cell": "c1",
            "layer_s": 2,
            "max_wait_s": 1,
            "channels": [{"name": "welding"}, {"name": "layer"}, {"name": "last_wait_s"}],
        },
        bad_configs=(({"channels": [{"name": "heat"}]}, "channels"), ({"cell": "a b"}, "cell")),
    )


# --- outputs, on their simulated transports ---------------------------------------------------


class TestLabJackT8Dac(OutputConformance):
    case = OutputCase(
        {"driver": "labjack_t8_dac", "dac": 0, "min": 0, "max": 5, "safe": 1, "sim": {"seed": 3}},
        fault={"kind": "unplug", "at_s": 1, "for_s": 2},
        bad_configs=(({"max": 11}, "max"), ({"dac": 2}, "dac")),
    )


class TestLabJackT8Dio(OutputConformance):
    case = OutputCase(
        {"driver": "labjack_t8_dio", "line": "FIO2", "safe": 0, "sim": {"seed": 3}},
        fault={"kind": "unplug", "at_s": 1, "for_s": 2},
        bad_configs=(({"line": "FIO9"}, "line"), ({"max_rate": 1}, "max_rate")),
    )


class TestPcf8574(OutputConformance):
    case = OutputCase(
        {"driver": "pcf8574", "address": 0x20, "pin": 3, "invert": True, "safe": 0, "sim": {}},
        fault={"kind": "nack", "at_s": 1, "for_s": 1},
        bad_configs=(({"address": 0x30}, "address"), ({"pin": 8}, "pin")),
    )


class TestMcp4725(OutputConformance):
    case = OutputCase(
        {"driver": "mcp4725", "address": 0x61, "min": 0, "max": 3, "safe": 1, "sim": {}},
        tolerance=3.3 / 4096,
        fault={"kind": "nack", "at_s": 1, "for_s": 1},
        bad_configs=(({"max": 4}, "max"), ({"unit": "mA"}, "unit")),
    )


class TestWeldRobotResume(OutputConformance):
    case = OutputCase(
        {"driver": "weld_robot_resume", "cell": "c1", "safe": 0},
        bad_configs=(({"kind": "analog"}, "kind"),),
    )


def test_every_built_in_driver_runs_the_conformance_suite() -> None:
    cases = [c for c in globals().values() if isinstance(c, type) and hasattr(c, "case")]
    streams = {c.case.driver for c in cases if issubclass(c, DriverConformance)}
    outputs = {c.case.driver for c in cases if issubclass(c, OutputConformance)}
    built_in = {
        name: found.plugin.kind
        for name, found in driver_registry().found.items()
        if found.origin.dist.split()[0] == "fleetdaq"
    }
    assert streams == {n for n, kind in built_in.items() if kind == DriverKind.STREAM}
    assert outputs == {n for n, kind in built_in.items() if kind == DriverKind.OUTPUT}


def test_checks_a_case_has_nothing_for_are_left_out_not_skipped() -> None:
    names = {n for n in dir(TestWaveSim) if n.startswith("test_") and getattr(TestWaveSim, n)}
    assert "test_an_injected_fault_is_flagged_or_a_typed_error" not in names
    assert "test_unplug_is_a_disconnect_and_replug_reopens" not in names
    assert "test_reads_block_at_the_configured_rate" in names
    assert callable(TestMax31855.test_unplug_is_a_disconnect_and_replug_reopens)
    assert TestWeldRobotResume.test_a_faulty_device_is_a_typed_error_then_reopens is None


# --- the suite fails drivers that break the contract -----------------------------------------


def _wrapping(name: str, wrap: type[Any]) -> FoundDriver:
    """The built-in driver `name`, each instance wrapped in `wrap` (a driver breaking a rule)."""
    real = find_driver(name)

    def create(cfg: StreamBase, clock: TimeSource, shared: SharedDevices) -> Driver:
        made: Driver = wrap(real.create(cfg, clock, shared))
        return made

    return FoundDriver(name, real.schema, create)


class Wrapper:
    def __init__(self, inner: Driver) -> None:
        self.inner = inner

    def open(self) -> None:
        self.inner.open()

    def read(self) -> Block:
        return self.inner.read()

    def close(self) -> None:
        self.inner.close()


class HidesFaults(Wrapper):
    """Reports every sample valid: a fault's readings pass as data."""

    def read(self) -> Block:
        b = self.inner.read()
        raw = np.where(b.status != 0, 21.0, b.raw) if b.status is not None else b.raw
        return Block(raw, b.host_ns, None, b.device_ns, b.events, b.late_polls)


class CrashesOnFaults(Wrapper):
    def read(self) -> Block:
        b = self.inner.read()
        if b.status is not None:
            raise KeyError("status")
        return b


class ClosesOnce(Wrapper):
    def __init__(self, inner: Driver) -> None:
        super().__init__(inner)
        self.closed = 0

    def close(self) -> None:
        self.closed += 1
        if self.closed > 1:
            raise RuntimeError("already closed")
        self.inner.close()


class SkipsHalfTheScans(Wrapper):
    """Returns every other scan only (a driver that drops data and still claims the rate)."""

    def read(self) -> Block:
        b = self.inner.read()
        status = None if b.status is None else b.status[::2]
        return Block(b.raw[::2], b.host_ns, status, b.device_ns, b.events, b.late_polls)


MAX31855 = TestMax31855.case


def test_the_suite_fails_a_driver_that_passes_faulty_readings_off_as_data() -> None:
    with pytest.raises(AssertionError, match="left no flagged sample nor error"):
        check_fault(MAX31855, MAX31855.faults[0], _wrapping("max31855", HidesFaults))


def test_the_suite_fails_a_driver_that_crashes_on_a_fault() -> None:
    with pytest.raises(AssertionError, match="crashed a read: KeyError"):
        check_fault(MAX31855, MAX31855.faults[0], _wrapping("max31855", CrashesOnFaults))


def test_the_suite_fails_a_driver_whose_close_is_not_idempotent() -> None:
    with pytest.raises(RuntimeError, match="already closed"):
        check_close(MAX31855, _wrapping("max31855", ClosesOnce))


def test_the_suite_fails_a_driver_whose_blocks_do_not_hold_the_rates_scans() -> None:
    t8 = TestLabJackT8.case
    with pytest.raises(AssertionError, match="the device clock spans"):
        check_reads_at_rate(t8, _wrapping("labjack_t8", SkipsHalfTheScans))


class LaxWaveSimStream(WaveSimStream):
    """The wave sim's schema, but ignoring keys it does not know."""

    model_config = ConfigDict(extra="ignore")


def test_the_suite_fails_a_schema_that_accepts_an_unknown_key() -> None:
    real = find_driver("wave_sim")
    with pytest.raises(AssertionError, match="'no_such_key': 1} was accepted"):
        check_config_errors(
            TestWaveSim.case, FoundDriver("wave_sim", LaxWaveSimStream, real.create)
        )


class OutputWrapper:
    def __init__(self, inner: OutputDriver) -> None:
        self.inner = inner

    @property
    def where(self) -> str:
        return self.inner.where

    def open(self) -> None:
        self.inner.open()

    def write(self, value: float) -> None:
        self.inner.write(value)

    def read(self) -> float:
        return self.inner.read()

    def close(self) -> None:
        self.inner.close()


class SwallowsErrors(OutputWrapper):
    """Says the last value written when the device cannot say (a made-up readback)."""

    last = 0.0

    def write(self, value: float) -> None:
        self.last = value
        with contextlib.suppress(DeviceError):
            self.inner.write(value)

    def read(self) -> float:
        try:
            return self.inner.read()
        except DeviceError:
            return self.last


class ReadsBackOff(OutputWrapper):
    def read(self) -> float:
        return self.inner.read() + 0.01


def _wrapping_output(name: str, wrap: type[Any]) -> FoundOutput:
    real = find_output(name)

    def create(cfg: OutputBase, clock: VirtualTime, shared: SharedDevices) -> OutputDriver:
        made: OutputDriver = wrap(real.create(cfg, clock, shared))
        return made

    return FoundOutput(name, real.schema, create)


def test_the_suite_fails_an_output_that_hides_a_faulty_device() -> None:
    with pytest.raises(AssertionError, match="writes and reads went on during fault"):
        check_output_fault(TestMcp4725.case, _wrapping_output("mcp4725", SwallowsErrors))


def test_the_suite_fails_an_output_whose_readback_is_not_what_it_holds() -> None:
    with pytest.raises(AssertionError, match=r"wrote 0, read back 0.01 \(tolerance 0.0008"):
        check_output_write_readback(TestMcp4725.case, _wrapping_output("mcp4725", ReadsBackOff))


class UnplugIsAPlainError(Wrapper):
    """Reports an unplugged device as a plain DeviceError: the agent could not tell it apart."""

    def read(self) -> Block:
        try:
            return self.inner.read()
        except DeviceDisconnected as err:
            raise DeviceError(str(err)) from err


class FastDeviceClock(Wrapper):
    """Scales device time by 1.02: a clock running 2 % fast, beyond any crystal's drift."""

    def read(self) -> Block:
        b = self.inner.read()
        device_ns = None if b.device_ns is None else round(b.device_ns * 1.02)
        return Block(b.raw, b.host_ns, b.status, device_ns, b.events, b.late_polls)


def test_the_suite_fails_a_driver_that_hides_an_unplug_as_a_plain_device_error() -> None:
    t8 = TestLabJackT8.case
    with pytest.raises(AssertionError, match=r"raised DeviceError .* not DeviceDisconnected"):
        check_unplug_replug(t8, _wrapping("labjack_t8", UnplugIsAPlainError))


def test_the_suite_fails_a_driver_whose_device_clock_runs_at_the_wrong_rate() -> None:
    t8 = TestLabJackT8.case
    with pytest.raises(AssertionError, match="more than the 1 % of drift the fit follows"):
        check_time_fit(t8, _wrapping("labjack_t8", FastDeviceClock))
