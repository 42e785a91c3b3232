"""The serial barometer passes fleetdaq's driver conformance suite through its installed entry
point, and decodes the instrument's lines."""

from __future__ import annotations

import pytest
from fleetdaq_driver_example.barometer import (
    SerialBarometer,
    SerialBarometerStream,
    decode_line,
    encode_line,
)
from fleetdaq_driver_example.plugin import PLUGIN

from fleetdaq.contract.wire import SampleStatus
from fleetdaq.edge.drivers.conformance import DriverCase, DriverConformance, find_driver
from fleetdaq.edge.drivers.pacing import VirtualTime
from fleetdaq.edge.drivers.shared import SharedDevices

CONFIG = {
    "driver": "serial_barometer",
    "rate_hz": 2,
    "scans_per_batch": 2,
    "channels": [{"name": "p", "unit": "hPa"}],
    "port": "/dev/ttyUSB3",
    "sim": {"seed": 1},
}


class TestSerialBarometer(DriverConformance):
    case = DriverCase(
        CONFIG,
        faults=(
            {"kind": "no_response", "at_s": 3, "for_s": 2},
            {"kind": "garbled", "at_s": 3, "for_s": 1},
        ),
        unplug={"kind": "unplug", "at_s": 3, "for_s": 2},
        bad_configs=(
            ({"baudrate": 1234}, "baudrate"),
            ({"channels": [{"name": "p"}, {"name": "q"}]}, "channels"),
            ({"sim": {"pressure_hpa": 2000}}, "sim.pressure_hpa"),
            ({"sim": {"faults": [{"kind": "fire"}]}}, "sim.faults.0.kind"),
        ),
    )


def test_the_installed_entry_point_is_the_packages_plugin() -> None:
    found = find_driver("serial_barometer")
    assert found.schema is PLUGIN.schema is SerialBarometerStream


@pytest.mark.parametrize(
    ("line", "hpa"),
    [
        (b"P= 1013.25 hPa\r\n", 1013.25),
        (b"P=  998.40 hPa\r\n", 998.40),
        (b"P=1100.00 hPa\n", 1100.0),
    ],
)
def test_answer_lines_decode_to_hpa(line: bytes, hpa: float) -> None:
    assert decode_line(line) == hpa


@pytest.mark.parametrize(
    "line", [b"", b"P= 1#13.25 hPa\r\n", b"P= 1013.25 mbar\r\n", b"ERR\r\n", b"P= 1013 hPa\r\n"]
)
def test_lines_that_are_no_pressure_are_refused(line: bytes) -> None:
    with pytest.raises(ValueError, match="not a pressure line"):
        decode_line(line)


def test_the_encoder_is_the_decoders_inverse() -> None:
    for hpa in (500.0, 872.31, 1013.25, 1100.0):
        assert decode_line(encode_line(hpa)) == hpa


def test_a_silent_barometer_is_a_comm_error_after_the_ports_timeout() -> None:
    cfg = SerialBarometerStream.model_validate(
        {**CONFIG, "sim": {"faults": [{"kind": "no_response"}]}, "timeout_s": 0.25}
    )
    clock = VirtualTime()
    driver = find_driver("serial_barometer").create(cfg, clock, SharedDevices())
    assert isinstance(driver, SerialBarometer)
    driver.open()
    block = driver.read()
    driver.close()
    assert block.status is not None
    assert (block.status == SampleStatus.COMM_ERROR).all()
    assert [e.tag for e in block.events] == ["barometer_fault"]
    assert "no answer (within 0.25 s)" in block.events[0].message
