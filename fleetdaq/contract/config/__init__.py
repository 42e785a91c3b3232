"""The site file: one YAML describing the hub and every node, validated once into typed objects.

This package holds what every machine reads of it; the hub's full schema subclasses it in
`fleetdaq.hub.config`. One module per concern:

- `fleetdaq.contract.schema` (beside this package, so drivers can use it without importing the
  site file): the types every schema is made of (strict models, names, endpoints, channels,
  streams);
- `node`: an edge machine (spool, clock, streams, outputs, displays); each driver's own schema
  lives beside the driver and reaches the node's schema through the driver registry
  (`fleetdaq.contract.drivers`);
- `node_control`: commands' age ceiling, a node's dead-man and edge interlocks;
- `hubs`: the `hub:` section as a node needs it (router endpoints, partitions);
- `universal_alarms`: the alarms every site gets (the hub raises them, a node reads one);
- `security`: mutual TLS and operators;
- `site`: the whole file as a node reads it (`SiteConfig`); the hub-only sections are known
  keys whose contents only the hub's schema checks;
- `load`: reading YAML and turning every mistake into one line: ``file: key.path: problem``.

This package's ``__init__`` imports nothing, so a driver module can import
`fleetdaq.contract.schema` without pulling in the whole schema (which loads the drivers).
"""
