"""Displays on an edge node: character LCDs showing live values (e.g. a weld cell's substrate
temperature next to the cell, as the seed's testbed showed its pyrometer).

A node's `displays:` config names each display's lines; a line is text with placeholders
``{stream.channel}`` or ``{stream.channel:.1f}`` (a Python format spec). `create_displays`
returns one `DisplayLoop` per display: a thread that renders the lines from
``latest(stream, channel)`` at `refresh_hz` and sends changed rows to the LCD. A display is a
sink: when its bus fails it retries a bounded number of times per refresh, then raises an
event, keeps trying at the refresh rate, and raises another event when it works again; it
never touches acquisition. Line syntax: `fleetdaq.contract.display_text`.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from fleetdaq.contract.display_text import Latest, parse_line
from fleetdaq.contract.errors import DriverError
from fleetdaq.edge.drivers.hd44780 import Hd44780Pcf8574, LcdDisplay
from fleetdaq.edge.drivers.i2cbus import load_smbus2, open_bus
from fleetdaq.edge.drivers.pacing import SYSTEM_TIME, TimeSource
from fleetdaq.edge.drivers.table import display_sim, load_sim
from fleetdaq.runtime.threads import NamedThread

if TYPE_CHECKING:
    from fleetdaq.contract.config.node import NodeConfig

log = logging.getLogger("fleetdaq.display")

Emit = Callable[[int, str, str], None]
"""emit(level, tag, message): raise an event."""


class DisplayLoop:
    """Keeps one LCD showing its lines; `start()` and `close()` (idempotent)."""

    def __init__(
        self,
        name: str,
        cfg: LcdDisplay,
        latest: Latest,
        emit: Emit,
        transport: Any | None = None,
        clock: TimeSource = SYSTEM_TIME,
        sleep: Callable[[float], None] = time.sleep,
    ) -> None:
        """`transport` is an `smbus2`-like module (the simulated LCD's bus in sims, a fake in
        tests); default: smbus2 (imported now). `sleep` waits out the LCD's start-up delays."""
        self.name = name
        self.cfg = cfg
        self.latest = latest
        self.emit = emit
        self.clock = clock
        self._sleep = sleep
        self.smbus = transport if transport is not None else load_smbus2("LCD display")
        self.lines = [parse_line(text) for text in cfg.lines]
        self.where = f"display {name} (LCD at 0x{cfg.address:02X} on /dev/i2c-{cfg.bus})"
        self._bus: Any = None
        self._lcd: Hd44780Pcf8574 | None = None
        self._failing: str | None = None
        self._stop = threading.Event()
        self._thread = NamedThread(target=self._run, name=f"display-{name}", daemon=True)
        self.refreshes = 0
        self.failures = 0
        self.refreshed = threading.Event()
        """Set after every refresh the LCD took (tests wait on it instead of sleeping)."""

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
            self.refreshed.set()
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
    """One DisplayLoop per display of the node (not started); a display with `sim:` runs on
    its simulated transport (from the driver registry), without the LCD's start-up waits.

    Raises:
        DriverUnavailable: a real (not simulated) display needs smbus2 and it is missing.
    """
    loops = []
    for name, cfg in node_cfg.displays.items():
        if not isinstance(cfg, LcdDisplay):  # the one display loop there is drives an HD44780
            driver = getattr(cfg, "driver", None)
            raise DriverError(f"displays.{name}: no display loop for driver {driver!r}")
        sim = display_sim(cfg.driver)
        if cfg.sim is not None and sim is not None:
            bus = load_sim(sim)(cfg, SYSTEM_TIME)
            loops.append(DisplayLoop(name, cfg, latest, emit, bus, sleep=lambda s: None))
        else:
            loops.append(DisplayLoop(name, cfg, latest, emit))
    return loops
