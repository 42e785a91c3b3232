"""The fleetdaq hub. Its root holds the runtime and what every wing shares: the runtime
(`runtime`) and its composition root (`composition`, which builds every service from one
`context` through each wing's factory, ``<wing>.wiring``), the service lifecycle (`services`,
`periodic`), the in-process bus (`bus`), the read model (`read_model`), operators' requests
over Zenoh (`requests`), compiled loops (`jit`), the error tree (`errors`) and the hub's own
config (`config`).

Wings, one package each: `recording`, `partitions`, `nodes` (node health, fleet time),
`supervision` (alarms, notify, events), `control` (commands, rules), `live` (dashboard,
Foxglove, metrics), and `routing` (the embedded Zenoh router). The hub imports the contract,
the runtime and `fleetdaq.ptp`, never the agent (`fleetdaq.edge`)."""

from __future__ import annotations
