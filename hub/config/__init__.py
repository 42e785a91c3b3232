"""The hub's site schema: the contract's site model (`fleetdaq.contract.config`) narrowed with what
only the hub reads. `site` is the whole file as the hub validates it (`SiteConfig`), `load` reads
it; the hub section (`hub`: recorder, snapshot, partitions' own settings), alarms (`alarms`),
rules and hub interlocks (`control`), notifications (`notify`) and the dashboard (`dashboard`).
Change a mail setting in `notify`."""

from __future__ import annotations
