"""The one driver table: a config's `driver:` name -> its schema, its class, its simulator;
for streams (`DRIVERS`), displays (`DISPLAYS`) and outputs (`OUTPUTS`).

Adding a driver is its module (schema + decoding + class) plus one row here. The schemas are
imported with this module (the site file is validated against them); a driver module imports
its vendor library (labjack-ljm, spidev, smbus2) only when a driver is constructed without a
simulated transport, and the simulators are imported only when a config has a `sim:` block.
So the hub, laptops and the tests never load a vendor library, and a Pi never loads a sim.
"""

from __future__ import annotations

import functools
import importlib
import operator
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Annotated, Any

from pydantic import Field

from fleetdaq.contract.errors import DriverError
from fleetdaq.contract.schema import OutputBase, StreamBase
from fleetdaq.edge.drivers.base import Driver, OutputDriver
from fleetdaq.edge.drivers.environment_sim import EnvironmentSim, EnvironmentSimStream
from fleetdaq.edge.drivers.hd44780 import LcdDisplay
from fleetdaq.edge.drivers.labjack_t8 import LabJackT8, LabJackT8Stream
from fleetdaq.edge.drivers.labjack_t8_out import (
    LabJackT8DacOutput,
    LabJackT8DioOutput,
    T8DacDriver,
    T8DioDriver,
)
from fleetdaq.edge.drivers.labjack_t8_poll import LabJackT8Poll, LabJackT8PollStream
from fleetdaq.edge.drivers.max31855 import Max31855, Max31855Stream
from fleetdaq.edge.drivers.max31856 import Max31856, Max31856Stream
from fleetdaq.edge.drivers.mcp4725 import Mcp4725Driver, Mcp4725Output
from fleetdaq.edge.drivers.pacing import SYSTEM_TIME, TimeSource
from fleetdaq.edge.drivers.pcf8574 import Pcf8574Driver, Pcf8574Output
from fleetdaq.edge.drivers.shared import SharedDevices
from fleetdaq.edge.drivers.sht3x import Sht3x, Sht3xStream
from fleetdaq.edge.drivers.thermocouple_sim import ThermocoupleSim, ThermocoupleSimStream
from fleetdaq.edge.drivers.wave_sim import WaveSim, WaveSimStream
from fleetdaq.edge.drivers.weld_robot import (
    WeldRobotResume,
    WeldRobotResumeOutput,
    WeldRobotSim,
    WeldRobotSimStream,
)


@dataclass(frozen=True, slots=True)
class DriverSpec:
    schema: type[StreamBase]
    """The stream's config schema (its `driver` field is a Literal of the row's name)."""
    driver: Callable[..., Driver]
    """``driver(cfg)`` opens the real device; ``driver(cfg, transport=t, clock=c)`` runs the
    same code on a simulated transport."""
    sim: str | None = None
    """``"module:function"``: ``function(cfg, clock, shared)`` builds the simulated transport
    used when the config has a `sim:` block. None for drivers that are simulations themselves."""
    shared: bool = False
    """A simulation itself that reaches the agent's shared devices: ``driver(cfg, clock=c,
    shared=s)`` (the weld robot)."""


DRIVERS: dict[str, DriverSpec] = {
    "wave_sim": DriverSpec(WaveSimStream, WaveSim),
    "thermocouple_sim": DriverSpec(ThermocoupleSimStream, ThermocoupleSim),
    "environment_sim": DriverSpec(EnvironmentSimStream, EnvironmentSim),
    "labjack_t8": DriverSpec(
        LabJackT8Stream, LabJackT8, "fleetdaq.edge.drivers.sim_ljm:t8_transport"
    ),
    "labjack_t8_poll": DriverSpec(
        LabJackT8PollStream, LabJackT8Poll, "fleetdaq.edge.drivers.sim_ljm:t8_transport"
    ),
    "max31855": DriverSpec(
        Max31855Stream, Max31855, "fleetdaq.edge.drivers.sim_spi:max31855_transport"
    ),
    "max31856": DriverSpec(
        Max31856Stream, Max31856, "fleetdaq.edge.drivers.sim_spi:max31856_transport"
    ),
    "sht3x": DriverSpec(Sht3xStream, Sht3x, "fleetdaq.edge.drivers.sim_smbus:sht3x_transport"),
    "weld_robot_sim": DriverSpec(WeldRobotSimStream, WeldRobotSim, shared=True),
}


@dataclass(frozen=True, slots=True)
class OutputSpec:
    schema: type[OutputBase]
    """The output's config schema (its `driver` field is a Literal of the row's name)."""
    driver: Callable[..., OutputDriver]
    """``driver(cfg, transport=None, clock=c, shared=s)``: the real device without a
    transport, the same code on a simulated one with it."""
    sim: str | None = None
    """``"module:function"`` building the simulated transport for a config with `sim:`; None
    for outputs that are simulations themselves."""


OUTPUTS: dict[str, OutputSpec] = {
    "labjack_t8_dac": OutputSpec(
        LabJackT8DacOutput, T8DacDriver, "fleetdaq.edge.drivers.sim_ljm:t8_transport"
    ),
    "labjack_t8_dio": OutputSpec(
        LabJackT8DioOutput, T8DioDriver, "fleetdaq.edge.drivers.sim_ljm:t8_transport"
    ),
    "pcf8574": OutputSpec(
        Pcf8574Output, Pcf8574Driver, "fleetdaq.edge.drivers.sim_smbus:pcf8574_transport"
    ),
    "mcp4725": OutputSpec(
        Mcp4725Output, Mcp4725Driver, "fleetdaq.edge.drivers.sim_smbus:mcp4725_transport"
    ),
    "weld_robot_resume": OutputSpec(WeldRobotResumeOutput, WeldRobotResume),
}

DISPLAYS: dict[str, tuple[type[LcdDisplay], str]] = {
    "hd44780_pcf8574": (LcdDisplay, "fleetdaq.edge.drivers.sim_smbus:lcd_transport"),
}
"""Display drivers: name -> (schema, simulated transport)."""

if TYPE_CHECKING:
    StreamConfig = StreamBase
else:
    StreamConfig = Annotated[
        functools.reduce(operator.or_, (spec.schema for spec in DRIVERS.values())),
        Field(discriminator="driver"),
    ]
"""Any stream's config: pydantic picks the schema by its `driver:` value."""

if TYPE_CHECKING:
    OutputConfig = OutputBase
else:
    OutputConfig = Annotated[
        functools.reduce(operator.or_, (spec.schema for spec in OUTPUTS.values())),
        Field(discriminator="driver"),
    ]
"""Any output's config: pydantic picks the schema by its `driver:` value."""


def load_sim(target: str) -> Callable[..., Any]:
    """Import a simulator's transport factory (``"module:function"``) now."""
    module_name, _, name = target.partition(":")
    factory: Callable[..., Any] = getattr(importlib.import_module(module_name), name)
    return factory


def create_driver(
    cfg: StreamBase, clock: TimeSource = SYSTEM_TIME, shared: SharedDevices | None = None
) -> Driver:
    """The driver for a stream's config, on its simulated transport when the config has `sim:`.

    `shared` is the agent's shared devices (a T8 that streams and has outputs, a weld cell).

    Raises:
        DriverUnavailable: the device's vendor library is not installed.
        DriverError: no driver of that name.
    """
    spec = DRIVERS.get(cfg.driver)
    if spec is None:
        raise DriverError(f"no driver named {cfg.driver!r}")
    shared = shared if shared is not None else SharedDevices()
    if spec.sim is not None and getattr(cfg, "sim", None) is not None:
        transport = load_sim(spec.sim)(cfg, clock, shared)
        return spec.driver(cfg, transport=transport, clock=clock)
    if spec.shared:
        return spec.driver(cfg, clock=clock, shared=shared)
    return spec.driver(cfg)


def create_output(
    cfg: OutputBase, clock: TimeSource = SYSTEM_TIME, shared: SharedDevices | None = None
) -> OutputDriver:
    """The driver for an output's config, on its simulated transport when the config has `sim:`.

    Raises:
        DriverUnavailable: the device's vendor library is not installed.
        DriverError: no output driver of that name.
    """
    spec = OUTPUTS.get(cfg.driver)
    if spec is None:
        raise DriverError(f"no output driver named {cfg.driver!r}")
    shared = shared if shared is not None else SharedDevices()
    transport = None
    if spec.sim is not None and getattr(cfg, "sim", None) is not None:
        transport = load_sim(spec.sim)(cfg, clock, shared)
    return spec.driver(cfg, transport=transport, clock=clock, shared=shared)
