"""LabJack T8 outputs through LJM: `labjack_t8_dac` (DAC0/DAC1) and `labjack_t8_dio` (a digital
line), and the T8's hardware watchdog set to the outputs' safe values.

Both read back from the device (eReadName of the same register after every write and at every
readback poll). All outputs of one T8 go through one `T8Outputs` (fleetdaq.edge.drivers.shared); on
a T8 that also streams, LJM hands out the stream's handle (see `T8Outputs`).

Hardware watchdog (T-Series datasheet 23.0, "Watchdog"): when the T8 hears no command-response
communication for WATCHDOG_TIMEOUT_S_DEFAULT seconds it performs the enabled actions: drive DIO
lines (WATCHDOG_DIO_ENABLE_DEFAULT; the lines whose bit is 0 in WATCHDOG_DIO_INHIBIT_DEFAULT
and 1 in WATCHDOG_DIO_DIRECTION_DEFAULT go to their bit of WATCHDOG_DIO_STATE_DEFAULT) and
set DAC0/DAC1 (WATCHDOG_DACn_ENABLE_DEFAULT, WATCHDOG_DACn_DEFAULT in volts). Stream data does
not clear the timer: the output service's readback poll does. The other watchdog registers
must only be written while WATCHDOG_ENABLE_DEFAULT is 0, and they are stored in flash, so they
are read first and written only when they differ.
"""

from __future__ import annotations

import math
from typing import Annotated, ClassVar, Literal

from pydantic import Field

from fleetdaq.contract.drivers import DriverKind, DriverPlugin
from fleetdaq.contract.schema import OutputBase
from fleetdaq.edge.drivers.labjack_ljm import (
    LabJackT8Sim,
    Ljm,
    T8Connection,
    T8Outputs,
    dio_number,
)
from fleetdaq.edge.drivers.pacing import SYSTEM_TIME, TimeSource
from fleetdaq.edge.drivers.shared import SharedDevices

T8_DIO_LINE = r"^(FIO[0-7]|EIO[0-7]|CIO[0-3]|DIO([0-9]|1[0-9]))$"
ALL_DIO = (1 << 23) - 1
"""The watchdog's DIO bitmasks cover DIO0-22 (datasheet 23.0)."""


class LabJackT8DacOutput(OutputBase, T8Connection):
    """DAC0 or DAC1 of a LabJack T8: -0.1..10 V, read back from the device."""

    driver: Literal["labjack_t8_dac"]
    kind: Literal["analog"] = "analog"
    unit: str = "V"
    dac: Literal[0, 1]
    sim: LabJackT8Sim | None = None

    DEVICE_SPAN: ClassVar[tuple[float, float] | None] = (
        T8Outputs.DAC_MIN_V,
        T8Outputs.DAC_MAX_V,
    )

    @property
    def resource(self) -> str:
        return f"DAC{self.dac} of the T8 {self.identifier}"


class LabJackT8DioOutput(OutputBase, T8Connection):
    """A digital line of a LabJack T8 driven as an output (0 = low, 1 = high)."""

    driver: Literal["labjack_t8_dio"]
    kind: Literal["digital"] = "digital"
    line: Annotated[str, Field(pattern=T8_DIO_LINE)]
    """FIO0-7, EIO0-7, CIO0-3 or DIO0-19."""
    sim: LabJackT8Sim | None = None

    @property
    def resource(self) -> str:
        return f"DIO{dio_number(self.line)} of the T8 {self.identifier}"


class T8Watchdog:
    """The T8's hardware watchdog, set to the safe values of every output on the device."""

    NAMES: ClassVar[tuple[str, ...]] = (
        "WATCHDOG_TIMEOUT_S_DEFAULT",
        "WATCHDOG_STRICT_ENABLE_DEFAULT",
        "WATCHDOG_RESET_ENABLE_DEFAULT",
        "WATCHDOG_DIO_ENABLE_DEFAULT",
        "WATCHDOG_DIO_INHIBIT_DEFAULT",
        "WATCHDOG_DIO_DIRECTION_DEFAULT",
        "WATCHDOG_DIO_STATE_DEFAULT",
        "WATCHDOG_DAC0_ENABLE_DEFAULT",
        "WATCHDOG_DAC0_DEFAULT",
        "WATCHDOG_DAC1_ENABLE_DEFAULT",
        "WATCHDOG_DAC1_DEFAULT",
    )

    def __init__(self, device: T8Outputs) -> None:
        self.device = device
        self.dacs: dict[int, float] = {}
        self.dios: dict[int, int] = {}
        self.writes = 0
        """How many times the configuration was written (flash writes)."""

    @property
    def where(self) -> str:
        return self.device.where

    def register_dac(self, dac: int, safe_v: float) -> None:
        self.dacs[dac] = safe_v

    def register_dio(self, line: str, safe: int) -> None:
        self.dios[dio_number(line)] = safe

    def settings(self, timeout_s: float) -> dict[str, float]:
        """The register values for these outputs and `timeout_s` (whole seconds, at least 1)."""
        mask = sum(1 << bit for bit in self.dios)
        state = sum(1 << bit for bit, level in self.dios.items() if level)
        out: dict[str, float] = {
            "WATCHDOG_TIMEOUT_S_DEFAULT": float(max(1, math.ceil(timeout_s))),
            "WATCHDOG_STRICT_ENABLE_DEFAULT": 0.0,  # strict mode: only STRICT_CLEAR would feed it
            "WATCHDOG_RESET_ENABLE_DEFAULT": 0.0,  # a reset would bring power-up values instead
            "WATCHDOG_DIO_ENABLE_DEFAULT": 1.0 if self.dios else 0.0,
            "WATCHDOG_DIO_INHIBIT_DEFAULT": float(ALL_DIO & ~mask),  # 1 = leave that line alone
            "WATCHDOG_DIO_DIRECTION_DEFAULT": float(mask),  # 1 = output
            "WATCHDOG_DIO_STATE_DEFAULT": float(state),
        }
        for dac in (0, 1):
            out[f"WATCHDOG_DAC{dac}_ENABLE_DEFAULT"] = 1.0 if dac in self.dacs else 0.0
            out[f"WATCHDOG_DAC{dac}_DEFAULT"] = float(self.dacs.get(dac, 0.0))
        return out

    def arm(self, timeout_s: float) -> str:
        """Configure and enable the watchdog; write only what differs (flash). Returns what it
        did, in words. Raises DriverError when the device refuses."""
        want = self.settings(timeout_s)
        names = ["WATCHDOG_ENABLE_DEFAULT", *self.NAMES]
        with self.device.lock:
            have = self.device.call(self.device.ljm.eReadNames, len(names), names)
            enabled = float(have[0]) == 1.0
            same = all(
                math.isclose(float(h), want[n], abs_tol=1e-3)
                for n, h in zip(names[1:], have[1:], strict=True)
            )
            what = (
                f"{self.where}: hardware watchdog after {want['WATCHDOG_TIMEOUT_S_DEFAULT']:g} s "
                f"without communication: {self.describe()}"
            )
            if enabled and same:
                return what + " (already set)"
            order = ["WATCHDOG_ENABLE_DEFAULT", *self.NAMES, "WATCHDOG_ENABLE_DEFAULT"]
            values = [0.0, *(want[n] for n in self.NAMES), 1.0]
            self.device.call(self.device.ljm.eWriteNames, len(order), order, values)
            self.writes += 1
        return what

    def feed(self) -> None:
        """Every command-response exchange restarts the T8's watchdog timer."""
        self.device.read("WATCHDOG_ENABLE_DEFAULT")

    def describe(self) -> str:
        parts = [f"DAC{d} -> {v:g} V" for d, v in sorted(self.dacs.items())]
        parts += [f"DIO{b} -> {lvl}" for b, lvl in sorted(self.dios.items())]
        return ", ".join(parts) or "nothing"


def _t8(
    cfg: LabJackT8DacOutput | LabJackT8DioOutput,
    transport: Ljm | None,
    clock: TimeSource,
    shared: SharedDevices,
) -> tuple[T8Outputs, T8Watchdog]:
    where = (cfg.connection, cfg.identifier)
    device = shared.get(
        ("t8_outputs", *where),
        lambda: T8Outputs(transport, cfg.connection, cfg.identifier, clock),
        T8Outputs,
    )
    watchdog = shared.get(("t8_watchdog", *where), lambda: T8Watchdog(device), T8Watchdog)
    return device, watchdog


class _T8Output:
    register: str

    def __init__(self, device: T8Outputs, watchdog: T8Watchdog) -> None:
        self.device = device
        self.watchdog = watchdog

    @property
    def where(self) -> str:
        return f"{self.device.where} {self.register}"

    def open(self) -> None:
        self.device.open()

    def write(self, value: float) -> None:
        self.device.call(self.device.ljm.eWriteName, self.register, float(value))

    def read(self) -> float:
        return self.device.read(self.register)

    def close(self) -> None:
        self.device.close()

    def hardware_watchdog(self) -> T8Watchdog:
        return self.watchdog


class T8DacDriver(_T8Output):
    """The `labjack_t8_dac` output driver.

    Args:
        cfg: the output's config.
        transport: the `ljm` module (the simulated T8 in sims, a fake in tests); default:
            labjack-ljm, imported when the device is first made.
        shared: the agent's shared devices (one `T8Outputs` per T8).
    """

    def __init__(
        self,
        cfg: LabJackT8DacOutput,
        transport: Ljm | None = None,
        clock: TimeSource = SYSTEM_TIME,
        shared: SharedDevices | None = None,
    ) -> None:
        super().__init__(*_t8(cfg, transport, clock, shared or SharedDevices()))
        self.register = f"DAC{cfg.dac}"
        self.watchdog.register_dac(cfg.dac, cfg.safe)


class T8DioDriver(_T8Output):
    """The `labjack_t8_dio` output driver (1 = high); arguments as `T8DacDriver`."""

    def __init__(
        self,
        cfg: LabJackT8DioOutput,
        transport: Ljm | None = None,
        clock: TimeSource = SYSTEM_TIME,
        shared: SharedDevices | None = None,
    ) -> None:
        super().__init__(*_t8(cfg, transport, clock, shared or SharedDevices()))
        self.register = cfg.line
        self.watchdog.register_dio(cfg.line, int(cfg.safe))

    def write(self, value: float) -> None:
        super().write(1.0 if value >= 0.5 else 0.0)


DAC_PLUGIN = DriverPlugin(
    DriverKind.OUTPUT,
    LabJackT8DacOutput,
    T8DacDriver,
    "fleetdaq.edge.drivers.sim_ljm:t8_transport",
)

DIO_PLUGIN = DriverPlugin(
    DriverKind.OUTPUT,
    LabJackT8DioOutput,
    T8DioDriver,
    "fleetdaq.edge.drivers.sim_ljm:t8_transport",
)
