"""Output drivers: PCF8574 and MCP4725 bytes against their datasheets (pure), every output driver
on its simulated transport (write, readback from the device, device errors), one T8 shared by a
stream and outputs, and the T8's hardware watchdog: set by the driver, it puts the outputs to
their safe values once nobody talks to the device, in virtual time."""

from __future__ import annotations

import errno
import json
from typing import Any

import pytest

from fleetdaq.contract.errors import DeviceDisconnected, DeviceError
from fleetdaq.contract.schema import OutputBase
from fleetdaq.edge.drivers.labjack_t8_out import T8DacDriver, T8DioDriver, T8Watchdog
from fleetdaq.edge.drivers.mcp4725 import (
    Mcp4725Driver,
    code_to_volts,
    decode_mcp4725,
    fast_write,
    volts_to_code,
    write_dac,
)
from fleetdaq.edge.drivers.pacing import VirtualTime
from fleetdaq.edge.drivers.pcf8574 import Pcf8574Driver, level_for, pin_level, port_with, value_of
from fleetdaq.edge.drivers.shared import SharedDevices
from fleetdaq.edge.drivers.sim_ljm import SimLJM
from fleetdaq.edge.drivers.sim_smbus import SimMcp4725, SimPcf8574, SimSmbus2
from fleetdaq.edge.drivers.table import create_driver, create_output
from fleetdaq.edge.drivers.weld_cell import WeldCell
from fleetdaq.edge.drivers.weld_robot import WeldRobotResume
from fleetdaq.hub.config.load import parse_config
from tests.drivers.fakes import DATA

MCP = json.loads((DATA / "mcp4725.json").read_text())
PCF = json.loads((DATA / "pcf8574.json").read_text())


def _node(outputs: str, streams: str = "s: {driver: wave_sim, rate_hz: 10, channels: [{name: x}]}"):  # type: ignore[no-untyped-def]
    text = f"site: s\nnodes:\n  n:\n    streams: {{{streams}}}\n    outputs: {{{outputs}}}\n"
    return parse_config(text, "t").nodes["n"]


def _output(text: str) -> OutputBase:
    return next(iter(_node(f"o: {text}").outputs.values()))


# --- PCF8574 (pure) -----------------------------------------------------------------------------


@pytest.mark.parametrize("row", PCF["set_pin"], ids=lambda r: f"{r['port']}-P{r['pin']}")
def test_pcf8574_one_pin_changes_one_bit_of_the_port_byte(row: dict[str, Any]) -> None:
    port = int(row["port"], 16)
    after = port_with(port, row["pin"], row["level"])
    assert after == int(row["then"], 16)
    assert pin_level(after, row["pin"]) is row["level"]


@pytest.mark.parametrize("row", PCF["relay_board"], ids=str)
def test_pcf8574_invert_drives_active_low_relay_boards(row: dict[str, Any]) -> None:
    assert level_for(row["value"], row["invert"]) is row["pin_high"]
    assert value_of(row["pin_high"], row["invert"]) == row["value"]


# --- MCP4725 (pure) -----------------------------------------------------------------------------


@pytest.mark.parametrize("row", MCP["fast_write"], ids=lambda r: r["hex"])
def test_mcp4725_fast_write_bytes_follow_figure_6_1(row: dict[str, Any]) -> None:
    assert fast_write(row["code"], row["power_down"]).hex() == row["hex"]


@pytest.mark.parametrize("row", MCP["write_dac"], ids=lambda r: r["hex"])
def test_mcp4725_write_dac_register_and_eeprom_bytes_follow_figure_6_2(row: dict[str, Any]) -> None:
    assert write_dac(row["code"], row["eeprom"], row["power_down"]).hex() == row["hex"]


@pytest.mark.parametrize("row", MCP["read"], ids=lambda r: r["hex"])
def test_mcp4725_the_five_byte_read_decodes_per_figure_6_3(row: dict[str, Any]) -> None:
    status = decode_mcp4725(bytes.fromhex(row["hex"]))
    for key in ("ready", "por", "power_down", "code", "eeprom_power_down", "eeprom_code"):
        assert getattr(status, key) == row[key], key


@pytest.mark.parametrize("row", MCP["volts"], ids=lambda r: f"{r['volts']}V")
def test_mcp4725_volts_and_codes_follow_equation_4_1(row: dict[str, Any]) -> None:
    assert volts_to_code(row["volts"], row["vref"]) == row["code"]
    assert code_to_volts(row["code"], row["vref"]) == pytest.approx(
        row["volts"], abs=row["vref"] / 4096
    )


def test_mcp4725_refuses_a_read_of_the_wrong_length_and_codes_out_of_range() -> None:
    with pytest.raises(ValueError, match=r"5 bytes, got 4"):
        decode_mcp4725(b"\x00" * 4)
    with pytest.raises(ValueError, match=r"out of range"):
        fast_write(4096)


# --- PCF8574 driver on the simulated chip --------------------------------------------------------


def _pcf(extra: str = "", pins: tuple[tuple[int, float, bool], ...] = ((3, 0, True),)):
    """Drivers for pins of one simulated PCF8574 at 0x20, and the chip."""
    clock, shared = VirtualTime(), SharedDevices()
    drivers = []
    for pin, initial, invert in pins:
        cfg = _output(
            f"{{driver: pcf8574, address: 0x20, pin: {pin}, safe: 0, initial: {initial}, "
            f"invert: {str(invert).lower()}, sim: {{{extra}}}}}"
        )
        drivers.append(create_output(cfg, clock, shared))
    bus = shared.find(("sim_smbus",), SimSmbus2)
    assert bus is not None
    chip = bus.buses[1][0x20]
    assert isinstance(chip, SimPcf8574)
    return drivers, chip


def test_pcf8574_first_write_sets_every_pin_at_its_initial_level_in_one_byte() -> None:
    (a, b), chip = _pcf(pins=((3, 1, True), (5, 1, False)))
    assert isinstance(a, Pcf8574Driver)
    a.open()
    a.write(1)  # active-low relay on: P3 LOW; P5 (active-high, initial 1) HIGH from the start
    assert chip.writes == 1
    assert chip.latch == 0xF7
    assert (a.read(), b.read()) == (1.0, 1.0)
    b.write(0)
    assert chip.latch == 0xD7  # only P5 changed
    assert (a.read(), b.read()) == (1.0, 0.0)


def test_pcf8574_reads_back_the_pin_level_not_what_was_written() -> None:
    (d,), chip = _pcf("stuck_low: 0x08", pins=((3, 0, False),))
    d.open()
    d.write(1)
    assert chip.latch & 0x08
    assert d.read() == 0.0  # held low outside the chip (8.3): the readback says so


def test_pcf8574_nack_is_a_device_error_keeping_errno_and_text() -> None:
    (d,), _ = _pcf("faults: [{kind: nack, at_s: 0}]")
    d.open()
    with pytest.raises(
        DeviceError, match=r"PCF8574 0x20 on /dev/i2c-1: write: .*Remote I/O"
    ) as err:
        d.write(1)
    assert err.value.code == errno.EREMOTEIO


# --- MCP4725 driver on the simulated chip --------------------------------------------------------


def _mcp(extra: str = "", safe: float = 1.0) -> tuple[Mcp4725Driver, SimMcp4725, VirtualTime]:
    clock, shared = VirtualTime(), SharedDevices()
    cfg = _output(
        f"{{driver: mcp4725, address: 0x61, min: 0, max: 3, safe: {safe}, vref: 3.3, "
        f"sim: {{{extra}}}}}"
    )
    driver = create_output(cfg, clock, shared)
    assert isinstance(driver, Mcp4725Driver)
    bus = shared.find(("sim_smbus",), SimSmbus2)
    assert bus is not None
    chip = bus.buses[1][0x61]
    assert isinstance(chip, SimMcp4725)
    return driver, chip, clock


def test_mcp4725_writes_with_fast_mode_and_reads_the_dac_register_back() -> None:
    d, chip, _ = _mcp()
    d.open()
    d.write(2.0)
    assert chip.code == volts_to_code(2.0, 3.3)
    assert d.read() == pytest.approx(2.0, abs=3.3 / 4096)
    assert chip.volts(3.3) == pytest.approx(2.0, abs=3.3 / 4096)


def test_mcp4725_keeps_the_safe_value_in_its_eeprom_written_only_when_it_differs() -> None:
    d, chip, _ = _mcp("eeprom_code: 4000", safe=1.0)
    d.open()  # the EEPROM held 4000: rewritten to the safe code, waiting for RDY/BSY
    assert (chip.eeprom_code, chip.eeprom_writes) == (volts_to_code(1.0, 3.3), 1)
    d.write(2.5)  # accepted: the driver waited until the EEPROM write was done
    assert chip.ignored == 0
    assert d.read() == pytest.approx(2.5, abs=3.3 / 4096)
    d.close()
    d.open()
    assert chip.eeprom_writes == 1  # the same value: not written again (EEPROM endurance)


def test_mcp4725_nack_is_a_device_error() -> None:
    d, _, _ = _mcp("faults: [{kind: nack, at_s: 0}]")
    with pytest.raises(DeviceError, match=r"MCP4725 0x61 on /dev/i2c-1: read: .*Remote I/O"):
        d.open()


# --- LabJack T8 outputs ----------------------------------------------------------------------


def _t8(sim: str = "{seed: 3}", outputs: str = ""):  # type: ignore[no-untyped-def]
    node = _node(
        outputs
        or (
            f"dac: {{driver: labjack_t8_dac, dac: 0, min: 0, max: 5, safe: 1.0, sim: {sim}}}, "
            f"pump: {{driver: labjack_t8_dio, line: FIO2, safe: 0, sim: {sim}}}, "
            f"vent: {{driver: labjack_t8_dio, line: EIO1, safe: 1, sim: {sim}}}"
        ),
        streams=f"t8: {{driver: labjack_t8, rate_hz: 1000, sim: {sim}, channels: [{{name: a}}]}}",
    )
    clock, shared = VirtualTime(), SharedDevices()
    stream = create_driver(node.streams["t8"], clock, shared)
    outs = {name: create_output(cfg, clock, shared) for name, cfg in node.outputs.items()}
    ljm = shared.find(("sim_t8", "ANY"), SimLJM)
    assert ljm is not None
    return stream, outs, ljm, clock


def test_t8_dac_and_dio_read_back_from_the_device_the_stream_shares_it() -> None:
    stream, outs, ljm, _ = _t8()
    dac, pump = outs["dac"], outs["pump"]
    assert isinstance(dac, T8DacDriver)
    assert isinstance(pump, T8DioDriver)
    stream.open()
    dac.open()
    pump.open()
    assert ljm.opens == 1  # LJM hands the open device's handle to the outputs
    dac.write(2.5)
    pump.write(1)
    assert (dac.read(), pump.read()) == (2.5, 1.0)
    assert ljm.device.registers["DAC0"] == 2.5
    assert stream.read().raw.shape == (100, 1)  # the stream runs on, on the same T8
    stream.close()  # closes the shared handle...
    dac.write(3.0)  # ...and the outputs reopen it
    assert dac.read() == 3.0


def test_t8_output_on_an_unplugged_device_is_device_disconnected() -> None:
    _, outs, _, clock = _t8("{seed: 4, faults: [{kind: unplug, at_s: 1, for_s: 5}]}")
    dac = outs["dac"]
    dac.open()
    dac.write(2.0)
    clock.advance(1_500_000_000)
    with pytest.raises(DeviceDisconnected, match=r"LJM error 1226 DEVICE_DISCONNECTED"):
        dac.write(2.5)


def test_t8_hardware_watchdog_sets_the_safe_values_once_nobody_talks_to_the_device() -> None:
    stream, outs, ljm, clock = _t8()
    dog = outs["dac"].hardware_watchdog()  # type: ignore[attr-defined]
    assert isinstance(dog, T8Watchdog)
    assert outs["pump"].hardware_watchdog() is dog  # type: ignore[attr-defined]
    for out in outs.values():
        out.open()
    assert "3 s" in dog.arm(2.2)  # whole seconds, rounded up
    r = ljm.device.watchdog.registers
    assert r["WATCHDOG_ENABLE_DEFAULT"] == 1.0
    assert r["WATCHDOG_TIMEOUT_S_DEFAULT"] == 3.0
    assert (r["WATCHDOG_DAC0_ENABLE_DEFAULT"], r["WATCHDOG_DAC0_DEFAULT"]) == (1.0, 1.0)
    assert r["WATCHDOG_DAC1_ENABLE_DEFAULT"] == 0.0
    mask = 1 << 2 | 1 << 9  # FIO2 = DIO2, EIO1 = DIO9
    assert int(r["WATCHDOG_DIO_DIRECTION_DEFAULT"]) == mask
    assert int(r["WATCHDOG_DIO_INHIBIT_DEFAULT"]) & mask == 0
    assert int(r["WATCHDOG_DIO_STATE_DEFAULT"]) == 1 << 9
    writes = ljm.device.watchdog.flash_writes
    assert "already set" in dog.arm(2.2)
    assert ljm.device.watchdog.flash_writes == writes  # nothing rewritten: flash wear

    outs["dac"].write(4.0)
    outs["pump"].write(1)
    outs["vent"].write(0)
    ljm.eWriteName(ljm.openS("T8"), "FIO5", 1)  # a line no output owns
    for _ in range(5):  # the edge polls its readbacks: the timer never runs out
        clock.advance(2_000_000_000)
        dog.feed()
    ljm.device.check_watchdog()
    assert ljm.device.registers["DAC0"] == 4.0
    stream.open()
    for _ in range(40):  # 4 s of stream data only: it does not feed the watchdog
        stream.read()
    ljm.device.check_watchdog()  # looks at the device without talking to it
    dev = ljm.device
    assert dev.registers["DAC0"] == 1.0
    assert (dev.dio_out[2], dev.dio_out[9]) == (0, 1)
    assert dev.dio_out[5] == 1  # not one of the watchdog's lines: untouched
    assert dev.watchdog.trips == 1


def test_t8_watchdog_settings_change_when_a_safe_value_does() -> None:
    _, outs, ljm, _ = _t8()
    dog = outs["dac"].hardware_watchdog()  # type: ignore[attr-defined]
    outs["dac"].open()
    dog.arm(3)
    dog.register_dac(0, 2.0)
    dog.arm(3)  # disables, rewrites, enables again (the device refuses changes while enabled)
    assert ljm.device.watchdog.registers["WATCHDOG_DAC0_DEFAULT"] == 2.0
    assert ljm.device.watchdog.enabled


# --- the weld robot's resume input ---------------------------------------------------------------


def test_weld_robot_resume_output_writes_and_reads_the_robots_input() -> None:
    node = parse_config(
        "site: s\nnodes:\n  n:\n    streams:\n      r: {driver: weld_robot_sim, rate_hz: 4, "
        "cell: w, channels: [{name: layer}]}\n    outputs:\n"
        "      resume: {driver: weld_robot_resume, cell: w, safe: 0}\n",
        "t",
    ).nodes["n"]
    clock, shared = VirtualTime(), SharedDevices()
    create_driver(node.streams["r"], clock, shared)
    out = create_output(node.outputs["resume"], clock, shared)
    assert isinstance(out, WeldRobotResume)
    cell = shared.find(("weld_cell", "w"), WeldCell)
    assert cell is not None
    out.write(1)
    assert cell.resume_level
    assert out.read() == 1.0
