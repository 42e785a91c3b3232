"""The site file: one YAML describing the hub and every node, validated once into typed objects.

It lives in `edge` (the lower layer) because every process loads it and `edge` never imports
`hub`. One module per concern:

- `fleetdaq.contract.schema` (beside this package, so drivers can use it without importing the site
file):
  the types every schema is made of (strict models, names, endpoints, channels, streams);
- `node`: an edge machine (spool, clock, streams, displays); each driver's own schema lives
  beside the driver, and `fleetdaq.edge.drivers.table` puts them together;
- `hub`: what only the hub uses (router endpoints, recorder, ...);
- `site`: the whole file;
- `load`: reading YAML and turning every mistake into one line: ``file: key.path: problem``.

This package's ``__init__`` imports nothing, so a driver module can import
`fleetdaq.contract.schema`
without pulling in the whole schema (which imports the drivers).
"""
