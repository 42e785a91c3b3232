"""The hub's web side in the site file (`hub.dashboard:`): the fleet health dashboard, its
Prometheus ``/metrics``, and the Foxglove live view.

Users and their password hashes never live in the site file: `users_file` names a file of
argon2 hashes and roles (`fleetdaq users add NAME --role view|control` writes it). Viewing may
be open to anyone who can reach the address (`open_view`); every action (ack, shelve, outputs,
rules, recorder) needs a login with the ``control`` role.
"""

from __future__ import annotations

import ipaddress
from typing import Annotated

from pydantic import AfterValidator, Field, model_validator

from fleetdaq.contract.schema import Float, Int, Strict


def check_listen(value: str) -> str:
    """``host:port`` (``[::1]:8080`` for IPv6) with an address, not a name: what is exposed
    must be said exactly. ``0.0.0.0:8080`` serves the whole LAN; port 0 takes any free port
    (the one bound is logged, and the demo prints it)."""
    host, sep, port = value.rpartition(":")
    if not sep or not port.isdigit() or not 0 <= int(port) < 65536:
        raise ValueError(f"{value!r} is not address:port (e.g. 127.0.0.1:8080, 0.0.0.0:8080)")
    try:
        ipaddress.ip_address(host.removeprefix("[").removesuffix("]"))
    except ValueError:
        raise ValueError(
            f"{host!r} in {value!r} is not an IP address (127.0.0.1 for this machine only, "
            "0.0.0.0 for every interface)"
        ) from None
    return value


Listen = Annotated[str, AfterValidator(check_listen)]


def split_listen(listen: str) -> tuple[str, int]:
    """``"127.0.0.1:8080"`` -> ("127.0.0.1", 8080); ``"[::1]:8080"`` -> ("::1", 8080) (a
    `Listen`, checked by the config)."""
    host, _, port = listen.rpartition(":")
    return host.removeprefix("[").removesuffix("]"), int(port)


def url_host(host: str) -> str:
    """The host to put in a URL for this machine's own browser or viewer (every interface:
    this machine's loopback; IPv6 in brackets)."""
    if host in ("0.0.0.0", ""):
        return "127.0.0.1"
    if host == "::":
        return "[::1]"
    return f"[{host}]" if ":" in host else host


class ServerTls(Strict):
    """TLS for a server the hub runs for people (the dashboard: HTTPS; the Foxglove live view:
    WSS). The site CA's hub pair serves (``pki_dir``'s ``hub.crt`` and ``hub.key``, made for
    the ``--hub-name``s browsers use) once ``ca.crt`` is trusted by the browsers; so does a
    certificate from any CA they already trust."""

    cert_file: str
    """The certificate (PEM; a chain: the server's first)."""
    key_file: str
    """Its private key (PEM, not encrypted); only its owner may read it (``chmod 600``)."""


def is_loopback(listen: str) -> bool:
    """Whether a `Listen` serves this machine only (127.0.0.0/8, ::1)."""
    return ipaddress.ip_address(split_listen(listen)[0]).is_loopback


class LiveSlots(Strict):
    """How many live views (``/api/live``) the dashboard serves at once, and how they are
    shared: a logged-in user always finds a slot free of anonymous viewers (`reserved`), and
    one address cannot hold every anonymous slot (`per_address`)."""

    max_clients: Annotated[Int, Field(ge=1, le=10_000)] = 64
    """Live views at once, logged in or not."""
    reserved: Annotated[Int, Field(ge=0)] = 16
    """Of those, the slots only logged-in users may take: anonymous viewers (`open_view`) get
    at most ``max_clients - reserved``."""
    per_address: Annotated[Int, Field(ge=1)] = 8
    """Anonymous live views from one client address at most. Behind a reverse proxy every
    viewer has the proxy's address: raise it, or close the view (`open_view: false`)."""

    @model_validator(mode="after")
    def _fits(self) -> LiveSlots:
        if self.reserved >= self.max_clients:
            raise ValueError(
                f"reserved ({self.reserved}) must be less than max_clients ({self.max_clients})"
            )
        return self


class FoxgloveConfig(Strict):
    """Foxglove (or Lichtblick) connects here with "Foxglove WebSocket" and sees every stream,
    the events, the alarms and the nodes' health live."""

    enabled: bool = False
    listen: Listen = "127.0.0.1:8765"
    tls: ServerTls | None = None
    """Serve ``wss://`` (what a page loaded over HTTPS may open) instead of ``ws://``."""


class DashboardConfig(Strict):
    enabled: bool = False
    """Off unless the site file says so: a hub opens no port but its router's without being
    asked (`fleetdaq demo`'s site turns it on)."""
    listen: Listen = "127.0.0.1:8080"
    """Where the dashboard and ``/metrics`` are served. The default serves this machine only;
    ``0.0.0.0:8080`` serves the LAN (put it behind the site's firewall)."""
    open_view: bool = True
    """Anyone who reaches the address may look; actions always need a login."""
    users_file: str | None = None
    """Users and their argon2 password hashes (default: ``<state dir>/dashboard-users``).
    No file: nobody can log in, so nothing can be done from the page."""
    session_ttl_s: Annotated[Float, Field(ge=60, le=7 * 24 * 3600)] = 12 * 3600.0
    """A login lasts this long without use (it is renewed by use)."""
    metrics: bool = True
    """Serve Prometheus ``/metrics`` (never needs a login: a scraper has none)."""
    tls: ServerTls | None = None
    """Serve HTTPS instead of HTTP (see `ServerTls`). Without it, expose the page beyond
    this machine only behind a TLS reverse proxy."""
    http_redirect: Listen | None = None
    """With `tls`: also listen for plain HTTP here (``0.0.0.0:8080``) and send every request on
    to the HTTPS address, path and query kept (307), so ``http://hub:8080`` typed from habit
    reaches the page. Nothing else is served on it."""
    live: LiveSlots = LiveSlots()
    """The live views' slots (see `LiveSlots`)."""
    foxglove: FoxgloveConfig = FoxgloveConfig()

    @model_validator(mode="after")
    def _foxglove_closed_with_the_view(self) -> DashboardConfig:
        # The Foxglove WebSocket protocol has no login and foxglove-sdk offers no hook to ask
        # for one: with the view closed, only this machine may reach it (an SSH tunnel).
        fox = self.foxglove
        if not self.open_view and fox.enabled and not is_loopback(fox.listen):
            raise ValueError(
                f"foxglove.listen {fox.listen} would show every stream to anyone who reaches "
                "it while open_view is false (the Foxglove protocol has no login): listen on "
                "127.0.0.1 and tunnel (ssh -L 8765:127.0.0.1:8765 hub), or open_view: true"
            )
        return self

    @model_validator(mode="after")
    def _redirect(self) -> DashboardConfig:
        if self.http_redirect is None:
            return self
        if self.tls is None:
            raise ValueError("http_redirect sends plain HTTP on to HTTPS: it needs tls")
        if split_listen(self.http_redirect)[1] == split_listen(self.listen)[1] != 0:
            raise ValueError(f"http_redirect and listen share port {split_listen(self.listen)[1]}")
        return self
