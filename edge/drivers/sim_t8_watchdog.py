"""The simulated T8's hardware watchdog (T-Series datasheet 23.0, "Watchdog").

The WATCHDOG_*_DEFAULT registers are kept in flash: they survive a power cycle, and every write
that changes one is counted (`flash_writes`). While WATCHDOG_ENABLE_DEFAULT is 1 the other
watchdog registers cannot be written. With the watchdog enabled, when no command-response
communication has arrived for WATCHDOG_TIMEOUT_S_DEFAULT seconds (stream data does not count)
it performs its actions once: the DIO lines whose WATCHDOG_DIO_INHIBIT_DEFAULT bit is 0 and
WATCHDOG_DIO_DIRECTION_DEFAULT bit is 1 go to their WATCHDOG_DIO_STATE_DEFAULT bit (with
WATCHDOG_DIO_ENABLE_DEFAULT), DAC0/DAC1 to WATCHDOG_DACn_DEFAULT volts (with
WATCHDOG_DACn_ENABLE_DEFAULT). The next communication starts a new timeout period.

The timeout is evaluated when anything asks (a call, or `check` from a test): the actions are
applied as of the moment the timer ran out, so what a later read sees is what the device held.
"""

from __future__ import annotations

from dataclasses import dataclass

WATCHDOG_DEFAULTS: dict[str, float] = {
    "WATCHDOG_ENABLE_DEFAULT": 0.0,
    "WATCHDOG_ADVANCED_DEFAULT": 0.0,
    "WATCHDOG_TIMEOUT_S_DEFAULT": 20.0,
    "WATCHDOG_STARTUP_DELAY_S_DEFAULT": 0.0,
    "WATCHDOG_STRICT_ENABLE_DEFAULT": 0.0,
    "WATCHDOG_STRICT_KEY_DEFAULT": 0.0,
    "WATCHDOG_RESET_ENABLE_DEFAULT": 0.0,
    "WATCHDOG_DIO_ENABLE_DEFAULT": 0.0,
    "WATCHDOG_DIO_STATE_DEFAULT": 0.0,
    "WATCHDOG_DIO_DIRECTION_DEFAULT": 0.0,
    "WATCHDOG_DIO_INHIBIT_DEFAULT": 0.0,
    "WATCHDOG_DAC0_ENABLE_DEFAULT": 0.0,
    "WATCHDOG_DAC0_DEFAULT": 0.0,
    "WATCHDOG_DAC1_ENABLE_DEFAULT": 0.0,
    "WATCHDOG_DAC1_DEFAULT": 0.0,
}
DIO_LINES = 23


@dataclass(frozen=True, slots=True)
class WatchdogAction:
    """What a timeout does: DAC volts by number, DIO levels by DIO#."""

    dacs: dict[int, float]
    dios: dict[int, int]


class SimWatchdog:
    """The watchdog's registers (flash) and its timer (monotonic ns)."""

    def __init__(self) -> None:
        self.registers = dict(WATCHDOG_DEFAULTS)
        self.flash_writes = 0
        self.trips = 0
        self._fed_ns = 0
        self._tripped = False

    @staticmethod
    def owns(name: str) -> bool:
        return name in WATCHDOG_DEFAULTS

    @property
    def enabled(self) -> bool:
        return self.registers["WATCHDOG_ENABLE_DEFAULT"] == 1.0

    def write(self, name: str, value: float) -> str | None:
        """Store a register; returns why the device refuses it (None: stored)."""
        if name != "WATCHDOG_ENABLE_DEFAULT" and self.enabled:
            return f"{name}: disable the watchdog (WATCHDOG_ENABLE_DEFAULT=0) before changing it"
        if name == "WATCHDOG_TIMEOUT_S_DEFAULT" and value < 1:
            return f"{name}={value:g}: at least 1 s"
        if self.registers[name] != float(value):
            self.flash_writes += 1
        self.registers[name] = float(value)
        return None

    def read(self, name: str) -> float:
        return self.registers[name]

    def power_on(self, now_ns: int) -> None:
        """A power cycle: the flash keeps the settings; the timer starts again."""
        self._fed_ns = now_ns
        self._tripped = False

    def feed(self, now_ns: int) -> None:
        """Command-response communication: clears the timer (call `due` first)."""
        self._fed_ns = now_ns
        self._tripped = False

    def due(self, now_ns: int) -> WatchdogAction | None:
        """The actions to perform now, once per timeout period (None: nothing to do)."""
        if not self.enabled or self._tripped:
            return None
        timeout_ns = self.registers["WATCHDOG_TIMEOUT_S_DEFAULT"] * 1e9
        if now_ns - self._fed_ns < timeout_ns:
            return None
        self._tripped = True
        self.trips += 1
        r = self.registers
        dios: dict[int, int] = {}
        if r["WATCHDOG_DIO_ENABLE_DEFAULT"] == 1.0:
            inhibit = int(r["WATCHDOG_DIO_INHIBIT_DEFAULT"])
            direction = int(r["WATCHDOG_DIO_DIRECTION_DEFAULT"])
            state = int(r["WATCHDOG_DIO_STATE_DEFAULT"])
            for bit in range(DIO_LINES):
                if not inhibit >> bit & 1 and direction >> bit & 1:
                    dios[bit] = state >> bit & 1
        dacs = {
            d: r[f"WATCHDOG_DAC{d}_DEFAULT"]
            for d in (0, 1)
            if r[f"WATCHDOG_DAC{d}_ENABLE_DEFAULT"] == 1.0
        }
        return WatchdogAction(dacs, dios)
