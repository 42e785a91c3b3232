"""One output of the edge at run time: its driver, what was written, what the device reads back,
whether it is armed, its pulse in progress, its counters. Only the output service's worker
thread changes it (device calls included); the health thread reads its fields.
"""

from __future__ import annotations

import contextlib
import math
from dataclasses import dataclass

from fleetdaq.contract.errors import DriverError
from fleetdaq.contract.messages import OutputState
from fleetdaq.contract.schema import OutputBase
from fleetdaq.edge.command_check import OutputView
from fleetdaq.edge.drivers.base import OutputDriver
from fleetdaq.edge.drivers.pacing import TimeSource

REOPEN_FIRST_S = 0.5
REOPEN_MAX_S = 30.0


@dataclass(slots=True)
class Pulse:
    ends_s: float
    """Monotonic seconds when the output goes back."""
    back_to: float
    command_id: str


class OutputChannel:
    """An output and its state."""

    def __init__(self, name: str, cfg: OutputBase, driver: OutputDriver, clock: TimeSource) -> None:
        self.name = name
        self.cfg = cfg
        self.driver = driver
        self.clock = clock
        self.value = math.nan
        self.changed_s = -math.inf
        self.readback = math.nan
        self.readback_ns = 0
        self.armed = not cfg.arm_required
        """An output with `arm_required` is armed by an operator before every use; any other is
        armed from the start, and needs arming again only after a safe state."""
        self.pulse: Pulse | None = None
        self.commands = 0
        self.refused = 0
        self.fault: str | None = None
        """The device's last error (None: working)."""
        self.mismatch = False
        self._open = False
        self._retry_s = 0.0
        self._backoff = REOPEN_FIRST_S

    @property
    def source(self) -> str:
        return self.cfg.readback

    def now_s(self) -> float:
        return self.clock.monotonic_ns() / 1e9

    def view(self, interlocks: tuple[str, ...]) -> OutputView:
        return OutputView(self.cfg, self.value, self.changed_s, self.armed, interlocks)

    def state(self, safe_state: bool, interlocks: tuple[str, ...]) -> OutputState:
        return OutputState(
            name=self.name,
            kind=self.cfg.kind,
            unit=self.cfg.unit,
            value=self.value,
            readback=self.readback,
            readback_ns=self.readback_ns,
            readback_source=self.source,
            armed=self.armed,
            safe_state=safe_state,
            interlocks=interlocks,
            commands=self.commands,
            refused=self.refused,
        )

    # -- device calls (the worker thread only) ---------------------------------------------

    def ensure_open(self) -> None:
        """Open the device if it is not (raises DriverError)."""
        if not self._open:
            self.driver.open()
            self._open = True

    def write(self, value: float) -> None:
        """Write `value` and read it back. Raises DriverError (the fault is kept)."""
        try:
            self.ensure_open()
            self.driver.write(value)
        except (DriverError, OSError) as err:
            self._failed(err)
            raise DriverError(str(err)) from err
        self.value = value
        self.changed_s = self.now_s()
        self.fault = None
        self._backoff = REOPEN_FIRST_S
        self.read_back()

    def read_back(self) -> None:
        """Refresh the readback: from the device, or the last value written. A device that
        cannot be read leaves NaN (and the fault)."""
        if self.cfg.readback == "last_written":
            self.readback, self.readback_ns = self.value, self.clock.time_ns()
            return
        try:
            self.ensure_open()
            value = float(self.driver.read())
        except (DriverError, OSError) as err:
            self._failed(err)
            self.readback, self.readback_ns = math.nan, self.clock.time_ns()
            return
        self.fault = None
        self.readback, self.readback_ns = value, self.clock.time_ns()

    def poll_due(self) -> bool:
        """Whether a readback poll should touch the device now (a faulty one backs off)."""
        return self.fault is None or self.now_s() >= self._retry_s

    def readback_differs(self) -> bool:
        """The device holds something else than what was written (beyond its resolution)."""
        if self.cfg.readback != "device" or math.isnan(self.value):
            return False
        if math.isnan(self.readback):
            return False
        if self.cfg.kind == "digital":
            return (self.readback >= 0.5) != (self.value >= 0.5)
        tolerance = 0.005 * (self.cfg.high - self.cfg.low)
        return abs(self.readback - self.value) > tolerance

    def close(self) -> None:
        self._open = False
        with contextlib.suppress(DriverError, OSError):
            self.driver.close()

    def _failed(self, err: BaseException) -> None:
        # The driver is not closed: its device may be shared (a T8 that also streams, the other
        # pins of a PCF8574), and the drivers heal their own handles on the next call.
        self.fault = str(err) or type(err).__name__
        self._open = False
        self._retry_s = self.now_s() + self._backoff
        self._backoff = min(self._backoff * 2, REOPEN_MAX_S)
