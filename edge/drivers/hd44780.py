"""HD44780 character LCD behind a PCF8574 I2C backpack (smbus2): the LCD of `edge.display`.

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
from typing import Any

RS, E, BACKLIGHT = 0x01, 0x04, 0x08
ROW_OFFSETS = (0x00, 0x40, 0x14, 0x54)
CLEAR, ENTRY_MODE, DISPLAY_ON, FUNCTION_SET_4BIT_2LINE, SET_DDRAM = 0x01, 0x06, 0x0C, 0x28, 0x80
DEGREE = 0xDF
"""'°' in the HD44780's A00 character ROM."""


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
        bus: Any,
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
