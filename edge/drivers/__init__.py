"""Drivers: one device, one module, behind the small `Driver` protocol
(`fleetdaq.edge.drivers.base`).

Each driver module holds the device's config schema, its decoding, its driver class and the
`DriverPlugin` that registers them (`fleetdaq.contract.drivers`, through the
``fleetdaq.drivers`` entry points in ``pyproject.toml``); the simulated transports live beside
them (``sim_*.py``) and the drivers never import them. `fleetdaq.edge.drivers.table` opens a
config's driver: adding a driver is its module plus one entry point."""
