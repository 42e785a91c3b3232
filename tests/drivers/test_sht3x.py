"""SHT3x: CRC-8 and conversion against the datasheet; the driver through the simulated SMBus
(register-level: NACK while measuring, CRC per word) with NACK and CRC faults; the fake smbus2
against the real one (installed by the dev extra)."""

from __future__ import annotations

import inspect
import json

import pytest

from fleetdaq.contract.errors import DeviceNotFound
from fleetdaq.contract.wire import SampleStatus
from fleetdaq.edge.drivers.pacing import VirtualTime
from fleetdaq.edge.drivers.sht3x import (
    CrcError,
    Sht3x,
    Sht3xStream,
    crc8,
    decode_sht3x,
    encode_sht3x,
)
from fleetdaq.edge.drivers.sim_smbus import SimI2cMsg, SimSht3x, SimSMBus, SimSmbus2
from fleetdaq.hub.config.load import parse_config
from tests.dev_extra import vendor_module
from tests.drivers.fakes import DATA

TABLE = json.loads((DATA / "sht3x.json").read_text())


def _stream(extra: str = "", rate: float = 1) -> Sht3xStream:
    text = (
        "site: s\nnodes:\n  n:\n    streams:\n      env: {driver: sht3x, "
        f"rate_hz: {rate}, channels: [{{name: t}}, {{name: rh}}]{extra}}}\n"
    )
    cfg = parse_config(text, "t").nodes["n"].streams["env"]
    assert isinstance(cfg, Sht3xStream)
    return cfg


@pytest.mark.parametrize("row", TABLE["crc"], ids=lambda r: r["data"])
def test_crc8_matches_the_datasheet_example_and_table(row: dict) -> None:
    assert crc8(bytes.fromhex(row["data"])) == int(row["crc"], 16)


@pytest.mark.parametrize("row", TABLE["measurements"], ids=lambda r: r["hex"])
def test_measurements_convert_as_the_datasheet_formulas(row: dict) -> None:
    r = decode_sht3x(bytes.fromhex(row["hex"].replace(" ", "")))
    assert r.temperature_c == pytest.approx(row["celsius"], abs=1e-4)
    assert r.humidity_pct == pytest.approx(row["percent_rh"], abs=1e-4)


def test_a_corrupted_crc_is_refused() -> None:
    data = bytearray(encode_sht3x(21.5, 40.0))
    data[5] ^= 1
    with pytest.raises(CrcError, match=r"humidity CRC"):
        decode_sht3x(bytes(data))


def _driver(extra: str = "", retries: int = 3) -> tuple[Sht3x, SimSht3x]:
    cfg = _stream(f", retries: {retries}, sim: {{seed: 1}}{extra}")
    clock = VirtualTime()
    bus = SimSmbus2(clock)
    assert cfg.sim is not None
    sensor = SimSht3x(cfg.sim, clock)
    bus.attach(1, 0x44, sensor)
    return Sht3x(cfg, transport=bus, clock=clock), sensor


def test_driver_measures_temperature_and_humidity_once_per_poll() -> None:
    d, sensor = _driver()
    d.open()
    blocks = [d.read() for _ in range(5)]
    assert sensor.measurements == 5
    for b in blocks:
        assert b.status is None
        t, rh = b.raw[0]
        assert 10 < t < 18
        assert 60 < rh < 95


def test_reading_before_the_measurement_is_done_is_nacked_by_the_sensor() -> None:
    d, _sensor = _driver()
    d.open()
    bus = d.smbus.SMBus(1)
    msg = d.smbus.i2c_msg
    bus.i2c_rdwr(msg.write(0x44, [0x24, 0x00]))
    with pytest.raises(OSError, match="Remote I/O") as err:
        bus.i2c_rdwr(msg.read(0x44, 6))  # no time has passed: still measuring
    assert err.value.errno == 121


def test_occasional_nacks_and_crc_errors_are_retried_and_the_samples_stay_valid() -> None:
    faults = (
        ", faults: [{kind: nack, at_s: 0, probability: 0.3},"
        " {kind: crc_error, at_s: 0, probability: 0.3}]"
    )
    cfg = _stream(", retries: 6, sim: {seed: 1" + faults + "}")
    clock = VirtualTime()
    bus = SimSmbus2(clock)
    assert cfg.sim is not None
    bus.attach(1, 0x44, SimSht3x(cfg.sim, clock))
    d = Sht3x(cfg, transport=bus, clock=clock)
    d.open()
    blocks = [d.read() for _ in range(20)]
    invalid = sum(b.status is not None for b in blocks)
    health = d.health()
    assert health["retries"] > 5
    assert health["crc_errors"] > 0
    assert health["nacks"] > 0
    assert invalid <= 1


def test_a_sensor_that_keeps_failing_gives_invalid_samples_and_one_event() -> None:
    cfg = _stream(", retries: 2, sim: {seed: 1, faults: [{kind: crc_error, at_s: 1, for_s: 3}]}")
    clock = VirtualTime()
    bus = SimSmbus2(clock)
    assert cfg.sim is not None
    bus.attach(1, 0x44, SimSht3x(cfg.sim, clock))
    d = Sht3x(cfg, transport=bus, clock=clock)
    d.open()
    blocks = [d.read() for _ in range(6)]
    status = [None if b.status is None else b.status.tolist() for b in blocks]
    assert status == [None, [[5, 5]], [[5, 5]], [[5, 5]], None, None]
    tags = [e.tag for b in blocks for e in b.events]
    assert tags == ["sensor_fault", "sensor_fault_cleared"]
    assert "CRC error" in blocks[1].events[0].message
    assert "3 attempt(s)" in blocks[1].events[0].message
    assert SampleStatus.COMM_ERROR == 5


def test_no_sensor_at_the_address_is_device_not_found() -> None:
    cfg = _stream(", address: 0x45, sim: {}")
    clock = VirtualTime()
    bus = SimSmbus2(clock)
    assert cfg.sim is not None
    bus.attach(1, 0x44, SimSht3x(cfg.sim, clock))  # wired at 0x44, configured at 0x45
    with pytest.raises(DeviceNotFound, match=r"SHT3x at 0x45 on /dev/i2c-1: no answer \(NACK\)"):
        Sht3x(cfg, transport=bus, clock=clock).open()


def test_a_missing_i2c_bus_is_device_not_found() -> None:
    clock = VirtualTime()
    d = Sht3x(_stream(", bus: 3, sim: {}"), transport=SimSmbus2(clock), clock=clock)
    with pytest.raises(DeviceNotFound, match=r"/dev/i2c-3 not found: enable I2C"):
        d.open()


def test_the_driver_works_with_smbus2s_own_i2c_msg() -> None:
    smbus2 = vendor_module("smbus2", "smbus2")  # in the dev extra: never skipped

    class RealMsgBus(SimSmbus2):
        i2c_msg = smbus2.i2c_msg

    cfg = _stream(", sim: {seed: 3}")
    clock = VirtualTime()
    bus = RealMsgBus(clock)
    assert cfg.sim is not None
    bus.attach(1, 0x44, SimSht3x(cfg.sim, clock))
    d = Sht3x(cfg, transport=bus, clock=clock)
    d.open()
    assert d.read().status is None


def test_the_fake_smbus2_has_smbus2s_signatures_for_what_the_drivers_call() -> None:
    smbus2 = vendor_module("smbus2", "smbus2")

    def params(fn: object) -> list[str]:
        return list(inspect.signature(fn).parameters)  # type: ignore[arg-type]

    # SMBus(bus, force) opens /dev/i2c-<bus>; the fake's factory takes the same arguments.
    assert params(SimSmbus2.SMBus) == params(smbus2.SMBus.__init__)
    for name in ("i2c_rdwr", "write_byte", "read_byte", "close"):  # SHT3x, HD44780
        assert params(getattr(SimSMBus, name)) == params(getattr(smbus2.SMBus, name)), name
    for name in ("read", "write"):
        assert params(getattr(SimI2cMsg, name)) == params(getattr(smbus2.i2c_msg, name)), name
