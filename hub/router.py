"""The hub's embedded Zenoh router: the session every other hub service uses."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import zenoh

from edge.config.site import SiteConfig
from edge.security import SecretFileError, hub_tls
from edge.zenoh_session import router_config
from hub.acl import access_control
from hub.errors import RouterError

log = logging.getLogger("fleetdaq.hub")


class Router:
    """Opens the router on start (edges connect to its `listen` endpoints); closes it last.

    With the site's `security.tls`, the router speaks mutual TLS only, with the hub's
    certificate, and filters every message by the access control list made from the site file
    (`hub.acl`)."""

    name = "router"

    def __init__(
        self,
        listen: list[str],
        site: SiteConfig | None = None,
        connect: list[str] | None = None,
        partition: str | None = None,
    ) -> None:
        """`connect`: the routers of the other hubs to mesh with (`SiteConfig.mesh_connect`);
        `partition`: the partition hub this router serves (its own certificate), or None for
        the main hub."""
        self.listen = listen
        self.site = site
        self.connect = connect or []
        self.partition = partition
        self._session: Any = None

    @property
    def session(self) -> Any:
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
        try:
            self._session = zenoh.open(router_config(self.listen, tls, acl, self.connect))
        except zenoh.ZError as err:
            raise RouterError(f"cannot start the Zenoh router on {self.listen}: {err}") from err

    def stop(self) -> None:
        session, self._session = self._session, None
        if session is not None:
            session.close()

    def failure(self) -> str | None:
        return None
