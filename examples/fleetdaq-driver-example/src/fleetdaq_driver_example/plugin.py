"""The plugin object the `fleetdaq.drivers` entry point `serial_barometer` names.

fleetdaq finds it at load, as python-can finds third-party interfaces: the entry point's name is
a config's `driver:` value; the object says what kind of driver it is, its config schema, its
class (``driver(cfg, transport=..., clock=...)``) and its simulator (``"module:function"``,
imported only for a config with `sim:`).
"""

from __future__ import annotations

from fleetdaq.contract.drivers import DriverKind, DriverPlugin
from fleetdaq_driver_example.barometer import SerialBarometer, SerialBarometerStream

PLUGIN = DriverPlugin(
    kind=DriverKind.STREAM,
    schema=SerialBarometerStream,
    driver=SerialBarometer,
    sim="fleetdaq_driver_example.sim:barometer_transport",
)
