"""The control wing: commands to the edges' outputs with a reply (`commands`), the rules that
turn conditions into commands (`rules`) and the AM layer-wait condition (`layer_waits`).
`wiring` builds them."""

from __future__ import annotations
