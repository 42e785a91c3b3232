"""The readers' tier reads with environments of their own, not the project's."""

from __future__ import annotations

import json
import sys

from tests.readers.conftest import Readers


def test_the_readers_run_in_a_python_of_their_own_without_fleetdaq(readers: Readers) -> None:
    code = """
import importlib.util, json, sys
names = ["pandas", "pyarrow", "duckdb", "polars", "xarray", "h5netcdf", "rosbags", "mcap",
         "mcap_ros2", "jsonschema"]
found = importlib.util.find_spec("fleetdaq") is not None
print(json.dumps({"prefix": sys.prefix, "fleetdaq": found,
                  "missing": [n for n in names if importlib.util.find_spec(n) is None]}))
"""
    seen = json.loads(readers.run(code))
    assert seen["prefix"] != sys.prefix
    assert seen == {"prefix": seen["prefix"], "fleetdaq": False, "missing": []}


def test_node_finds_the_stock_foxglove_client(readers: Readers, tmp_path) -> None:  # type: ignore[no-untyped-def]
    script = tmp_path / "probe.js"
    script.write_text(
        'const { FoxgloveClient } = require("@foxglove/ws-protocol");\n'
        "console.log(JSON.stringify(FoxgloveClient.SUPPORTED_SUBPROTOCOL));\n"
    )
    assert json.loads(readers.node(script)) == "foxglove.websocket.v1"
