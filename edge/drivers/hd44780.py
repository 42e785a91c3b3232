"""HD44780 character LCD behind a PCF8574 I2C backpack (smbus2): the LCD of `fleetdaq.edge.display`.

The PCF8574's eight port bits drive the LCD in 4-bit mode (the common backpack wiring):
P0 = RS, P1 = R/W (kept low: write only), P2 = E, P3 = backlight, P4-P7 = D4-D7. Every byte
written to the PCF8574 sets the port; the HD44780 latches D4-D7 on E's falling edge, high
nibble first. Start-up (HD44780 datasheet, Figure 24, "Initializing by instruction", 4-bit):
0x3, 0x3, 0x3 as 8-bit function sets with 4.1 ms / 100 µs waits, then 0x2 (4-bit), then
function set 0x28 (2 lines, 5x8), display on 0x0C, clear 0x01 (1.52 ms), entry mode 0x06.
DDRAM rows start at 0x00, 0x40, 0x14, 0x54; set address = 0x80 | address.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Annotated, Literal

from pydantic import Field, model_validator

from fleetdaq.contract.display_text import parse_line
from fleetdaq.contract.drivers import DriverKind, DriverPlugin
from fleetdaq.contract.schema import Float, Int, Strict
from fleetdaq.edge.drivers.i2cbus import I2cBus, I2cFault

RS, E, BACKLIGHT = 0x01, 0x04, 0x08
ROW_OFFSETS = (0x00, 0x40, 0x14, 0x54)
CLEAR, ENTRY_MODE, DISPLAY_ON, FUNCTION_SET_4BIT_2LINE, SET_DDRAM = 0x01, 0x06, 0x0C, 0x28, 0x80
DEGREE = 0xDF
"""'°' in the HD44780's A00 character ROM."""


class LcdSim(Strict):
    """A simulated HD44780 + PCF8574 (edge/drivers/sim_smbus.py)."""

    faults: list[I2cFault] = []


class LcdDisplay(Strict):
    """An HD44780 character LCD behind a PCF8574 I2C backpack, showing live values.

    Each line is text with placeholders ``{stream.channel}`` or ``{stream.channel:.1f}`` (a
    Python format spec) naming a stream of this node and one of its channels."""

    driver: Literal["hd44780_pcf8574"] = "hd44780_pcf8574"
    bus: Annotated[Int, Field(ge=0, le=255)] = 1
    address: Annotated[Int, Field(ge=0x20, le=0x3F)] = 0x27
    """PCF8574: 0x20-0x27, PCF8574A: 0x38-0x3F (0x27 and 0x3F are the usual backpacks)."""
    cols: Literal[8, 16, 20] = 16
    rows: Literal[1, 2, 4] = 2
    refresh_hz: Annotated[Float, Field(gt=0, le=10)] = 2.0
    backlight: bool = True
    lines: Annotated[list[str], Field(min_length=1, max_length=4)]
    retries: Annotated[Int, Field(ge=0, le=10)] = 3
    sim: LcdSim | None = None

    @model_validator(mode="after")
    def _lines_fit(self) -> LcdDisplay:
        if len(self.lines) > self.rows:
            raise ValueError(f"{len(self.lines)} lines for a display of {self.rows} row(s)")
        for i, line in enumerate(self.lines):
            try:
                parse_line(line)
            except ValueError as err:
                raise ValueError(f"lines[{i}]: {err}") from None
        return self


def lcd_bytes(text: str, width: int) -> bytes:
    """`text` as HD44780 (ROM A00) codes, cut or padded to `width`; unknown characters: '?'."""
    out = bytearray()
    for ch in text[:width]:
        if ch == "°":
            out.append(DEGREE)
        elif " " <= ch <= "}":
            out.append(ord(ch))
        else:
            out.append(ord("?"))
    return bytes(out.ljust(width, b" "))


class Hd44780Pcf8574:
    """An HD44780 on a PCF8574 at `address` on an open SMBus (`write_byte` per port update).

    `write_lines` only sends rows that changed since the last call.
    """

    def __init__(
        self,
        bus: I2cBus,
        address: int,
        cols: int = 16,
        rows: int = 2,
        backlight: bool = True,
        sleep: Callable[[float], None] | None = None,
    ) -> None:
        self.bus = bus
        self.address = address
        self.cols = cols
        self.rows = rows
        self._light = BACKLIGHT if backlight else 0
        self._sleep = sleep or (lambda s: None)
        self._shown: list[bytes | None] = [None] * rows

    def init(self) -> None:
        """The 4-bit initialisation sequence; clears the screen."""
        self._sleep(0.05)  # > 40 ms after power rises
        for wait in (0.0045, 0.0045, 0.00015):
            self._nibble(0x3, rs=False)
            self._sleep(wait)
        self._nibble(0x2, rs=False)
        for command in (FUNCTION_SET_4BIT_2LINE, DISPLAY_ON, CLEAR, ENTRY_MODE):
            self.command(command)
        self._shown = [None] * self.rows

    def command(self, value: int) -> None:
        self._byte(value, rs=False)
        if value in (CLEAR, 0x02):
            self._sleep(0.002)  # clear / home: 1.52 ms

    def write_lines(self, lines: list[str]) -> None:
        for row in range(self.rows):
            data = lcd_bytes(lines[row] if row < len(lines) else "", self.cols)
            if self._shown[row] == data:
                continue
            self._shown[row] = None  # unknown until the whole row went out
            self.command(SET_DDRAM | ROW_OFFSETS[row])
            for b in data:
                self._byte(b, rs=True)
            self._shown[row] = data

    def _byte(self, value: int, rs: bool) -> None:
        self._nibble(value >> 4, rs)
        self._nibble(value & 0x0F, rs)

    def _nibble(self, nibble: int, rs: bool) -> None:
        port = (nibble & 0x0F) << 4 | self._light | (RS if rs else 0)
        self.bus.write_byte(self.address, port | E)
        self.bus.write_byte(self.address, port)  # E falls: the LCD latches D4-D7


PLUGIN = DriverPlugin(
    DriverKind.DISPLAY,
    LcdDisplay,
    Hd44780Pcf8574,
    "fleetdaq.edge.drivers.sim_smbus:lcd_transport",
)
