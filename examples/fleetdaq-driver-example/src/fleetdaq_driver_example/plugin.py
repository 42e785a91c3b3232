"""The plugin object the `fleetdaq.drivers` entry point `serial_barometer` names.

fleetdaq finds it at load, as python-can finds third-party interfaces: the entry point's name is
a config's `driver:` value; the object says what kind of driver it is, its config schema, its
class (``driver(cfg, transport=..., clock=...)``) and its simulator (``"module:function"``,
imported only for a config with `sim:`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal

from fleetdaq.contract.schema import StreamBase
from fleetdaq_driver_example.barometer import SerialBarometer, SerialBarometerStream


@dataclass(frozen=True, slots=True)
class DriverPlugin:
    """fleetdaq's plugin record, field for field (kind, schema, driver, sim, shared): here until
    fleetdaq ships its registry's own, which this package then imports instead."""

    kind: Literal["stream", "output", "display"]
    schema: type[StreamBase]
    driver: Callable[..., object]
    sim: str | None = None
    shared: bool = False


PLUGIN = DriverPlugin(
    kind="stream",
    schema=SerialBarometerStream,
    driver=SerialBarometer,
    sim="fleetdaq_driver_example.sim:barometer_transport",
)
