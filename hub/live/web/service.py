"""The dashboard as a hub service: an aiohttp application on a thread of its own, with its own
asyncio loop, serving the page, its JSON API, the live WebSocket and ``/metrics`` on
``hub.dashboard.listen``.

`start` returns once the socket is bound (a taken port is a `DashboardError` with one line: the
hub does not start). `stop` closes every WebSocket (1001, going away), lets requests in
progress finish, and ends the thread. `failure` names a loop thread that died. Nothing here
runs on another service's thread: the blocking requests go to a small pool of its own.
"""

from __future__ import annotations

import asyncio
import contextlib
import errno
import logging
import ssl
import threading
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from aiohttp import web

from fleetdaq.hub.config.dashboard import split_listen, url_host
from fleetdaq.hub.config.site import SiteConfig
from fleetdaq.hub.errors import HubError
from fleetdaq.hub.live import server_tls
from fleetdaq.hub.live.web.api import MAX_BODY, Api, middlewares
from fleetdaq.hub.live.web.auth import Auth
from fleetdaq.hub.live.web.events import EventTail
from fleetdaq.hub.live.web.live import Live
from fleetdaq.hub.live.web.parts import HubParts
from fleetdaq.hub.live.web.stats import WebStats
from fleetdaq.hub.live.web.users import UsersFile, default_users_file
from fleetdaq.runtime.threads import NamedThread, name_os_thread

log = logging.getLogger("fleetdaq.dashboard")

START_TIMEOUT_S = 30.0
STOP_TIMEOUT_S = 15.0


def new_loop() -> asyncio.AbstractEventLoop:
    """uvloop's loop (in the hub extra): its loop, transports and timers are C, and the
    dashboard's thread takes about a fifth less CPU on it than on asyncio's own
    (bench/dashboard.py); asyncio's where uvloop is not installed."""
    try:
        import uvloop
    except ImportError:
        return asyncio.new_event_loop()
    return uvloop.new_event_loop()


class DashboardError(HubError):
    """The dashboard cannot serve (its address is taken or not on this machine)."""


class WebService:
    name = "dashboard"

    def __init__(self, site: SiteConfig, parts: HubParts) -> None:
        self.cfg = site.hub.dashboard
        self.site = site.site
        self.parts = parts
        path = Path(self.cfg.users_file) if self.cfg.users_file else default_users_file()
        self.users = UsersFile(path)
        self.auth = Auth(self.users, self.cfg.session_ttl_s)
        self.events = EventTail(parts.bus)  # subscribed now: sees the hub's first events
        self.stats = WebStats()
        self.host, self.port = split_listen(self.cfg.listen)
        self.bound_port: int | None = None
        self.redirect_port: int | None = None
        """`http_redirect`'s port, once bound."""
        self._thread: threading.Thread | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._stop: asyncio.Event | None = None
        self._ready = threading.Event()
        self._error: BaseException | None = None
        self._pool: ThreadPoolExecutor | None = None
        self._running = False
        self._ssl: ssl.SSLContext | None = None

    @property
    def url(self) -> str:
        """The page's address (``http://127.0.0.1:8080/``, ``https://`` with `tls`), with the
        port actually bound."""
        scheme = "https" if self.cfg.tls is not None else "http"
        return f"{scheme}://{url_host(self.host)}:{self.bound_port or self.port}/"

    # --- lifecycle ----------------------------------------------------------------------------

    def start(self) -> None:
        if self._running:
            return
        self.users.check()
        tls = self.cfg.tls
        self._ssl = server_tls.load(tls, "hub.dashboard.tls").context if tls else None
        self._pool = ThreadPoolExecutor(
            4, thread_name_prefix="dash-work", initializer=name_os_thread
        )
        self._ready.clear()
        self._error = None
        self._thread = NamedThread(target=self._run, name="dashboard", daemon=True)
        self._thread.start()
        if not self._ready.wait(START_TIMEOUT_S):
            self.stop()
            raise DashboardError(f"dashboard: not serving on {self.cfg.listen} after 30 s")
        if self._error is not None:
            err = self._error
            self._thread.join(STOP_TIMEOUT_S)
            self._pool.shutdown(wait=False)
            raise DashboardError(self._why(err)) from err
        self._running = True
        log.info("dashboard on %s (users file %s)", self.url, self.users.path)

    def _why(
        self, err: BaseException, listen: str | None = None, key: str = "hub.dashboard.listen"
    ) -> str:
        if isinstance(err, DashboardError):  # said already (the redirect's port)
            return str(err)
        where = f"dashboard: cannot listen on {listen or self.cfg.listen}"
        code = err.errno if isinstance(err, OSError) else None
        if code == errno.EADDRINUSE:
            return (
                f"{where}: the address is in use (another hub or program); set "
                f"{key} to a free port, or hub.dashboard.enabled: false"
            )
        if code == errno.EADDRNOTAVAIL:
            return f"{where}: that address is not one of this machine's"
        if code == errno.EACCES:
            return f"{where}: permission denied (ports below 1024 need privileges)"
        return f"{where}: {err}"

    def stop(self) -> None:
        """Close every client, let requests in progress finish, end the thread. Idempotent."""
        loop, stop, thread = self._loop, self._stop, self._thread
        if loop is not None and stop is not None and thread is not None and thread.is_alive():
            with contextlib.suppress(RuntimeError):  # the loop already closed
                loop.call_soon_threadsafe(stop.set)
            thread.join(STOP_TIMEOUT_S)
            if thread.is_alive():
                log.error("dashboard: its thread did not stop within %g s", STOP_TIMEOUT_S)
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool = None
        self._running = False

    def failure(self) -> str | None:
        if self._running and self._thread is not None and not self._thread.is_alive():
            return "the dashboard's event loop thread died"
        return None

    # --- the loop's thread ----------------------------------------------------------------------

    def _run(self) -> None:
        loop = new_loop()
        self._loop = loop
        try:
            loop.run_until_complete(self._main())
        except BaseException as err:  # reported by start(), or by failure() once running
            if not self._ready.is_set():
                self._error = err
            else:
                log.exception("dashboard: its event loop failed")
        finally:
            self._ready.set()
            loop.close()

    async def _main(self) -> None:
        assert self._pool is not None
        self._stop = asyncio.Event()
        app = web.Application(client_max_size=MAX_BODY, middlewares=middlewares(self.stats))
        api = Api(self.parts, self.cfg, self.auth, self.events, self.stats, self._pool, self.site)
        api.add_routes(app)
        live = Live(self.parts, self.cfg, api, self.events, self.stats)
        live.add_routes(app)
        runner = web.AppRunner(app, access_log=None, shutdown_timeout=5.0)
        await runner.setup()
        runners = [runner]
        try:
            site = web.TCPSite(runner, self.host, self.port, backlog=128, ssl_context=self._ssl)
            await site.start()
            self.bound_port = int(runner.addresses[0][1])
            if self.cfg.http_redirect is not None:
                redirect = await self._redirect_runner(self.cfg.http_redirect)
                runners.append(redirect)
            live.start()
            self._ready.set()
            await self._stop.wait()
            await live.close()
        finally:
            for r in reversed(runners):
                await r.cleanup()

    async def _redirect_runner(self, listen: str) -> web.AppRunner:
        """Plain HTTP on `listen`: every request sent on to the same path over HTTPS."""
        tls_port = self.bound_port

        async def redirect(request: web.Request) -> web.StreamResponse:
            target: object
            try:  # the name the person typed (the Host header), else this hub's own address
                target = request.url.with_scheme("https").with_port(tls_port)
            except ValueError:
                target = self.url.rstrip("/") + str(request.rel_url)
            self.stats.redirects += 1
            raise web.HTTPTemporaryRedirect(str(target))

        app = web.Application()
        app.router.add_route("*", "/{tail:.*}", redirect)
        runner = web.AppRunner(app, access_log=None, shutdown_timeout=1.0)
        await runner.setup()
        host, port = split_listen(listen)
        try:
            await web.TCPSite(runner, host, port, backlog=16).start()
        except OSError as err:
            await runner.cleanup()
            raise DashboardError(self._why(err, listen, "hub.dashboard.http_redirect")) from err
        except BaseException:
            await runner.cleanup()
            raise
        self.redirect_port = int(runner.addresses[0][1])
        log.info("dashboard: plain HTTP on %s sent on to %s", listen, self.url)
        return runner
