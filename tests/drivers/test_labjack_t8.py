"""LabJack T8: stream decoding and CORE_TIMER unwrapping (pure, from a table), the driver through
the fake `ljm` (the simulated T8, in virtual time): drift, wraps, skipped scans, backlog, stream
errors, unplug and replug; polled I/O and outputs; the fake's API against labjack-ljm's."""

from __future__ import annotations

import inspect
import json
import logging
import subprocess
import sys
import threading
from pathlib import Path

import numpy as np
import pytest

from fleetdaq.contract.config.node import SpoolConfig
from fleetdaq.contract.errors import (
    ConfigError,
    DeviceDisconnected,
    DeviceError,
    DeviceNotFound,
)
from fleetdaq.contract.wire import SampleStatus
from fleetdaq.edge.device_time import DeviceTimeFit
from fleetdaq.edge.drivers.base import Block
from fleetdaq.edge.drivers.labjack_ljm import CORE_TIMER_HZ, CoreTimer, T8Outputs
from fleetdaq.edge.drivers.labjack_t8 import LabJackT8, LabJackT8Stream, decode_scans
from fleetdaq.edge.drivers.labjack_t8_poll import LabJackT8Poll, LabJackT8PollStream
from fleetdaq.edge.drivers.pacing import SystemTime, VirtualTime
from fleetdaq.edge.drivers.sim_ljm import SimLJM, errorcodes
from fleetdaq.edge.event_publisher import EventPublisher
from fleetdaq.edge.spool import StreamSpool
from fleetdaq.edge.stream_loop import StreamLoop
from fleetdaq.hub.config.load import parse_config
from tests.dev_extra import vendor_module
from tests.drivers.fakes import DATA
from tests.procs import REPO, wait_until

TWO32 = 1 << 32


def _stream(sim: str, rate: float = 10_000, scans: int = 1000, chans: int = 8, extra: str = ""):
    channels = ", ".join(f"{{name: c{i}, unit: V}}" for i in range(chans))
    text = (
        "site: s\nnodes:\n  wec:\n    streams:\n      t8: {driver: labjack_t8, "
        f"rate_hz: {rate}, scans_per_batch: {scans}, sim: {sim}, channels: [{channels}]{extra}}}\n"
    )
    cfg = parse_config(text, "t").nodes["wec"].streams["t8"]
    assert isinstance(cfg, LabJackT8Stream)
    return cfg


def _driver(sim: str, **kw):  # type: ignore[no-untyped-def]
    cfg = _stream(sim, **kw)
    clock = VirtualTime()
    assert cfg.sim is not None
    ljm = SimLJM(cfg.sim, clock)
    return LabJackT8(cfg, transport=ljm, clock=clock), ljm, clock


# --- pure decoding --------------------------------------------------------------------------


def test_stream_data_splits_into_volts_skipped_scans_and_32_bit_timer_values() -> None:
    table = json.loads((DATA / "t8_stream.json").read_text())
    volts, skipped, ticks32 = decode_scans(table["data"], table["ain_count"])
    assert volts.tolist() == table["volts"]
    assert skipped.tolist() == table["skipped"]
    for got, want in zip(ticks32.tolist(), table["ticks32"], strict=True):
        if want is not None:
            assert got == want


def test_core_timer_unwraps_exactly_across_wraps_and_between_reads() -> None:
    tps = 10_000.0  # ticks per scan at 10 kS/s
    truth = 4_294_900_000 + np.arange(0, 2_000_000, dtype=np.int64) * 10_000
    timer = CoreTimer()
    out = []
    for block in np.array_split(np.arange(truth.size), 37):  # reads of uneven length
        expected = np.full(block.size, tps)
        out.append(timer.unwrap(truth[block] % TWO32, expected))
    assert np.array_equal(np.concatenate(out), truth)
    assert timer.wraps == (truth[-1] // TWO32) - (truth[0] // TWO32)


def test_modaq2s_wrap_arithmetic_loses_a_tick_per_wrap_where_ours_is_exact() -> None:
    raw = np.array([TWO32 - 5, 7, 20], dtype=np.int64)  # one wrap between the first two
    ours = CoreTimer().unwrap(raw, np.array([0.0, 12.0, 13.0]))
    modaq2 = raw + np.array([0, TWO32 - 1, TWO32 - 1])  # += UINT32_MAX per wrap
    assert ours.tolist() == [TWO32 - 5, TWO32 + 7, TWO32 + 20]
    assert (ours - modaq2).tolist() == [0, 1, 1]


# --- the driver through the fake ljm -----------------------------------------------------


def test_stream_configures_the_t8_and_reads_blocks_of_scans_per_read() -> None:
    d, ljm, _ = _driver("{seed: 1}", chans=3, extra=", resolution_index: 4, settling_us: 50")
    d.open()
    regs = ljm.device.registers
    assert regs["STREAM_RESOLUTION_INDEX"] == 4
    assert regs["STREAM_SETTLING_US"] == 50
    assert regs["STREAM_BUFFER_SIZE_BYTES"] == 32768
    stream = ljm.device.stream
    assert stream is not None
    assert stream.addresses == [0, 2, 4, 61520, 4899]
    block = d.read()
    assert block.raw.shape == (1000, 3)
    assert block.raw.flags.c_contiguous
    assert np.all(np.abs(block.raw) <= 11.0)
    assert np.std(block.raw) > 0.1
    assert block.status is None
    assert block.events == ()


def test_each_channel_gets_its_range_and_ain() -> None:
    extra = ""
    text = (
        "site: s\nnodes:\n  wec:\n    streams:\n      t8: {driver: labjack_t8, rate_hz: 1000, "
        "sim: {seed: 2}, channels: [{name: a, ain: 6, range: 0.3}, {name: b, range: 2.4}]}\n"
    )
    cfg = parse_config(text + extra, "t").nodes["wec"].streams["t8"]
    assert isinstance(cfg, LabJackT8Stream)
    assert cfg.sim is not None
    clock = VirtualTime()
    ljm = SimLJM(cfg.sim, clock)
    d = LabJackT8(cfg, transport=ljm, clock=clock)
    d.open()
    assert ljm.device.registers["AIN6_RANGE"] == 0.3
    assert ljm.device.registers["AIN1_RANGE"] == 2.4
    raw = d.read().raw
    assert np.abs(raw[:, 0]).max() <= 0.3
    assert np.abs(raw[:, 1]).max() <= 2.4


def test_device_time_is_the_core_timer_unwrapped_through_wraps_at_100_mhz() -> None:
    d, ljm, _ = _driver("{seed: 3, core_timer_start: 4290000000, drift_ppm: 40}")
    d.open()
    index = 0
    first_dev = None
    for _ in range(600):  # 60 s: the 32-bit timer wraps once (every ~43 s)
        block = d.read()
        index += block.raw.shape[0]
        assert block.device_ns is not None
        truth = ljm.core_timer_at_scan(index - 1) * 1_000_000_000 // CORE_TIMER_HZ
        assert block.device_ns == truth
        first_dev = first_dev if first_dev is not None else block.device_ns
    assert d.health()["core_timer_wraps"] == 2  # at ~0.05 s and ~43 s
    assert block.device_ns - first_dev == pytest.approx(59.9e9, rel=1e-4)  # device ns, not host


def test_skipped_scans_are_marked_invalid_counted_and_raised_as_an_event() -> None:
    d, _, _ = _driver("{seed: 4, faults: [{kind: skipped_scans, at_s: 0.25, scans: 30}]}")
    d.open()
    blocks = [d.read() for _ in range(6)]
    bad = [
        (i, int(b.status.any(axis=1).sum())) for i, b in enumerate(blocks) if b.status is not None
    ]
    assert sum(n for _, n in bad) == 30
    status = np.concatenate([b.status for b in blocks if b.status is not None])
    assert set(np.unique(status)) == {0, SampleStatus.SKIPPED_SCAN}
    events = [e for b in blocks for e in b.events]
    assert [e.tag for e in events] == ["skipped_scans"] * len(bad)
    assert d.health()["skipped_scans"] == 30
    assert all(b.device_ns is not None for b in blocks)  # time survives skipped scans


def test_a_slow_reader_sees_the_ljm_backlog_grow_in_health_and_an_event() -> None:
    d, _, clock = _driver("{seed: 5}")
    d.open()
    d.read()
    clock.advance(1_000_000_000)  # the reader stalls for a second: 10 reads' worth
    block = d.read()
    health = d.health()
    assert health["ljm_scan_backlog"] >= 9000
    assert [e.tag for e in block.events] == ["reader_behind"]
    tags = []
    for _ in range(12):
        tags += [e.tag for e in d.read().events]
    assert tags == ["reader_caught_up"]
    assert d.health()["ljm_scan_backlog"] < 1000


def test_an_ljm_buffer_overflow_is_a_typed_error_keeping_the_ljm_code() -> None:
    d, _, clock = _driver("{seed: 6}")
    d.open()
    clock.advance(30_000_000_000)  # 30 s behind: more than LJM buffers
    with pytest.raises(DeviceError, match=r"eStreamRead: LJM error 1301 LJM_BUFFER_FULL") as err:
        d.read()
    assert err.value.code == errorcodes.LJM_BUFFER_FULL
    assert err.value.__cause__ is not None
    assert type(err.value.__cause__).__name__ == "LJMError"


def test_unplug_is_device_disconnected_and_the_driver_reopens_after_replug() -> None:
    d, ljm, clock = _driver("{seed: 7, faults: [{kind: unplug, at_s: 1.05, for_s: 2}]}")
    d.open()
    for _ in range(10):
        d.read()
    with pytest.raises(DeviceDisconnected, match=r"LJM error 1226 DEVICE_DISCONNECTED"):
        d.read()
    d.close()
    with pytest.raises(DeviceNotFound, match=r"openS: LJM error 1227 DEVICE_NOT_FOUND"):
        d.open()  # still unplugged
    clock.advance(2_100_000_000)
    d.open()
    block = d.read()
    assert [e.tag for e in block.events] == ["reconnected"]
    assert ljm.device.power_ons == 2  # replugging power-cycled the T8
    assert d.health()["reconnects"] == 1


def test_a_stream_error_from_config_is_raised_and_the_stream_restarts() -> None:
    d, _, _ = _driver("{seed: 8, faults: [{kind: stream_error, at_s: 0.5, for_s: 0.1}]}")
    d.open()
    for _ in range(5):
        d.read()  # 0.1 .. 0.5 s
    with pytest.raises(DeviceError, match=r"SYNCHRONIZATION_TIMEOUT"):
        d.read()
    d.close()
    d.open()
    assert d.read().raw.shape == (1000, 8)


def test_device_time_fit_survives_a_stream_restart_and_restarts_after_a_power_cycle() -> None:
    d, _, clock = _driver("{seed: 9, faults: [{kind: unplug, at_s: 20, for_s: 1}]}")
    fit = DeviceTimeFit(10_000)
    d.open()
    index = 0

    def run(reads: int) -> None:
        nonlocal index
        for _ in range(reads):
            block = d.read()
            index += block.raw.shape[0]
            fit.observe(index - 1, block.host_ns, block.device_ns)

    run(50)
    d.close()
    d.open()  # a plain restart: the device clock ran on
    index = 0
    run(50)
    assert fit.restarts == 0
    with pytest.raises(DeviceDisconnected):
        run(200)
    d.close()
    clock.advance(1_000_000_000)
    d.open()  # power-cycled: CORE_TIMER started from a new value
    index = 0
    run(5)
    assert fit.restarts == 1


class SteppableTime(VirtualTime):
    """Virtual time whose CLOCK_REALTIME can be stepped, as an NTP daemon or an operator's
    `date -s` steps a host's (its monotonic clock runs on)."""

    def __init__(self) -> None:
        super().__init__()
        self.step_ns = 0

    def time_ns(self) -> int:
        return super().time_ns() + self.step_ns


class Events(EventPublisher):
    def __init__(self) -> None:
        super().__init__(None, "fleetdaq/s/wec/events", "wec")
        self.said: list[tuple[int, str, str, dict[str, object]]] = []

    def emit(self, level: int, source: str, tag: str, message: str, /, **fields: object) -> None:
        self.said.append((level, tag, message, fields))

    def tagged(self, tag: str) -> list[tuple[int, str, str, dict[str, object]]]:
        return [e for e in self.said if e[1] == tag]


def test_a_host_clock_step_back_is_an_event_with_how_far_sample_times_went_back(
    tmp_path: Path,
) -> None:
    """The agent's acquisition loop on the T8 driver and the fake `ljm`: the host clock steps
    50 ms back mid-run. The fit restarts and the batches after the step are stamped on the new
    clock (times go back), and the loop says so once, with the jump and the sequence."""
    cfg = _stream("{seed: 3}", rate=10_000, scans=500, chans=2)
    clock = SteppableTime()
    assert cfg.sim is not None
    driver = LabJackT8(cfg, transport=SimLJM(cfg.sim, clock), clock=clock)
    spool_cfg = SpoolConfig()
    spool = StreamSpool(tmp_path / "spool", spool_cfg.max_bytes, spool_cfg.max_age_s)
    events = Events()
    loop = StreamLoop("s", "wec", "t8", cfg, None, events, spool, spool_cfg, driver=driver)
    loop.start()
    try:
        wait_until(lambda: loop.counters.batches >= 40, 30, "40 batches before the step", 0.01)
        clock.step_ns = -50_000_000
        wait_until(lambda: events.tagged("time_restart"), 30, "a time_restart event", 0.01)
    finally:
        loop.stop()
        loop.join(5.0)
    (said,) = events.tagged("time_restart")
    level, _, message, fields = said
    assert level == logging.WARNING
    assert "the host clock stepped back" in message
    assert "go back" in message
    jump = fields["jump_ns"]
    assert isinstance(jump, int)
    assert -55_000_000 < jump < -45_000_000, jump  # the step, give or take read latency
    assert loop.time_fit.restarts == 1
    assert f"from sequence {fields['sequence']}:" in message


class WatchedSystemTime(SystemTime):
    """Real time for the fake T8, telling when a read starts waiting for its scans."""

    def __init__(self) -> None:
        self.waiting = threading.Event()

    def sleep_until(self, monotonic_ns: int, cancel: threading.Event) -> bool:
        self.waiting.set()
        return super().sleep_until(monotonic_ns, cancel)


def test_closing_during_a_read_ends_it_as_interrupted_not_as_an_error() -> None:
    # One read is 60 s of scans in real time: only the close can end it within the test.
    cfg = _stream("{seed: 10}", rate=100, scans=6000)
    assert cfg.sim is not None
    clock = WatchedSystemTime()
    d = LabJackT8(cfg, transport=SimLJM(cfg.sim, clock))
    d.open()
    outcome: list[BaseException | Block] = []

    def reader() -> None:
        try:
            outcome.append(d.read())
        except BaseException as err:
            outcome.append(err)

    t = threading.Thread(target=reader)
    t.start()
    assert clock.waiting.wait(30), "the read never reached eStreamRead's wait"
    d.close()
    t.join(30)
    assert not t.is_alive(), "close() did not end the read"
    assert len(outcome) == 1
    assert isinstance(outcome[0], InterruptedError), outcome


def test_polled_ain_and_dio_are_stamped_by_the_core_timer() -> None:
    text = (
        "site: s\nnodes:\n  n:\n    streams:\n      io: {driver: labjack_t8_poll, rate_hz: 10,"
        " sim: {seed: 11}, channels: [{name: v, source: AIN2, range: 4.8},"
        " {name: door, source: FIO3}]}\n"
    )
    cfg = parse_config(text, "t").nodes["n"].streams["io"]
    assert isinstance(cfg, LabJackT8PollStream)
    assert cfg.sim is not None
    clock = VirtualTime()
    ljm = SimLJM(cfg.sim, clock)
    d = LabJackT8Poll(cfg, transport=ljm, clock=clock)
    d.open()
    blocks = [d.read() for _ in range(30)]
    assert ljm.device.registers["AIN2_RANGE"] == 4.8
    values = np.concatenate([b.raw for b in blocks])
    assert np.abs(values[:, 0]).max() <= 4.8
    assert set(values[:, 1]) == {1.0}
    devs = np.array([b.device_ns for b in blocks], dtype=np.int64)
    assert np.all(np.diff(devs) > 0)
    assert np.diff(devs).mean() == pytest.approx(1e8 * (1 + 40e-6), rel=1e-5)  # 100 ms, 40 ppm


def test_outputs_return_the_devices_readback_and_refuse_what_the_t8_cannot_do() -> None:
    cfg = _stream("{seed: 12}")
    clock = VirtualTime()
    with T8Outputs(SimLJM(cfg.sim, clock)) as out:  # type: ignore[arg-type]
        assert out.set_dac(0, 2.5) == 2.5
        assert out.set_dio("FIO4", True) is True
        assert out.read_dio("FIO4") is True
        assert out.set_dio("EIO1", False) is False
        with pytest.raises(ValueError, match=r"outside -0.1..10.0 V"):
            out.set_dac(1, 12.0)
        with pytest.raises(ValueError, match=r"not a T8 digital line"):
            out.set_dio("FIO9", True)


def test_config_refuses_what_a_t8_cannot_stream() -> None:
    with pytest.raises(ConfigError, match=r"rate_hz: must be at most 40000"):
        _stream("{}", rate=50_000)
    with pytest.raises(ConfigError, match=r"not a T8 range: 10"):
        parse_config(
            "site: s\nnodes:\n  n:\n    streams:\n      t8: {driver: labjack_t8, rate_hz: 10,"
            " channels: [{name: a, range: 10}]}\n",
            "t",
        )
    with pytest.raises(ConfigError, match=r"two channels read the same AIN"):
        parse_config(
            "site: s\nnodes:\n  n:\n    streams:\n      t8: {driver: labjack_t8, rate_hz: 10,"
            " channels: [{name: a}, {name: b, ain: 0}]}\n",
            "t",
        )


# --- the fake against the vendor, and the vendor missing ------------------------------------


LJM_FUNCTIONS = [
    "openS",
    "close",
    "eWriteName",
    "eWriteNames",
    "eReadName",
    "eReadNames",
    "namesToAddresses",
    "eStreamStart",
    "eStreamRead",
    "eStreamStop",
    "errorToString",
]


def test_the_fake_ljm_has_labjack_ljms_functions_signatures_codes_and_error_type() -> None:
    ljm = vendor_module("labjack-ljm", "labjack.ljm")  # in the dev extra: never skipped
    fake = SimLJM(_stream("{}").sim, VirtualTime())  # type: ignore[arg-type]
    for name in LJM_FUNCTIONS:
        real = list(inspect.signature(getattr(ljm, name)).parameters)
        ours = list(inspect.signature(getattr(fake, name)).parameters)
        assert ours == real, name
    for code, value in vars(errorcodes).items():
        if not code.startswith("_"):
            assert getattr(ljm.errorcodes, code) == value, code
    assert fake.constants.DUMMY_VALUE == ljm.constants.DUMMY_VALUE
    err = fake.LJMError(errorcodes.STREAM_NOT_RUNNING)
    real_err = ljm.LJMError(errorcodes.STREAM_NOT_RUNNING, errorString="STREAM_NOT_RUNNING")
    assert (err.errorCode, err.errorAddress) == (real_err.errorCode, real_err.errorAddress)
    assert str(err) == str(real_err)


# Each runs the real driver table in a child process whose view of the vendor's software is
# faked at the import boundary, so the outcome is the same where LJM is installed and where not.
NO_LABJACK_LJM = """
import sys

class NoLabjackLjm:  # as if `pip install labjack-ljm` had never run
    def find_spec(self, name, path=None, target=None):
        if name == "labjack" or name.startswith("labjack."):
            raise ModuleNotFoundError(f"No module named {name!r}", name=name)
        return None

sys.meta_path.insert(0, NoLabjackLjm())
"""
NO_NATIVE_LJM = """
import ctypes

class NoLibLabJackM(ctypes.CDLL):  # as if LJM itself (libLabJackM.so) were not installed
    def __init__(self, name, *args, **kwargs):
        if name is not None and "LabJackM" in str(name):
            raise OSError(f"{name}: cannot open shared object file: No such file or directory")
        super().__init__(name, *args, **kwargs)

ctypes.CDLL = NoLibLabJackM
"""
CREATE_T8_DRIVERS = """
import sys
from fleetdaq.hub.config.load import parse_config
from fleetdaq.edge.drivers.table import create_driver
from fleetdaq.contract.errors import DriverUnavailable

SITE = (
    "site: s\\nnodes:\\n  wec:\\n    streams:\\n"
    "      t8: {driver: labjack_t8, rate_hz: 1000, channels: [{name: a}]}\\n"
    "      io: {driver: labjack_t8_poll, rate_hz: 10, channels: [{name: b, source: AIN1}]}\\n"
)
for name, cfg in parse_config(SITE, "site.yaml").nodes["wec"].streams.items():
    try:
        create_driver(cfg)
    except DriverUnavailable as err:
        print(name, err)
    else:
        print(name, "created")
wrapper = sys.modules.get("labjack.ljm.ljm")
print("wrapper", "absent" if wrapper is None else f"native={wrapper._staticLib is not None}")
"""


def _t8_drivers_in_a_child(prelude: str) -> list[str]:
    done = subprocess.run(
        [sys.executable, "-c", prelude + CREATE_T8_DRIVERS],
        cwd=REPO,
        capture_output=True,
        text=True,
        check=False,
        timeout=60,
    )
    assert done.returncode == 0, done.stderr
    return done.stdout.splitlines()


def test_without_labjack_ljm_installed_the_t8_is_unavailable_in_one_line() -> None:
    lines = _t8_drivers_in_a_child(NO_LABJACK_LJM)
    assert [line.split(":")[0] for line in lines] == [
        "t8 the LabJack T8 needs labjack-ljm",
        "io the LabJack T8 needs labjack-ljm",
        "wrapper absent",
    ], lines
    assert all("install LJM" in line for line in lines[:2])


def test_without_the_native_ljm_library_the_t8_is_unavailable_in_one_line() -> None:
    vendor_module("labjack-ljm", "labjack")  # the real wrapper goes down its own no-library path
    lines = _t8_drivers_in_a_child(NO_NATIVE_LJM)
    # labjack-ljm itself prints why it could not load the library ("Cannot load the LJM ...").
    ours = [line for line in lines if "Cannot load the LJM library" not in line]
    assert [line.split(":")[0] for line in ours] == [
        "t8 the LabJack T8 needs LJM's native library",
        "io the LabJack T8 needs LJM's native library",
        "wrapper native=False",
    ], lines
    assert all("install LJM" in line for line in ours[:2])
