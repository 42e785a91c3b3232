"""The LCD display: line templates, the HD44780 + PCF8574 byte protocol through the simulated
backpack (which decodes nibbles the way the LCD does), NACK handling and the display loop."""

from __future__ import annotations

import logging

import pytest

from fleetdaq.contract.errors import ConfigError
from fleetdaq.edge.display import DisplayLoop, create_displays, parse_line
from fleetdaq.edge.drivers.hd44780 import Hd44780Pcf8574, LcdDisplay, lcd_bytes
from fleetdaq.edge.drivers.pacing import VirtualTime
from fleetdaq.edge.drivers.sim_smbus import SimLcd, SimSmbus2, lcd_transport
from fleetdaq.hub.config.load import parse_config

NODE = """\
site: s
nodes:
  am-cell:
    streams:
      tc: {{driver: max31855, rate_hz: 4, sim: {{}}, channels: [{{name: substrate}}, {{name: cj}}]}}
    displays:
      lcd:
        sim: {sim}
        retries: 1
        lines: {lines}
"""


def _node(lines: str = '["TC {tc.substrate:6.1f}\\u00b0C"]', sim: str = "{}") -> tuple:
    site = parse_config(NODE.format(lines=lines, sim=sim), "site.yaml")
    node = site.nodes["am-cell"]
    return node, node.displays["lcd"]


class Values:
    def __init__(self) -> None:
        self.values: dict[tuple[str, str], float] = {}

    def __call__(self, stream: str, channel: str) -> float | None:
        return self.values.get((stream, channel))


class Events:
    def __init__(self) -> None:
        self.seen: list[tuple[int, str, str]] = []

    def __call__(self, level: int, tag: str, message: str) -> None:
        self.seen.append((level, tag, message))


def test_a_line_renders_fields_with_their_format_spec_and_literal_braces() -> None:
    line = parse_line("{{x}} {tc.substrate:.1f} C {tc.cj}")
    assert line.references == [("tc", "substrate"), ("tc", "cj")]
    values = {("tc", "substrate"): 412.349, ("tc", "cj"): 25.0625}
    assert line.render(lambda s, c: values[(s, c)]) == "{x} 412.3 C 25.0625"


def test_missing_or_invalid_values_show_as_dashes() -> None:
    line = parse_line("T {tc.substrate:6.1f}|{tc.cj}")
    assert line.render(lambda s, c: None) == "T ------|----"
    assert line.render(lambda s, c: float("nan")) == "T ------|----"


@pytest.mark.parametrize(
    ("text", "problem"),
    [
        ("{tc}", "expected {stream.channel}"),
        ("{tc.x:q}", "bad format spec"),
        ("a } b", "unmatched"),
    ],
)
def test_bad_lines_are_refused_naming_the_problem(text: str, problem: str) -> None:
    with pytest.raises(ValueError, match=problem):
        parse_line(text)


def test_a_display_naming_an_unknown_channel_fails_the_config_in_one_line() -> None:
    with pytest.raises(ConfigError) as err:
        _node(lines='["{tc.nope}"]')
    message = str(err.value)
    assert "\n" not in message
    assert message == (
        "site.yaml: nodes.am-cell.displays.lcd.lines[0]: stream 'tc' has no channel 'nope'"
    )


def test_more_lines_than_rows_are_refused() -> None:
    with pytest.raises(ConfigError, match=r"3 lines for a display of 2 row\(s\)"):
        _node(lines='["a", "b", "c"]')


def test_lcd_bytes_map_the_degree_sign_to_the_rom_and_pad_to_the_width() -> None:
    assert lcd_bytes("25.0°C", 8) == b"25.0\xdfC  "
    assert lcd_bytes("äbcdefghijk", 4) == b"?bcd"


def test_the_4_bit_start_up_and_text_reach_the_lcd_as_the_hd44780_decodes_them() -> None:
    clock = VirtualTime()
    lcd = SimLcd(None, clock)
    bus = SimSmbus2(clock)
    bus.attach(1, 0x27, lcd)
    driver = Hd44780Pcf8574(bus.SMBus(1), 0x27)
    driver.init()
    driver.write_lines(["Hello", "world 25.0°C"])
    assert lcd.four_bit
    assert lcd.display_on
    assert lcd.backlight
    assert lcd.lines() == ["Hello           ", "world 25.0°C    "]
    before = lcd.instructions
    driver.write_lines(["Hello", "world 25.5°C"])  # only the changed row goes out
    assert lcd.lines()[1] == "world 25.5°C    "
    assert lcd.instructions - before == 1 + 16


def _sim_loop(cfg, values, events, clock):  # type: ignore[no-untyped-def]
    """A display loop on the simulated LCD the driver table would give it."""
    bus = lcd_transport(cfg, clock)
    loop = DisplayLoop("lcd", cfg, values, events, bus, clock=clock, sleep=lambda s: None)
    return loop, bus.buses[cfg.bus][cfg.address]


def test_the_display_loop_shows_live_values_from_latest() -> None:
    _, cfg = _node(lines='["TC {tc.substrate:6.1f}\\u00b0C", "CJ {tc.cj:.2f}"]')
    values, events = Values(), Events()
    display, lcd = _sim_loop(cfg, values, events, VirtualTime())
    assert display.refresh()
    assert lcd.lines() == ["TC ------°C     ", "CJ ----         "]
    values.values.update({("tc", "substrate"): 431.25, ("tc", "cj"): 25.0625})
    assert display.refresh()
    assert lcd.lines() == ["TC  431.2°C     ", "CJ 25.06        "]
    assert events.seen == []


def test_nacks_are_retried_then_raise_one_event_and_recovery_raises_another() -> None:
    sim = "{faults: [{kind: nack, at_s: 1, for_s: 2}]}"
    _, cfg = _node(sim=sim)
    clock, values, events = VirtualTime(), Values(), Events()
    display, lcd = _sim_loop(cfg, values, events, clock)
    results = []
    for i in range(8):
        values.values[("tc", "substrate")] = 100.0 + i  # a new value: the row must go out
        results.append(display.refresh())
        clock.advance(500_000_000)
    assert results == [True, True, False, False, False, False, True, True]
    assert [(level, tag) for level, tag, _ in events.seen] == [
        (logging.WARNING, "display_error"),
        (logging.INFO, "display_ok"),
    ]
    assert "2 attempt(s)" in events.seen[0][2]
    assert lcd.lines()[0].startswith("TC")  # re-initialised after the outage


def test_create_displays_gives_loops_that_start_and_close() -> None:
    node, _ = _node()
    values, events = Values(), Events()
    values.values[("tc", "substrate")] = 99.0
    (display,) = create_displays(node, values, events)
    display.start()
    try:
        assert display.refreshed.wait(30), "the loop never refreshed the display"
    finally:
        display.close()
        display.close()  # idempotent
    lcd = display.smbus.buses[1][0x27]
    assert lcd.lines()[0] == "TC   99.0°C     "


def test_display_config_defaults_are_a_16x2_lcd_at_0x27_on_bus_1() -> None:
    cfg = LcdDisplay(lines=["x"])
    assert (cfg.bus, cfg.address, cfg.cols, cfg.rows, cfg.refresh_hz) == (1, 0x27, 16, 2, 2.0)
