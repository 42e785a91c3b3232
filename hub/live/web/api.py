"""The dashboard's HTTP API (JSON), its login routes and the middlewares every response passes.

Reading (open to anyone who reaches the address when `open_view`, else after a login):
``GET /api/view`` (the whole read model), ``/api/outputs``, ``/api/streams``, ``/api/plot``,
``/api/events``; ``GET /metrics`` (Prometheus, never behind a login: a scraper has none).

Acting (a login with the ``control`` role, this session's CSRF token in ``X-CSRF-Token``, an
Origin that is this page's, a JSON body; a ``view`` login is refused, 403):
``POST /api/alarms`` (ack, shelve, unshelve), ``/api/outputs`` (set, pulse, arm, disarm),
``/api/recorder`` (start, stop, split, snapshot). Each goes the command line's way, with
``user`` and ``host`` always replaced by the logged-in user and the client's address, so every
action's audit names who did it: alarms and recorder to the same ``handle`` the command line's
request reaches; outputs parsed by the command line's own parser
(`fleetdaq.hub.requests.parse_control_request`), the `ControlRequest` handed to
`CommandService.act`. The handlers block
(an edge being asked, the journal fsynced): they run on a worker pool, never on the loop.

Bad input is answered 400 with one line saying what is wrong (401 without a login, 403 for a
failed CSRF/Origin check or a view-role action, 404 for what does not exist, 413 for a body
over 64 KiB, 429 after repeated failed logins) and counted; an unexpected error is logged and
answered 500.
"""

from __future__ import annotations

import asyncio
import json
import logging
import math
import time
from collections.abc import Awaitable, Callable, Mapping
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Final, TypeVar, TypeVarTuple

from aiohttp import web
from aiohttp.typedefs import Middleware

from fleetdaq.hub.config.dashboard import DashboardConfig
from fleetdaq.hub.live.metrics import render_metrics
from fleetdaq.hub.live.web.auth import COOKIE, CSRF_HEADER, Auth, Session, csrf_ok, origin_problem
from fleetdaq.hub.live.web.events import LEVELS, EventFilter, EventTail
from fleetdaq.hub.live.web.parts import HubParts
from fleetdaq.hub.live.web.stats import WebStats
from fleetdaq.hub.read_model import JsonObject, to_jsonable
from fleetdaq.hub.requests import (
    AlarmAction,
    BadRequest,
    ControlAction,
    RecorderAction,
    parse_control_request,
)

log = logging.getLogger("fleetdaq.dashboard")

MAX_BODY = 64 * 1024
STATIC = Path(__file__).resolve().parent / "static"
ALARM_ACTIONS: Final = (AlarmAction.ACK, AlarmAction.SHELVE, AlarmAction.UNSHELVE)
OUTPUT_ACTIONS: Final = (
    ControlAction.SET,
    ControlAction.PULSE,
    ControlAction.ARM,
    ControlAction.DISARM,
)
RECORDER_ACTIONS: Final = (
    RecorderAction.START, RecorderAction.STOP, RecorderAction.SPLIT, RecorderAction.SNAPSHOT,
)  # fmt: skip
"""What the page may do (the command line may do more: list, read, disable, enable...)."""

SECURITY_HEADERS = {
    "Content-Security-Policy": (
        "default-src 'self'; connect-src 'self'; img-src 'self' data:; style-src 'self'; "
        "script-src 'self'; frame-ancestors 'none'; base-uri 'none'; form-action 'self'"
    ),
    "X-Content-Type-Options": "nosniff",
    "X-Frame-Options": "DENY",
    "Referrer-Policy": "same-origin",
}

Handler = Callable[[web.Request], Awaitable[web.StreamResponse]]
R = TypeVar("R")
Ts = TypeVarTuple("Ts")


def fail(status: int, message: str, **headers: str) -> web.HTTPException:
    """An HTTP error whose body is ``{"ok": false, "error": message}``."""
    body = json.dumps({"ok": False, "error": message})
    cls: type[web.HTTPException] = {
        400: web.HTTPBadRequest,
        401: web.HTTPUnauthorized,
        403: web.HTTPForbidden,
        404: web.HTTPNotFound,
        415: web.HTTPUnsupportedMediaType,
        429: web.HTTPTooManyRequests,
        501: web.HTTPNotImplemented,
        503: web.HTTPServiceUnavailable,
    }[status]
    return cls(text=body, content_type="application/json", headers=headers or None)


def client_address(request: web.Request) -> str:
    return request.remote or "unknown"


class Api:
    def __init__(
        self,
        parts: HubParts,
        cfg: DashboardConfig,
        auth: Auth,
        events: EventTail,
        stats: WebStats,
        pool: ThreadPoolExecutor,
        site: str,
    ) -> None:
        self.parts = parts
        self.cfg = cfg
        self.auth = auth
        self.events = events
        self.stats = stats
        self.pool = pool
        self.site = site
        self._login_slots = asyncio.Semaphore(2)
        """Password checks at once (each ~0.15 s of CPU and 64 MiB): the rest wait their turn."""

    def add_routes(self, app: web.Application) -> None:
        app.router.add_get("/", self.index)
        app.router.add_static("/static/", STATIC, follow_symlinks=False)
        app.router.add_get("/api/session", self.get_session)
        app.router.add_post("/api/login", self.login)
        app.router.add_post("/api/logout", self.logout)
        app.router.add_get("/api/view", self.view)
        app.router.add_get("/api/outputs", self.outputs)
        app.router.add_get("/api/streams", self.streams)
        app.router.add_get("/api/plot", self.plot)
        app.router.add_get("/api/events", self.event_tail)
        app.router.add_post("/api/alarms", self.alarms)
        app.router.add_post("/api/outputs", self.output_action)
        app.router.add_post("/api/recorder", self.recorder)
        if self.cfg.metrics:
            app.router.add_get("/metrics", self.metrics)

    # --- who is asking --------------------------------------------------------------------------

    def session_of(self, request: web.Request) -> Session | None:
        return self.auth.session(request.cookies.get(COOKIE))

    def viewer(self, request: web.Request) -> Session | None:
        """The session, if any; refuses (401) when viewing needs a login and there is none."""
        s = self.session_of(request)
        if s is None and not self.cfg.open_view:
            raise fail(401, "log in to view this dashboard")
        return s

    def same_origin(self, request: web.Request) -> None:
        h = request.headers
        why = origin_problem(h.get("Origin"), h.get("Referer"), h.get("Host"))
        if why:
            raise fail(403, f"refused: {why}")

    def actor(self, request: web.Request) -> Session:
        """The logged-in user of a state-changing request that passed the CSRF checks."""
        s = self.session_of(request)
        if s is None:
            raise fail(401, "log in first: actions need a login")
        self.same_origin(request)
        if not csrf_ok(s, request.headers.get(CSRF_HEADER)):
            raise fail(403, f"refused: missing or wrong {CSRF_HEADER} header (reload the page)")
        return s

    def controller(self, request: web.Request) -> Session:
        """`actor`, whose role may act: a ``view`` login is refused (403) with the reason."""
        s = self.actor(request)
        if not s.may_act:
            log.warning("dashboard: %s (view role) refused an action from %s", s.user,
                        client_address(request))  # fmt: skip
            raise fail(
                403,
                f"refused: {s.user} has the view role; acting needs the control role "
                f"(on the hub: fleetdaq users role {s.user} control)",
            )
        return s

    async def body(self, request: web.Request, allowed: tuple[str, ...]) -> JsonObject:
        if request.content_type != "application/json":
            raise fail(415, "send the request as application/json")
        raw = await request.read()  # at most client_max_size, else 413
        try:
            req = json.loads(raw or b"{}")
        except (ValueError, RecursionError):
            raise fail(400, "the body is not JSON") from None
        if not isinstance(req, dict):
            raise fail(400, "the body is not a JSON object")
        body: JsonObject = req
        unknown = sorted(set(map(str, req)) - set(allowed))
        if unknown:
            raise fail(400, f"unknown field(s): {', '.join(unknown)}")
        return body

    async def blocking(self, fn: Callable[[*Ts], R], *args: *Ts) -> R:
        return await asyncio.get_running_loop().run_in_executor(self.pool, fn, *args)

    # --- page and login ---------------------------------------------------------------------------

    async def index(self, request: web.Request) -> web.StreamResponse:
        return web.FileResponse(STATIC / "index.html", headers={"Cache-Control": "no-cache"})

    async def get_session(self, request: web.Request) -> web.Response:
        s = self.session_of(request)
        return web.json_response(
            {
                "ok": True,
                "site": self.site,
                "user": s.user if s else None,
                "role": s.role if s else None,
                "csrf": s.csrf if s else None,
                "open_view": self.cfg.open_view,
                "users_defined": bool(await self.blocking(self.auth.users.names)),
                "metrics": self.cfg.metrics,
            }
        )

    async def login(self, request: web.Request) -> web.Response:
        self.same_origin(request)  # a login from another site's page is refused (login CSRF)
        req = await self.body(request, ("user", "password"))
        user, password = req.get("user"), req.get("password")
        if not isinstance(user, str) or not user or len(user) > 64:
            raise fail(400, "user must be a name of 1 to 64 characters")
        if not isinstance(password, str) or not password or len(password) > 1024:
            raise fail(400, "password must be text of 1 to 1024 characters")
        address = client_address(request)
        async with self._login_slots:
            result = await self.blocking(self.auth.login, user, password, address)
        if result.retry_after_s > 0:
            raise fail(429, result.error, **{"Retry-After": str(math.ceil(result.retry_after_s))})
        if result.session is None:
            self._audit_login(False, user if result.known_user else None, address)
            raise fail(401, result.error)
        s = result.session
        self._audit_login(True, s.user, address)
        resp = web.json_response({"ok": True, "user": s.user, "role": s.role, "csrf": s.csrf})
        resp.set_cookie(
            COOKIE, s.token, httponly=True, samesite="Strict", path="/", secure=request.secure
        )
        return resp

    def _audit_login(self, ok: bool, user: str | None, address: str) -> None:
        """`user` None: the name typed is nobody's, and is never recorded (it may be a password
        typed into the wrong field); the client's address says where the try came from."""
        if ok:
            log.info("dashboard: %s logged in from %s", user, address)
            self.parts.bus.emit(
                logging.INFO, "dashboard", "login",
                f"{user} logged in to the dashboard from {address}", user=user, host=address,
            )  # fmt: skip
        elif self.auth.failures <= 100 or self.auth.failures % 100 == 0:
            who = repr(user) if user is not None else "an unknown user name"
            named = {"user": user} if user is not None else {}
            log.warning("dashboard: login refused for %s from %s", who, address)
            self.parts.bus.emit(
                logging.WARNING, "dashboard", "login_failed",
                f"dashboard login refused for {who} from {address} "
                f"({self.auth.failures} refused since the hub started)",
                host=address, **named,
            )  # fmt: skip

    async def logout(self, request: web.Request) -> web.Response:
        s = self.actor(request)
        self.auth.logout(s.token)
        resp = web.json_response({"ok": True})
        resp.del_cookie(COOKIE, path="/")
        return resp

    # --- reading ----------------------------------------------------------------------------------

    async def view(self, request: web.Request) -> web.Response:
        self.viewer(request)
        return web.json_response(to_jsonable(self.parts.snapshot()))

    async def outputs(self, request: web.Request) -> web.Response:
        self.viewer(request)
        rows = await self.blocking(self.parts.commands.listing)
        return web.json_response({"ok": True, "outputs": to_jsonable(rows)})

    async def streams(self, request: web.Request) -> web.Response:
        self.viewer(request)
        return web.json_response({"ok": True, "streams": self.parts.live_plots.streams()})

    async def plot(self, request: web.Request) -> web.Response:
        self.viewer(request)
        q = request.query
        stream = q.get("stream", "")
        channels = [c for c in q.get("channels", "").split(",") if c] or None
        try:
            width = int(q.get("width", "600"))
            span_s = float(q.get("span_s", "10"))
        except ValueError:
            raise fail(400, "width must be an integer and span_s a number") from None
        if not math.isfinite(span_s):
            raise fail(400, "span_s must be a finite number")
        info = self.parts.live_plots.streams().get(stream)
        if info is None:
            raise fail(404, f"no stream {stream!r} (NODE/STREAM)")
        unknown = [c for c in channels or [] if c not in info["channels"]]
        if unknown:
            raise fail(404, f"no stream {stream!r} channel(s) {', '.join(unknown)}")
        try:
            frame = self.parts.live_plots.frame(stream, channels, width, span_s)
        except ValueError as err:
            raise fail(400, str(err)) from None
        return web.json_response({"ok": True, **frame})

    async def event_tail(self, request: web.Request) -> web.Response:
        self.viewer(request)
        q = request.query
        level = q.get("level", "").lower()
        if level and level not in LEVELS:
            raise fail(400, f"level must be one of {', '.join(LEVELS)}")
        try:
            limit = int(q.get("limit", "200"))
            since = int(q.get("since", "0"))
        except ValueError:
            raise fail(400, "limit and since must be integers") from None
        if not 1 <= limit <= 2000:
            raise fail(400, "limit must be 1 to 2000")
        texts = {k: q.get(k, "") for k in ("node", "source", "text")}
        if any(len(v) > 200 for v in texts.values()):
            raise fail(400, "node, source and text are at most 200 characters")
        f = EventFilter(LEVELS.get(level, 0), texts["node"], texts["source"], texts["text"])
        events = self.events.query(f, limit) if not since else self.events.since(since, limit)
        if since:
            events = [e for e in events if f.matches(e)]
        return web.json_response(
            {"ok": True, "events": events, "last_seq": self.events.last_seq}
        )  # fmt: skip

    async def metrics(self, request: web.Request) -> web.Response:
        t0 = time.thread_time()
        body, content_type = render_metrics(self.parts.snapshot())
        self.stats.metrics_cpu_s += time.thread_time() - t0
        return web.Response(body=body, headers={"Content-Type": content_type})

    # --- acting -----------------------------------------------------------------------------------

    async def _act(
        self, request: web.Request, allowed: tuple[str, ...], actions: tuple[str, ...]
    ) -> JsonObject:
        """The body of an action by the logged-in control user: one of `actions`, its user and
        host those of the login and the client, whatever the body said (the audit names them)."""
        s = self.controller(request)
        req = await self.body(request, allowed)
        action = req.get("action")
        if action not in actions:
            raise fail(400, f"action must be one of {', '.join(actions)}")
        req["user"] = s.user
        req["host"] = client_address(request)
        self.stats.actions += 1
        return req

    @staticmethod
    def _answered(answer: Mapping[str, object]) -> web.Response:
        """The handler's answer: 400 when it says what was wrong, else 200."""
        status = 400 if answer.get("error") else 200
        return web.json_response(to_jsonable(answer), status=status)

    async def alarms(self, request: web.Request) -> web.Response:
        req = await self._act(request, ("action", "names", "all", "for_s", "note"), ALARM_ACTIONS)
        handle = self.parts.alarm_requests.handle
        return self._answered(await self.blocking(handle, json.dumps(req).encode()))

    async def output_action(self, request: web.Request) -> web.Response:
        req = await self._act(
            request, ("action", "output", "value", "pulse_s", "reason"), OUTPUT_ACTIONS
        )
        try:  # the command line's parser: the same checks, the same refusals
            parsed = parse_control_request(req)
        except BadRequest as err:
            return self._answered({"ok": False, "error": str(err)})
        return self._answered(await self.blocking(self.parts.commands.act, parsed))

    async def recorder(self, request: web.Request) -> web.Response:
        req = await self._act(request, ("action", "note"), RECORDER_ACTIONS)
        handle = self.parts.recorder_requests.handle
        return self._answered(await self.blocking(handle, json.dumps(req).encode()))


def middlewares(stats: WebStats) -> list[Middleware]:
    """Counting, JSON errors for the API, security headers on every answer."""

    @web.middleware
    async def guard(request: web.Request, handler: Handler) -> web.StreamResponse:
        stats.requests += 1
        resp: web.StreamResponse
        try:
            resp = await handler(request)
        except web.HTTPException as err:
            if err.status < 400:
                raise
            resp = _as_json(err)
        except asyncio.CancelledError:
            raise
        except Exception:
            stats.server_errors += 1
            log.exception("dashboard: %s %s failed", request.method, request.path)
            resp = web.json_response(
                {"ok": False, "error": "internal error (logged on the hub)"}, status=500
            )
        _count(stats, resp.status)
        if not resp.prepared:  # a WebSocket has sent its headers already
            _secure(resp)
        return resp

    return [guard]


def _count(stats: WebStats, status: int) -> None:
    if status == 401:
        stats.unauthorized += 1
    elif status == 403:
        stats.forbidden += 1
    if 400 <= status < 500:
        stats.bad_requests += 1


def _as_json(err: web.HTTPException) -> web.Response:
    """A refusal as the API's JSON shape (aiohttp's own 404, 405 and 413 included)."""
    if err.content_type == "application/json" and err.text:
        body = err.text
    else:
        message = {
            404: "no such page or API route",
            405: "method not allowed here",
            413: f"request body too large (at most {MAX_BODY} bytes)",
        }.get(err.status, err.reason)
        body = json.dumps({"ok": False, "error": message})
    headers = {
        k: v for k, v in err.headers.items() if k.lower() not in ("content-type", "content-length")
    }
    return web.Response(
        text=body, status=err.status, content_type="application/json", headers=headers
    )


def _secure(resp: web.StreamResponse) -> None:
    for k, v in SECURITY_HEADERS.items():
        resp.headers.setdefault(k, v)
    resp.headers.setdefault("Cache-Control", "no-store")
