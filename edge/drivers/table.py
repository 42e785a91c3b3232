"""Opening a config's driver: its stream, output or display driver looked up by name in the
driver registry (`fleetdaq.contract.drivers`), on its simulated transport when the config has a
``sim:`` block.

A driver module imports its vendor library (labjack-ljm, spidev, smbus2) only when a driver is
constructed without a simulated transport, and a simulator is imported only when a config has
a ``sim:`` block. So the hub, laptops and the tests never load a vendor library, and a Pi never
loads a sim.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from typing import Any, cast

from fleetdaq.contract.drivers import DriverKind, DriverPlugin, driver_registry
from fleetdaq.contract.schema import OutputBase, StreamBase
from fleetdaq.edge.drivers.base import Driver, OutputDriver
from fleetdaq.edge.drivers.pacing import SYSTEM_TIME, TimeSource
from fleetdaq.edge.drivers.shared import SharedDevices


def load_sim(target: str) -> Callable[..., Any]:
    """Import a simulator's transport factory (``"module:function"``) now."""
    module_name, _, name = target.partition(":")
    factory: Callable[..., Any] = getattr(importlib.import_module(module_name), name)
    return factory


def _factory(spec: DriverPlugin) -> Callable[..., object]:
    """A plugin's driver as this module calls it: with the keywords of its kind (the registry
    types it only as a callable of its own config class)."""
    return cast(Callable[..., object], spec.driver)


def create_driver(
    cfg: StreamBase, clock: TimeSource = SYSTEM_TIME, shared: SharedDevices | None = None
) -> Driver:
    """The driver for a stream's config, on its simulated transport when the config has `sim:`.

    `shared` is the agent's shared devices (a T8 that streams and has outputs, a weld cell).

    Raises:
        DriverUnavailable: the device's vendor library is not installed.
        DriverError: no driver of that name (or it failed to load: the reason).
    """
    spec = driver_registry().plugin(cfg.driver, DriverKind.STREAM)
    make = _factory(spec)
    shared = shared if shared is not None else SharedDevices()
    if spec.sim is not None and getattr(cfg, "sim", None) is not None:
        transport = load_sim(spec.sim)(cfg, clock, shared)
        return cast(Driver, make(cfg, transport=transport, clock=clock))
    if spec.shared:
        return cast(Driver, make(cfg, clock=clock, shared=shared))
    return cast(Driver, make(cfg))


def create_output(
    cfg: OutputBase, clock: TimeSource = SYSTEM_TIME, shared: SharedDevices | None = None
) -> OutputDriver:
    """The driver for an output's config, on its simulated transport when the config has `sim:`.

    Raises:
        DriverUnavailable: the device's vendor library is not installed.
        DriverError: no output driver of that name (or it failed to load: the reason).
    """
    spec = driver_registry().plugin(cfg.driver, DriverKind.OUTPUT)
    shared = shared if shared is not None else SharedDevices()
    transport = None
    if spec.sim is not None and getattr(cfg, "sim", None) is not None:
        transport = load_sim(spec.sim)(cfg, clock, shared)
    make = _factory(spec)
    return cast(OutputDriver, make(cfg, transport=transport, clock=clock, shared=shared))


def display_sim(driver: str) -> str | None:
    """The ``"module:function"`` building a display driver's simulated bus (None: it has none).

    Raises:
        DriverError: no display driver of that name (or it failed to load: the reason).
    """
    return driver_registry().plugin(driver, DriverKind.DISPLAY).sim
