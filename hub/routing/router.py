"""The hub's embedded Zenoh router: the session every other hub service uses."""

from __future__ import annotations

import logging
from pathlib import Path

import zenoh

from fleetdaq.hub.config.site import SiteConfig
from fleetdaq.hub.errors import RouterError
from fleetdaq.hub.routing.acl import access_control
from fleetdaq.hub.routing.refused_traffic import RefusedTraffic
from fleetdaq.hub.routing.router_log import RouterLogError, RouterLogTap
from fleetdaq.runtime.security import SecretFileError, hub_tls
from fleetdaq.runtime.zenoh_session import router_config

log = logging.getLogger("fleetdaq.hub")

Declared = zenoh.Publisher | zenoh.Subscriber[None] | zenoh.Queryable[None]
"""What a hub service declares on the router's session, and undeclares when it stops."""


def undeclare(entity: Declared) -> None:
    """Undeclare a publisher, subscriber or queryable (zenoh's stubs leave `undeclare`
    unannotated, so mypy is told once, here)."""
    entity.undeclare()  # type: ignore[no-untyped-call]


class Router:
    """Opens the router on start (edges connect to its `listen` endpoints); closes it last.

    With the site's `security.tls`, the router speaks mutual TLS only, with the hub's
    certificate, and filters every message by the access control list made from the site file
    (`fleetdaq.hub.routing.acl`); what the router refuses (ACL, TLS handshakes) goes to `refused`,
    read from the router's log (`fleetdaq.hub.routing.router_log`)."""

    name = "router"

    def __init__(
        self,
        listen: list[str],
        site: SiteConfig | None = None,
        connect: list[str] | None = None,
        partition: str | None = None,
        refused: RefusedTraffic | None = None,
    ) -> None:
        """`connect`: the routers of the other hubs to mesh with (`SiteConfig.mesh_connect`);
        `partition`: the partition hub this router serves (its own certificate), or None for
        the main hub; `refused`: counts what the router refuses (with TLS on)."""
        self.listen = listen
        self.site = site
        self.connect = connect or []
        self.partition = partition
        self.refused = refused
        self._session: zenoh.Session | None = None
        self._tap: RouterLogTap | None = None

    @property
    def session(self) -> zenoh.Session:
        if self._session is None:
            raise RouterError("the router is not running")
        return self._session

    def start(self) -> None:
        tls = acl = None
        if self.site is not None and self.site.security.tls:
            try:
                tls = hub_tls(Path(self.site.security.pki_dir), self.partition)
            except SecretFileError as err:
                raise RouterError(f"security.tls is on, but {err}") from None
            acl = access_control(self.site)
        if acl is not None and self.refused is not None:
            self._tap_log(self.refused)
        try:
            self._session = zenoh.open(router_config(self.listen, tls, acl, self.connect))
        except zenoh.ZError as err:
            self._untap()
            raise RouterError(f"cannot start the Zenoh router on {self.listen}: {err}") from err
        if self._tap is not None and self.refused is not None:
            try:
                self._tap.wait_enabled()
            except RouterLogError as err:
                self.refused.unavailable(str(err))

    def _tap_log(self, refused: RefusedTraffic) -> None:
        tap = RouterLogTap(refused)
        try:
            tap.start()
        except (RouterLogError, OSError) as err:
            refused.unavailable(str(err))
            return
        self._tap = tap
        refused.publish()

    def _untap(self) -> None:
        tap, self._tap = self._tap, None
        if tap is not None:
            tap.stop()

    def stop(self) -> None:
        session, self._session = self._session, None
        if session is not None:
            session.close()
        self._untap()

    def failure(self) -> str | None:
        tap = self._tap
        if tap is not None and tap.died is not None:
            return f"the router's log tap stopped ({tap.died}): refused traffic is not counted"
        return None
