"""Opening Zenoh sessions the way fleetdaq uses them: explicit endpoints, no scouting."""

from __future__ import annotations

import json
from typing import Any

import zenoh


def client_config(endpoints: list[str]) -> Any:
    """A client session that connects to the hub's router(s) and never scouts."""
    conf = zenoh.Config()
    conf.insert_json5("mode", json.dumps("client"))
    conf.insert_json5("connect/endpoints", json.dumps(endpoints))
    # Keep trying to reach the router at start-up instead of failing the open.
    conf.insert_json5("connect/timeout_ms", "-1")
    conf.insert_json5("scouting/multicast/enabled", "false")
    return conf


def router_config(listen: list[str]) -> Any:
    conf = zenoh.Config()
    conf.insert_json5("mode", json.dumps("router"))
    conf.insert_json5("listen/endpoints", json.dumps(listen))
    conf.insert_json5("scouting/multicast/enabled", "false")
    return conf
