"""MAX31856: decoder against the datasheet's tables, configuration registers, the driver
through a fake SpiDev and through the simulated register model in virtual time."""

from __future__ import annotations

import json

import pytest

from fleetdaq.contract.errors import ConfigError, DeviceNotFound
from fleetdaq.contract.wire import SampleStatus
from fleetdaq.edge.drivers.max31856 import (
    Max31856,
    Max31856Stream,
    config_registers,
    decode_max31856,
    encode_max31856,
)
from fleetdaq.edge.drivers.pacing import VirtualTime
from fleetdaq.edge.drivers.table import create_driver
from fleetdaq.hub.config.load import parse_config
from tests.drivers.fakes import DATA, FakeSpiDev

TABLE = json.loads((DATA / "max31856.json").read_text())


def _stream(extra: str = "", rate: float = 4) -> Max31856Stream:
    text = (
        "site: s\nnodes:\n  n:\n    streams:\n      tc: {driver: max31856, "
        f"rate_hz: {rate}, channels: [{{name: tc}}, {{name: cj}}]{extra}}}\n"
    )
    cfg = parse_config(text, "t").nodes["n"].streams["tc"]
    assert isinstance(cfg, Max31856Stream)
    return cfg


@pytest.mark.parametrize("row", TABLE["thermocouple"], ids=lambda r: f"{r['celsius']}C")
def test_linearized_thermocouple_registers_decode_as_in_the_datasheet(row: dict) -> None:
    regs = bytes(2) + bytes.fromhex(row["hex"]) + bytes(1)
    assert decode_max31856(regs).thermocouple_c == row["celsius"]
    assert encode_max31856(row["celsius"], 0.0)[2:5] == bytes.fromhex(row["hex"])


@pytest.mark.parametrize("row", TABLE["cold_junction"], ids=lambda r: f"{r['celsius']}C")
def test_cold_junction_registers_decode_as_in_the_datasheet(row: dict) -> None:
    regs = bytes.fromhex(row["hex"]) + bytes(4)
    assert decode_max31856(regs).cold_junction_c == row["celsius"]
    assert encode_max31856(0.0, row["celsius"])[0:2] == bytes.fromhex(row["hex"])


@pytest.mark.parametrize("row", TABLE["config"], ids=lambda r: f"{r['cr0']}-{r['cr1']}")
def test_thermocouple_type_averaging_filter_and_mode_set_cr0_and_cr1(row: dict) -> None:
    extra = (
        f", thermocouple: {row['thermocouple']}, averaging: {row['averaging']}, "
        f"mains_hz: {row['mains_hz']}, conversion: {row['conversion']}"
    )
    cfg = _stream(extra, rate=1)
    cr0, cr1, mask = config_registers(cfg)
    assert (f"{cr0:02X}", f"{cr1:02X}", mask) == (row["cr0"], row["cr1"], 0)


@pytest.mark.parametrize(
    ("sr", "tc", "cj"),
    [
        (0x01, SampleStatus.OPEN_CIRCUIT, SampleStatus.VALID),
        (0x02, SampleStatus.DEVICE_FAULT, SampleStatus.DEVICE_FAULT),
        (0x40, SampleStatus.OUT_OF_RANGE, SampleStatus.VALID),
        (0x80, SampleStatus.OUT_OF_RANGE, SampleStatus.OUT_OF_RANGE),
        (0x08, SampleStatus.OUT_OF_RANGE, SampleStatus.VALID),
        (0x20, SampleStatus.VALID, SampleStatus.OUT_OF_RANGE),
        (0x00, SampleStatus.VALID, SampleStatus.VALID),
    ],
)
def test_fault_status_register_bits_map_to_sample_status(sr: int, tc: int, cj: int) -> None:
    r = decode_max31856(encode_max31856(100.0, 25.0, sr))
    assert (r.thermocouple_status, r.cold_junction_status) == (tc, cj)
    assert (r.problem is None) == (sr == 0)


def test_driver_writes_its_configuration_reads_it_back_and_polls_registers_0a_to_0f() -> None:
    cr0, cr1 = 0x91, 0x03
    regs = encode_max31856(250.5, 23.25)
    spi = FakeSpiDev([[0xFF] * 4, [0xFF, cr0, cr1, 0x00], [0xFF, *regs]])
    d = Max31856(_stream(), transport=spi, clock=VirtualTime())
    d.open()
    block = d.read()
    assert spi.mode == 1
    assert spi.sent[0] == [0x80, cr0, cr1, 0x00]
    assert spi.sent[1] == [0x00, 0, 0, 0]
    assert spi.sent[2] == [0x0A, 0, 0, 0, 0, 0, 0]
    assert block.raw.tolist() == [[250.5, 23.25]]
    assert block.status is None


def test_a_chip_that_does_not_echo_its_configuration_is_not_found() -> None:
    spi = FakeSpiDev([[0xFF] * 4, [0xFF] * 4])  # nothing on MISO
    d = Max31856(_stream(), transport=spi, clock=VirtualTime())
    with pytest.raises(DeviceNotFound, match=r"no MAX31856 answering"):
        d.open()
    assert spi.closed


def test_simulated_chip_in_continuous_mode_follows_the_weld_cycle() -> None:
    d = create_driver(
        _stream(", sim: {seed: 2, peak_c: 400, layer_s: 10, cool_s: 10}"), VirtualTime()
    )
    d.open()
    temps = [d.read().raw[0, 0] for _ in range(80)]  # 20 s at 4 Hz
    assert max(temps[:40]) > 300
    assert temps[-1] < max(temps) - 100


def test_one_shot_mode_starts_a_conversion_and_waits_for_it() -> None:
    clock = VirtualTime()
    cfg = _stream(", conversion: one_shot, averaging: 2, sim: {seed: 4}", rate=2)
    d = create_driver(cfg, clock)
    d.open()
    block = d.read()
    assert block.status is None
    assert 20 < block.raw[0, 0] < 60
    assert 20 < block.raw[0, 1] < 35


def test_simulated_open_thermocouple_is_invalid_with_an_event() -> None:
    cfg = _stream(", sim: {seed: 5, faults: [{kind: open_circuit, at_s: 2, for_s: 2}]}")
    d = create_driver(cfg, VirtualTime())  # the table gives it the simulated chip
    d.open()
    blocks = [d.read() for _ in range(24)]
    bad = [i for i, b in enumerate(blocks) if b.status is not None]
    assert bad
    assert 8 <= bad[0] <= 9
    assert len(bad) in (8, 9)
    tags = [e.tag for b in blocks for e in b.events]
    assert tags == ["thermocouple_fault", "thermocouple_fault_cleared"]


def test_rate_faster_than_the_configured_conversion_is_refused() -> None:
    with pytest.raises(ConfigError, match=r"faster than a one_shot conversion with averaging 16"):
        _stream(", conversion: one_shot, averaging: 16", rate=2)
