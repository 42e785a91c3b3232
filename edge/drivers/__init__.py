"""Drivers: one device, one module, behind the small `Driver` protocol
(`fleetdaq.edge.drivers.base`).

Each driver module holds the device's config schema, its decoding and its driver class; the
simulated transports live beside them (``sim_*.py``) and the drivers never import them.
`fleetdaq.edge.drivers.table` is the one table that puts a driver name, its schema, its class and
its simulator together: adding a driver is its module plus one row there."""
