"""MAX31855: the pure decoder against the datasheet's tables; the driver through a fake SpiDev
(datasheet frames, faults) and through the simulated chip in virtual time."""

from __future__ import annotations

import importlib.util
import json
import logging

import numpy as np
import pytest

from fleetdaq.contract.errors import DeviceNotFound, DriverUnavailable
from fleetdaq.contract.wire import SampleStatus
from fleetdaq.edge.drivers.max31855 import (
    Max31855,
    Max31855Stream,
    decode_max31855,
    encode_max31855,
)
from fleetdaq.edge.drivers.pacing import VirtualTime
from fleetdaq.edge.drivers.table import create_driver
from fleetdaq.hub.config.load import parse_config
from tests.drivers.fakes import DATA, FakeSpiDev

TABLE = json.loads((DATA / "max31855.json").read_text())


def _stream(extra: str = "", rate: float = 4, channels: int = 2) -> Max31855Stream:
    chans = ", ".join(f"{{name: c{i}, unit: degC}}" for i in range(channels))
    text = (
        "site: s\nnodes:\n  n:\n    streams:\n      tc: {driver: max31855, "
        f"rate_hz: {rate}, channels: [{chans}]{extra}}}\n"
    )
    cfg = parse_config(text, "t").nodes["n"].streams["tc"]
    assert isinstance(cfg, Max31855Stream)
    return cfg


def _bits(text: str) -> int:
    return int(text.replace(" ", ""), 2)


@pytest.mark.parametrize("row", TABLE["thermocouple"], ids=lambda r: f"{r['celsius']}C")
def test_thermocouple_temperatures_decode_as_in_the_datasheet_table(row: dict) -> None:
    frame = (_bits(row["bits"]) << 18).to_bytes(4, "big")
    assert decode_max31855(frame).thermocouple_c == row["celsius"]


@pytest.mark.parametrize("row", TABLE["cold_junction"], ids=lambda r: f"{r['celsius']}C")
def test_cold_junction_temperatures_decode_as_in_the_datasheet_table(row: dict) -> None:
    frame = (_bits(row["bits"]) << 4).to_bytes(4, "big")
    assert decode_max31855(frame).cold_junction_c == row["celsius"]


@pytest.mark.parametrize("row", TABLE["frames"], ids=lambda r: r["hex"])
def test_whole_frames_decode_with_their_fault_bits(row: dict) -> None:
    r = decode_max31855(bytes.fromhex(row["hex"]))
    assert (r.thermocouple_c, r.cold_junction_c) == (row["tc"], row["cj"])
    assert r.status == getattr(SampleStatus, row["status"].upper())
    assert r.fault == (row["status"] != "valid")


@pytest.mark.parametrize("row", TABLE["bad_frames"], ids=lambda r: r["hex"])
def test_frames_the_chip_cannot_send_are_refused(row: dict) -> None:
    with pytest.raises(ValueError, match=r"frame"):
        decode_max31855(bytes.fromhex(row["hex"]))


def test_encoder_is_the_decoders_inverse_over_the_whole_range() -> None:
    for tc in np.arange(-270, 1800, 0.25)[::37]:
        for cj in (-55.0, -0.0625, 0.0, 24.5, 127.0):
            r = decode_max31855(encode_max31855(float(tc), cj))
            assert (r.thermocouple_c, r.cold_junction_c) == (tc, cj)


def test_driver_opens_spi_mode_0_and_decodes_each_poll_in_virtual_time() -> None:
    frames = [list(bytes.fromhex(r["hex"])) for r in TABLE["frames"][:1]] * 4
    spi = FakeSpiDev(frames)
    cfg = _stream(", bus: 0, device: 1, max_speed_hz: 2000000", rate=4)
    clock = VirtualTime()
    d = Max31855(cfg, transport=spi, clock=clock)
    d.open()
    t0 = clock.monotonic_ns()
    blocks = [d.read() for _ in range(4)]
    assert spi.opened == (0, 1)
    assert spi.mode == 0
    assert spi.max_speed_hz == 2_000_000
    assert all(sent == [0, 0, 0, 0] for sent in spi.sent)
    assert [b.raw.tolist() for b in blocks] == [[[25.0, 25.0]]] * 4
    assert all(b.status is None for b in blocks)
    assert clock.monotonic_ns() - t0 == 750_000_000  # polls at 0, 250, 500, 750 ms
    d.close()
    assert spi.closed


def test_open_thermocouple_makes_the_sample_invalid_with_one_event_and_recovers() -> None:
    ok = list(bytes.fromhex("01901900"))
    oc = list(bytes.fromhex("00011911"))
    spi = FakeSpiDev([ok, oc, oc, oc, ok])
    d = Max31855(_stream(), transport=spi, clock=VirtualTime())
    d.open()
    blocks = [d.read() for _ in range(5)]
    statuses = [None if b.status is None else b.status.tolist() for b in blocks]
    assert statuses == [None, [[2, 0]], [[2, 0]], [[2, 0]], None]  # cold junction stays valid
    tags = [e.tag for b in blocks for e in b.events]
    assert tags == ["thermocouple_fault", "thermocouple_fault_cleared"]
    assert "open (OC)" in blocks[1].events[0].message
    assert blocks[1].events[0].level == logging.WARNING
    assert d.health()["faulty_polls"] == 3


def test_a_floating_bus_is_a_comm_error_on_both_channels_not_a_crash() -> None:
    spi = FakeSpiDev([[0xFF] * 4, OSError(5, "Input/output error")])
    d = Max31855(_stream(), transport=spi, clock=VirtualTime())
    d.open()
    first, second = d.read(), d.read()
    assert first.status is not None
    assert first.status.tolist() == [[5, 5]]
    assert second.status is not None
    assert second.status.tolist() == [[5, 5]]
    assert [e.tag for e in first.events] == ["thermocouple_fault"]
    assert "reserved bits" in first.events[0].message
    assert "SPI transfer failed" in second.events[0].message


def test_missing_spi_device_is_device_not_found_keeping_the_errno() -> None:
    spi = FakeSpiDev(open_error=FileNotFoundError(2, "No such file or directory"))
    d = Max31855(_stream(), transport=spi, clock=VirtualTime())
    with pytest.raises(DeviceNotFound, match=r"/dev/spidev0\.0 not found: enable SPI") as err:
        d.open()
    assert err.value.code == 2
    assert isinstance(err.value.__cause__, FileNotFoundError)


def test_without_spidev_installed_the_driver_is_unavailable_in_one_line() -> None:
    if importlib.util.find_spec("spidev") is not None:
        pytest.skip("spidev is installed here")
    with pytest.raises(
        DriverUnavailable, match=r"needs spidev: `pip install fleetdaq\[pi\]`"
    ) as err:
        Max31855(_stream())
    assert "\n" not in str(err.value)


def test_rates_above_the_chips_conversion_rate_are_refused_by_config() -> None:
    with pytest.raises(Exception, match=r"rate_hz: must be at most 10"):
        _stream(rate=12)


def test_simulated_chip_heats_during_a_weld_layer_and_cools_between_layers() -> None:
    cfg = _stream(", sim: {ambient_c: 24, peak_c: 450, layer_s: 20, cool_s: 15, seed: 3}")
    d = create_driver(cfg, VirtualTime())  # the table gives it the simulated chip
    d.open()
    temps = np.array([d.read().raw[0, 0] for _ in range(4 * 35)])  # one layer cycle at 4 Hz
    assert np.all(np.abs(temps * 4 - np.round(temps * 4)) < 1e-9)  # 0.25 °C steps
    heating, cooling = temps[: 4 * 20], temps[4 * 20 :]
    assert heating[-1] > 400
    assert heating[-1] > heating[0] + 300
    assert cooling[-1] < heating[-1] - 200
    assert np.mean(np.diff(heating)) > 0 > np.mean(np.diff(cooling))


def test_simulated_faults_from_config_reach_the_samples() -> None:
    cfg = _stream(", sim: {seed: 1, faults: [{kind: open_circuit, at_s: 1, for_s: 1}]}")
    d = create_driver(cfg, VirtualTime())  # the table gives it the simulated chip
    d.open()
    blocks = [d.read() for _ in range(16)]
    bad = [i for i, b in enumerate(blocks) if b.status is not None]
    assert bad == [4, 5, 6, 7]  # polls at 1.00 .. 1.75 s
    assert {int(blocks[i].status[0, 0]) for i in bad} == {SampleStatus.OPEN_CIRCUIT}  # type: ignore[index]
