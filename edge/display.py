"""Displays on an edge node: character LCDs showing live values (e.g. a weld cell's substrate
temperature next to the cell, as the seed's testbed showed its pyrometer).

A node's `displays:` config names each display's lines; a line is text with placeholders
``{stream.channel}`` or ``{stream.channel:.1f}`` (a Python format spec). `create_displays`
returns one `DisplayLoop` per display: a thread that renders the lines from
``latest(stream, channel)`` at `refresh_hz` and sends changed rows to the LCD. A display is a
sink: when its bus fails it retries a bounded number of times per refresh, then raises an
event, keeps trying at the refresh rate, and raises another event when it works again; it
never touches acquisition. ``{{`` and ``}}`` are literal braces; a value that is missing or
not finite shows as dashes.
"""

from __future__ import annotations

import logging
import math
import re
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from edge.drivers.hd44780 import Hd44780Pcf8574
from edge.drivers.i2cbus import load_smbus2, open_bus
from edge.drivers.pacing import SYSTEM_CLOCK, Clock
from edge.errors import DriverError

if TYPE_CHECKING:
    from edge.config import LcdDisplay, NodeConfig

log = logging.getLogger("fleetdaq.display")

Latest = Callable[[str, str], float | None]
"""latest(stream, channel): the newest engineering value, None when there is none yet."""
Emit = Callable[[int, str, str], None]
"""emit(level, tag, message): raise an event."""

_FIELD = re.compile(r"\{\{|\}\}|\{([^{}]*)\}|[{}]")
_REF = re.compile(r"^([a-z][a-z0-9_-]{0,62})\.([A-Za-z][A-Za-z0-9_.-]{0,62})$")


@dataclass(frozen=True, slots=True)
class Field:
    stream: str
    channel: str
    spec: str


@dataclass(frozen=True, slots=True)
class Line:
    """A parsed display line: literal text and fields."""

    parts: tuple[str | Field, ...]

    @property
    def references(self) -> list[tuple[str, str]]:
        return [(p.stream, p.channel) for p in self.parts if isinstance(p, Field)]

    def render(self, latest: Latest) -> str:
        out: list[str] = []
        for part in self.parts:
            if isinstance(part, str):
                out.append(part)
                continue
            value = latest(part.stream, part.channel)
            if value is None or not math.isfinite(value):
                width = len(format(0.0, part.spec)) if part.spec else 4
                out.append("-" * max(width, 2))
            else:
                out.append(format(value, part.spec))
        return "".join(out)


def parse_line(text: str) -> Line:
    """Parse a display line. Raises ValueError naming what is wrong."""
    parts: list[str | Field] = []
    pos = 0
    for m in _FIELD.finditer(text):
        parts.append(text[pos : m.start()])
        pos = m.end()
        token = m.group(0)
        if token in ("{{", "}}"):
            parts.append(token[0])
            continue
        if m.group(1) is None:
            raise ValueError(f"unmatched {token!r} at column {m.start() + 1} (use {token * 2})")
        body = m.group(1)
        ref, _, spec = body.partition(":")
        ref_m = _REF.match(ref.strip())
        if ref_m is None:
            raise ValueError(f"{{{body}}}: expected {{stream.channel}} or {{stream.channel:spec}}")
        try:
            format(1.5, spec)
        except ValueError as err:
            raise ValueError(f"{{{body}}}: bad format spec {spec!r}: {err}") from None
        parts.append(Field(ref_m.group(1), ref_m.group(2), spec))
    parts.append(text[pos:])
    return Line(tuple(p for p in parts if p != ""))


class DisplayLoop:
    """Keeps one LCD showing its lines; `start()` and `close()` (idempotent)."""

    def __init__(
        self,
        name: str,
        cfg: LcdDisplay,
        latest: Latest,
        emit: Emit,
        smbus: Any | None = None,
        clock: Clock = SYSTEM_CLOCK,
        sleep: Callable[[float], None] = time.sleep,
    ) -> None:
        self.name = name
        self.cfg = cfg
        self.latest = latest
        self.emit = emit
        self.clock = clock
        self._sleep = sleep
        self.sim_lcd: Any = None
        """The simulated LCD when the config has `sim:` (tests read what it shows)."""
        if smbus is None:
            if cfg.sim is not None:
                from edge.drivers.sim_smbus import SimLcd, SimSmbus2

                smbus = SimSmbus2(clock)
                self.sim_lcd = SimLcd(cfg.sim, clock, cfg.cols, cfg.rows)
                smbus.attach(cfg.bus, cfg.address, self.sim_lcd)
                self._sleep = lambda s: None
            else:
                smbus = load_smbus2("LCD display")
        self.smbus = smbus
        self.lines = [parse_line(text) for text in cfg.lines]
        self.where = f"display {name} (LCD at 0x{cfg.address:02X} on /dev/i2c-{cfg.bus})"
        self._bus: Any = None
        self._lcd: Hd44780Pcf8574 | None = None
        self._failing: str | None = None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name=f"display-{name}", daemon=True)
        self.refreshes = 0
        self.failures = 0

    def start(self) -> None:
        self._thread.start()

    def close(self) -> None:
        self._stop.set()
        if self._thread.is_alive() and self._thread is not threading.current_thread():
            self._thread.join(5.0)
        self._disconnect()

    def refresh(self) -> bool:
        """Render and show the lines once (with bounded retries). True if the LCD took them."""
        text = [line.render(self.latest) for line in self.lines]
        problem = ""
        for _attempt in range(self.cfg.retries + 1):
            try:
                if self._lcd is None:
                    self._connect()
                assert self._lcd is not None
                self._lcd.write_lines(text)
            except (OSError, DriverError) as err:
                problem = str(err)
                self._disconnect()
                continue
            self.refreshes += 1
            if self._failing is not None:
                self.emit(logging.INFO, "display_ok", f"{self.where}: showing values again")
                self._failing = None
            return True
        self.failures += 1
        if self._failing is None:
            self.emit(
                logging.WARNING,
                "display_error",
                f"{self.where}: {problem} after {self.cfg.retries + 1} attempt(s); retrying",
            )
            self._failing = problem
        return False

    def _run(self) -> None:
        period_ns = round(1e9 / self.cfg.refresh_hz)
        due = self.clock.monotonic_ns()
        while not self._stop.is_set():
            self.refresh()
            due += period_ns
            if not self.clock.sleep_until(due, self._stop):
                break

    def _connect(self) -> None:
        self._bus = open_bus(self.smbus, self.cfg.bus)
        lcd = Hd44780Pcf8574(
            self._bus,
            self.cfg.address,
            self.cfg.cols,
            self.cfg.rows,
            self.cfg.backlight,
            self._sleep,
        )
        lcd.init()
        self._lcd = lcd

    def _disconnect(self) -> None:
        bus, self._bus, self._lcd = self._bus, None, None
        if bus is not None:
            try:
                bus.close()
            except OSError as err:
                log.debug("closing %s: %s", self.where, err)


def create_displays(node_cfg: NodeConfig, latest: Latest, emit: Emit) -> list[DisplayLoop]:
    """One DisplayLoop per display of the node (not started).

    Raises:
        DriverUnavailable: a real (not simulated) display needs smbus2 and it is missing.
    """
    return [DisplayLoop(name, cfg, latest, emit) for name, cfg in node_cfg.displays.items()]
