"""Opening Zenoh sessions the way fleetdaq uses them: explicit endpoints, no scouting."""

from __future__ import annotations

import json
from typing import Any

import zenoh


def client_config(endpoints: list[str], timeout_ms: int = -1) -> Any:
    """A client session that connects to the hub's router(s) and never scouts.

    `timeout_ms` bounds how long opening waits for a router (-1: forever). Once open, the
    session reconnects by itself when the router restarts.
    """
    conf = zenoh.Config()
    conf.insert_json5("mode", json.dumps("client"))
    conf.insert_json5("connect/endpoints", json.dumps(endpoints))
    conf.insert_json5("connect/timeout_ms", str(timeout_ms))
    conf.insert_json5("scouting/multicast/enabled", "false")
    _no_shared_memory(conf)
    return conf


def router_config(listen: list[str]) -> Any:
    conf = zenoh.Config()
    conf.insert_json5("mode", json.dumps("router"))
    conf.insert_json5("listen/endpoints", json.dumps(listen))
    conf.insert_json5("scouting/multicast/enabled", "false")
    _no_shared_memory(conf)
    return conf


def _no_shared_memory(conf: Any) -> None:
    # Zenoh's shared-memory transport creates POSIX shm segments lazily; where that fails (a
    # full disk, a file-size limit) it panics inside a reply. fleetdaq's links are TCP between
    # machines: shared memory would only ever help two processes on one host.
    conf.insert_json5("transport/shared_memory/enabled", "false")
