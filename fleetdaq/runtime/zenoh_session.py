"""Opening Zenoh sessions the way fleetdaq uses them: explicit endpoints, no scouting, and with
the site's security on, mutual TLS (`fleetdaq.runtime.security.TlsFiles`) and the hub's access
control."""

from __future__ import annotations

import json
from collections.abc import Mapping
from typing import Protocol, cast

import zenoh

from fleetdaq.runtime.security import TlsFiles


class Declared(Protocol):
    """What a session declared and must undeclare: a publisher, subscriber, queryable or
    liveliness token (zenoh's stubs leave `undeclare` unannotated; through this it is typed)."""

    def undeclare(self) -> None: ...


def has_subscribers(pub: zenoh.Publisher) -> bool:
    """Whether any subscriber matches `pub`'s key now."""
    # zenoh's stub (1.x) calls `matching_status` a bool; it is a `MatchingStatus`.
    status = cast(zenoh.MatchingStatus, pub.matching_status)
    return bool(status.matching)


def client_config(
    endpoints: list[str], timeout_ms: int = -1, tls: TlsFiles | None = None
) -> zenoh.Config:
    """A client session that connects to the hub's router(s) and never scouts.

    `timeout_ms` bounds how long opening waits for a router (-1: forever). Once open, the
    session reconnects by itself when the router restarts. With `tls`, it shows its own
    certificate and accepts only a router whose certificate the site CA signed, for the name or
    address it connects to."""
    conf = zenoh.Config()
    conf.insert_json5("mode", json.dumps("client"))
    conf.insert_json5("connect/endpoints", json.dumps(endpoints))
    conf.insert_json5("connect/timeout_ms", str(timeout_ms))
    conf.insert_json5("scouting/multicast/enabled", "false")
    _no_shared_memory(conf)
    if tls is not None:
        _tls(conf, tls, "connect")
    return conf


def router_config(
    listen: list[str],
    tls: TlsFiles | None = None,
    acl: Mapping[str, object] | None = None,
    connect: list[str] | None = None,
) -> zenoh.Config:
    """The hub's router; with `tls`, mutual TLS only (a client without a certificate from the
    site CA is refused), and `acl` as its access control. `connect`: other hubs' routers to
    mesh with (Zenoh retries them in the background and relinks when one returns)."""
    conf = zenoh.Config()
    conf.insert_json5("mode", json.dumps("router"))
    conf.insert_json5("listen/endpoints", json.dumps(listen))
    if connect:
        conf.insert_json5("connect/endpoints", json.dumps(connect))
    conf.insert_json5("scouting/multicast/enabled", "false")
    _no_shared_memory(conf)
    if tls is not None:
        _tls(conf, tls, "listen")
        if connect:  # to the other hubs' routers, as the hub (mutual TLS both ways)
            _tls(conf, tls, "connect")
        # Every link TLS: a plain tcp/ listener next to the TLS one would bypass it all.
        conf.insert_json5("transport/link/protocols", json.dumps(["tls"]))
    if acl is not None:
        conf.insert_json5("access_control", json.dumps(acl))
    return conf


def _tls(conf: zenoh.Config, tls: TlsFiles, side: str) -> None:
    conf.insert_json5("transport/link/tls/root_ca_certificate", json.dumps(str(tls.ca)))
    conf.insert_json5("transport/link/tls/enable_mtls", "true")
    conf.insert_json5(f"transport/link/tls/{side}_certificate", json.dumps(str(tls.cert)))
    conf.insert_json5(f"transport/link/tls/{side}_private_key", json.dumps(str(tls.key)))


def _no_shared_memory(conf: zenoh.Config) -> None:
    # Zenoh's shared-memory transport creates POSIX shm segments lazily; where that fails (a
    # full disk, a file-size limit) it panics inside a reply. fleetdaq's links are TCP between
    # machines: shared memory would only ever help two processes on one host.
    conf.insert_json5("transport/shared_memory/enabled", "false")
