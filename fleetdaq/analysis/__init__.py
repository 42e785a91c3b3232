"""Reading recordings for analysis: the library behind `fleetdaq.read` (the public call),
`fleetdaq export`, `fleetdaq report` and `fleetdaq import-modaq`.

One module per concern: `files` (which MCAP files a source names, their summaries and
acquisition-time spans), `mcapio` (the chunk reader), `assemble` (batches -> one stream:
dedupe, window, gaps), `stream` (the result and its pandas / xarray forms), `recording` (the
session(s) as one object), `window` (times and windows), then `export`, `envelope`, `plots`,
`report` and `modaq`. Nothing here is imported by the hub or an edge: a Pi never needs it.
"""
