"""Reading recordings for analysis: the library behind `fleetdaq.read` (the public call),
`fleetdaq export` and `fleetdaq report`.

One module per concern: `files` (which MCAP files a source names, their summaries and
acquisition-time spans), `mcapio` (the chunk reader), `assemble` (batches -> one stream:
dedupe, window, gaps), `stream` (the result and its pandas / xarray forms), `recording` (the
session(s) as one object), `window` (times and windows), `errors`, then `export`, `envelope`,
`plots` and `report`. Nothing here is imported by the hub or an edge: a Pi never needs it.
"""
