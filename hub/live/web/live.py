"""The dashboard's WebSocket (``/api/live``): the hub's state pushed once a second (nodes report
their health once a second), new events as they come, and the live plots each client asked for.

Server -> client (JSON text messages):

- ``{"type": "state", "view": <the read model, less its event tail>, "streams": <live values>,
  "outputs": <commands.listing()>, "dashboard": <the dashboard's counters>}`` at 1 Hz;
- ``{"type": "events", "events": [...]}``: the last events at connect, then what is new;
- a binary message per plot frame (`fleetdaq.hub.live.web.frames`: a JSON header with the client's
plot id,
  then min/max per pixel column as float32), sent as soon as its stream has new data (a stream
  of 100 ms batches plots at 10 frames/s). The first frame of a plot is whole, the next ones
  are deltas: only the columns recomputed since the frame that client was last sent;
- ``{"type": "error", "error": text}``: the client sent something that is not a valid request.

Client -> server: ``{"type": "plots", "plots": [{"id", "stream", "channels", "width",
"span_s"}, ...]}`` replaces that client's plots (at most 8).

Slots (`hub.dashboard.live`): at most ``max_clients`` sockets; anonymous viewers (`open_view`)
may hold all but ``reserved`` of them and at most ``per_address`` from one address, so a
logged-in user always finds a slot. A socket refused is answered before the upgrade: 503 when
the slots are taken, 429 when its address holds its share; each refusal is counted.

Each client has a bounded outbox: one pending state, one pending frame per plot, at most 500
pending events. A client slower than the hub's pace has its pending item replaced by the newer
one (counted as dropped), so it always gets the latest and never grows the hub's memory. The
state and each distinct frame are built and serialised once per tick for every client. A
pending frame that is replaced is rebuilt from what the client was last sent, so a delta never skips
one."""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import json
import logging
import math
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field

from aiohttp import WSCloseCode, WSMsgType, web

from fleetdaq.hub.bus import worth_telling
from fleetdaq.hub.config.dashboard import DashboardConfig
from fleetdaq.hub.live.plots import PlotFollower, StreamInfo
from fleetdaq.hub.live.web import frames, jsontext
from fleetdaq.hub.live.web.api import Api, client_address, fail
from fleetdaq.hub.live.web.events import EventJson, EventTail
from fleetdaq.hub.live.web.parts import HubParts
from fleetdaq.hub.live.web.stats import WebStats
from fleetdaq.hub.read_model import JsonObject

log = logging.getLogger("fleetdaq.dashboard")

STATE_PERIOD_S = 1.0
MAX_PLOTS = 8
MAX_CHANNELS = 16
MAX_WIDTH = 4000
MAX_BAD_MESSAGES = 50
PENDING_EVENTS = 500


ERROR_SLOT = "\0error"
"""The outbox slot of the last error message (no plot id can be this)."""

PlotKey = tuple[str, tuple[str, ...], int, float]
"""stream, channels, width, span: the plots that are the same for every client."""


@dataclass(frozen=True, slots=True)
class PlotRequest:
    id: str
    stream: str
    channels: tuple[str, ...]
    width: int
    span_s: float

    @property
    def key(self) -> PlotKey:
        return (self.stream, self.channels, self.width, self.span_s)


@dataclass(slots=True, eq=False)
class Client:
    ws: web.WebSocketResponse
    user: str
    stats: WebStats
    token: str = ""
    """The session it was opened with: with `open_view` off, the socket ends with it."""
    address: str = ""
    """The client's address (what the anonymous viewers' per-address share counts)."""
    ending: bool = False
    """Its sender closes the socket (4001: log in again) instead of sending more."""
    plots: dict[str, PlotRequest] = field(default_factory=dict)
    have: dict[str, int] = field(default_factory=dict)
    """Per plot id, the follower's version of the last frame taken out to be sent: what the
    next delta starts from."""
    state: str | None = None
    frames: dict[str, str | bytes] = field(default_factory=dict)
    frame_versions: dict[str, int] = field(default_factory=dict)
    """Per plot id, the follower's version a pending frame brings the client to."""
    events: deque[EventJson] = field(default_factory=lambda: deque(maxlen=PENDING_EVENTS))
    wake: asyncio.Event = field(default_factory=asyncio.Event)
    dropped: int = 0
    bad: int = 0

    def _drop(self, n: int = 1) -> None:
        self.dropped += n
        self.stats.ws_dropped += n

    def offer_state(self, text: str) -> None:
        if self.state is not None:
            self._drop()
        self.state = text
        self.wake.set()

    def offer_frame(self, plot: str, text: str | bytes, version: int = 0) -> None:
        if plot in self.frames:
            self._drop()
        self.frames[plot] = text
        if version:
            self.frame_versions[plot] = version
        self.wake.set()

    def queued(self, plot: str) -> int:
        """The version of `plot` this client has or will have once its outbox is sent."""
        return self.frame_versions.get(plot) or self.have.get(plot, 0)

    def new_plots(self, plots: list[PlotRequest]) -> None:
        """Its plots replaced: every plot starts again with a whole frame."""
        self.plots = {p.id: p for p in plots}
        self.have = {}
        self.frame_versions = {}
        self.frames = {k: v for k, v in self.frames.items() if k == ERROR_SLOT}

    def offer_events(self, events: list[EventJson]) -> None:
        overflow = len(self.events) + len(events) - PENDING_EVENTS
        if overflow > 0:
            self._drop(overflow)
        self.events.extend(events)
        self.wake.set()

    def take(self) -> list[str | bytes]:
        out: list[str | bytes] = []
        if self.state is not None:
            out.append(self.state)
            self.state = None
        if self.events:
            out.append(json.dumps({"type": "events", "events": list(self.events)}))
            self.events.clear()
        out.extend(self.frames.values())
        self.frames.clear()
        self.have.update(self.frame_versions)
        self.frame_versions.clear()
        return out


def parse_plots(msg: object, streams: dict[str, StreamInfo], window_s: float) -> list[PlotRequest]:
    """A client's ``plots`` message, checked against the site's streams; ValueError says why."""
    if not isinstance(msg, dict) or msg.get("type") != "plots":
        raise ValueError('expected {"type": "plots", "plots": [...]}')
    plots = msg.get("plots")
    if not isinstance(plots, list) or len(plots) > MAX_PLOTS:
        raise ValueError(f"plots must be a list of at most {MAX_PLOTS}")
    out: list[PlotRequest] = []
    for i, p in enumerate(plots):
        if not isinstance(p, dict) or set(p) - {"id", "stream", "channels", "width", "span_s"}:
            raise ValueError(f"plots[{i}]: an object with id, stream, channels, width, span_s")
        pid, stream, channels = p.get("id"), p.get("stream"), p.get("channels", [])
        width, span = p.get("width", 600), p.get("span_s", 10)
        if not isinstance(pid, str) or not 0 < len(pid) <= 32:
            raise ValueError(f"plots[{i}].id: text of 1 to 32 characters")
        info = streams.get(stream) if isinstance(stream, str) else None
        if info is None or not isinstance(stream, str):
            raise ValueError(f"plots[{i}].stream: no stream {stream!r} (NODE/STREAM)")
        if (
            not isinstance(channels, list)
            or len(channels) > MAX_CHANNELS
            or not all(isinstance(c, str) and c in info["channels"] for c in channels)
        ):
            raise ValueError(f"plots[{i}].channels: at most {MAX_CHANNELS} of {stream}'s channels")
        if isinstance(width, bool) or not isinstance(width, int) or not 1 <= width <= MAX_WIDTH:
            raise ValueError(f"plots[{i}].width: an integer from 1 to {MAX_WIDTH}")
        if (
            isinstance(span, bool)
            or not isinstance(span, int | float)
            or not math.isfinite(span)
            or not 0 < span <= window_s
        ):
            raise ValueError(f"plots[{i}].span_s: more than 0 and at most {window_s:g} s")
        out.append(PlotRequest(pid, stream, tuple(channels or info["channels"]), width, span))
    if len({p.id for p in out}) != len(out):
        raise ValueError("plot ids must differ")
    return out


class Live:
    def __init__(
        self,
        parts: HubParts,
        cfg: DashboardConfig,
        api: Api,
        events: EventTail,
        stats: WebStats,
        window_s: float = 60.0,
    ) -> None:
        self.parts = parts
        self.cfg = cfg
        self.api = api
        self.events = events
        self.stats = stats
        self.window_s = window_s
        self.clients: set[Client] = set()
        self._tasks: list[asyncio.Task[None]] = []
        self._senders: set[asyncio.Task[None]] = set()
        self._event_seq = 0
        self._followed: dict[PlotKey, _Followed] = {}
        self._new_data = asyncio.Event()
        self._listening = False
        self.closing = False

    def add_routes(self, app: web.Application) -> None:
        app.router.add_get("/api/live", self.websocket)

    def start(self) -> None:
        """Start the tickers (on the service's loop)."""
        self._event_seq = self.events.last_seq
        self._new_data = asyncio.Event()
        self._tasks = [
            asyncio.create_task(
                self._every(STATE_PERIOD_S, self._state_tick, "state_cpu_s"), name="dash-state"
            ),
            asyncio.create_task(self._frames(), name="dash-frames"),
        ]

    async def close(self) -> None:
        """Stop the tickers and say goodbye to every client (1001: going away)."""
        self.closing = True
        self.parts.live_plots.on_write(None)
        self._listening = False
        for t in self._tasks:
            t.cancel()
        for t in self._tasks:
            with contextlib.suppress(asyncio.CancelledError):
                await t
        for c in list(self.clients):
            with contextlib.suppress(Exception):
                await asyncio.wait_for(
                    c.ws.close(code=WSCloseCode.GOING_AWAY, message=b"hub stopping"), 2.0
                )
        for t in list(self._senders):
            t.cancel()

    # --- one client -------------------------------------------------------------------------------

    async def websocket(self, request: web.Request) -> web.StreamResponse:
        s = self.api.viewer(request)
        if request.headers.get("Origin") is not None:
            self.api.same_origin(request)  # another site's page may not read the live view
        if self.closing:
            raise fail(503, "the hub is stopping")
        address = client_address(request)
        self._admit(s is not None, address)
        # No per-message deflate: float32 noise hardly compresses and zlib costs the hub more
        # CPU than every other part of a frame (the link is a LAN, not a modem).
        ws = web.WebSocketResponse(heartbeat=20.0, max_msg_size=16 * 1024, compress=False)
        client = Client(ws, s.user if s else "", self.stats, s.token if s else "", address)
        # Held from here, not after the upgrade: sockets upgrading at once all count.
        self.clients.add(client)
        self.stats.ws_clients = len(self.clients)
        try:
            await ws.prepare(request)
        except BaseException:
            self.clients.discard(client)
            self.stats.ws_clients = len(self.clients)
            raise
        self.stats.ws_connections += 1
        sender = asyncio.create_task(self._send(client), name="dash-send")
        self._senders.add(sender)
        try:
            client.offer_events(self.events.since(0, 200))
            self._state_for(client)
            async for msg in ws:
                if msg.type == WSMsgType.TEXT:
                    self._on_message(client, msg.data)
                elif msg.type == WSMsgType.BINARY:
                    self._refuse(client, "binary messages are not understood")
                if client.bad > MAX_BAD_MESSAGES:
                    await ws.close(code=WSCloseCode.POLICY_VIOLATION, message=b"too many errors")
                    break
        except Exception:  # after the upgrade no HTTP answer can go out: log, close, go on
            self.stats.server_errors += 1
            log.exception("dashboard: a live connection failed")
            with contextlib.suppress(Exception):
                await ws.close(code=WSCloseCode.INTERNAL_ERROR, message=b"internal error")
        finally:
            self.clients.discard(client)
            self.stats.ws_clients = len(self.clients)
            self._new_data.set()  # what is plotted changed: the next tick says so
            sender.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await sender
            self._senders.discard(sender)
        return ws

    def _admit(self, logged_in: bool, address: str) -> None:
        """Refuse a new live view that has no slot (see the module's doc), with the reason."""
        slots = self.cfg.live
        if len(self.clients) >= slots.max_clients:
            self.stats.ws_refused += 1
            raise fail(503, f"every live view is taken (at most {slots.max_clients})")
        if logged_in:
            return
        anonymous = [c for c in self.clients if not c.user]
        if len(anonymous) >= slots.max_clients - slots.reserved:
            self.stats.ws_refused += 1
            raise fail(
                503,
                f"every live view open without a login is taken "
                f"({slots.max_clients - slots.reserved}); log in for one of the "
                f"{slots.reserved} kept for logged-in users",
            )
        if sum(c.address == address for c in anonymous) >= slots.per_address:
            self.stats.ws_refused += 1
            raise fail(
                429,
                f"{address} has {slots.per_address} live views open without a login already "
                "(the most one address may); close one, or log in",
            )

    def _on_message(self, client: Client, data: str) -> None:
        try:
            msg = json.loads(data)
        except (ValueError, RecursionError):
            self._refuse(client, "not JSON")
            return
        try:
            plots = parse_plots(msg, self.parts.live_plots.streams(), self.window_s)
        except ValueError as err:
            self._refuse(client, str(err))
            return
        client.new_plots(plots)
        self._new_data.set()  # its first frames now, not when the stream next writes

    def _refuse(self, client: Client, why: str) -> None:
        client.bad += 1
        self.stats.ws_bad_messages += 1
        with contextlib.suppress(Exception):
            client.offer_frame(ERROR_SLOT, json.dumps({"type": "error", "error": why}))

    async def _send(self, client: Client) -> None:
        ws = client.ws
        while not ws.closed:
            await client.wake.wait()
            client.wake.clear()
            if client.ending:
                await ws.close(code=4001, message=b"log in again")
                return
            for text in client.take():
                if ws.closed:
                    return
                t0 = time.thread_time()
                try:
                    if isinstance(text, bytes):
                        await ws.send_bytes(text)
                    else:
                        await ws.send_str(text)
                except (ConnectionError, RuntimeError):
                    return
                self.stats.send_cpu_s += time.thread_time() - t0
                self.stats.ws_sent += 1

    # --- the tickers ------------------------------------------------------------------------------

    async def _every(self, period: float, tick: Callable[[], None], cpu: str) -> None:
        loop = asyncio.get_running_loop()
        next_at = loop.time()
        while True:
            self._run(tick, cpu)
            next_at = max(next_at + period, loop.time())
            await asyncio.sleep(next_at - loop.time())

    async def _frames(self) -> None:
        """Frames when there is new data: the live plots call back after every batch they
        write (only while somebody plots), a client's new plots set it too."""
        while True:
            await self._new_data.wait()
            self._new_data.clear()
            self._run(self._frame_tick, "frames_cpu_s")

    def _run(self, tick: Callable[[], None], cpu: str) -> None:
        t0 = time.thread_time()
        try:
            tick()
        except Exception:
            self.stats.tick_errors += 1
            if worth_telling(self.stats.tick_errors, first=10):
                log.exception("dashboard: a live update failed (%d so far)",
                              self.stats.tick_errors)  # fmt: skip
        setattr(self.stats, cpu, getattr(self.stats, cpu) + time.thread_time() - t0)

    def _listen(self, on: bool) -> None:
        """Be called back by the live plots while any client plots (nothing costs otherwise)."""
        if on == self._listening:
            return
        self._listening = on
        if on:
            loop, new_data = asyncio.get_running_loop(), self._new_data

            def poke() -> None:
                with contextlib.suppress(RuntimeError):  # the loop closed meanwhile
                    loop.call_soon_threadsafe(new_data.set)

            self.parts.live_plots.on_write(poke)
        else:
            self.parts.live_plots.on_write(None)

    def _state_text(self) -> str:
        view = self.parts.snapshot()
        outputs = self.parts.commands.listing() if self.parts.commands.outputs() else []
        return jsontext.dumps(
            {
                "type": "state",
                "view": dataclasses.replace(view, recent_events=()),
                "streams": self.parts.live_plots.streams(),
                "outputs": outputs,
                "dashboard": self.stats.to_dict(),
                "sent_ns": time.time_ns(),
            }
        )

    def _state_for(self, client: Client) -> None:
        client.offer_state(self._state_text())

    def _state_tick(self) -> None:
        self.stats.loop_cpu_s = time.thread_time()
        if not self.clients:
            self._event_seq = self.events.last_seq
            return
        text = self._state_text()
        new = self.events.since(self._event_seq, PENDING_EVENTS)
        if new:
            self._event_seq = new[-1]["seq"]
        for c in list(self.clients):
            if not self.cfg.open_view and not self.api.auth.valid(c.token):
                # Logged out or expired: no more looking. 4001: the page shows its login.
                c.ending = True
                c.wake.set()
                continue
            c.offer_state(text)
            if new:
                c.offer_events(new)

    def _frame_tick(self) -> None:
        wanted = [(c, p) for c in self.clients if not c.ending for p in c.plots.values()]
        followed = self._followed
        keys = {p.key for _, p in wanted}
        for key in [k for k in followed if k not in keys]:
            del followed[key]  # nobody plots it any more
        self._listen(bool(keys))
        self.parts.live_plots.demand(frozenset(p.stream for _, p in wanted))
        updated: set[PlotKey] = set()
        for c, p in wanted:
            f = followed.get(p.key)
            if f is None:
                f = followed[p.key] = _Followed(
                    self.parts.live_plots.follow(p.stream, list(p.channels), p.width, p.span_s)
                )
            follower = f.follower
            if p.key not in updated:
                updated.add(p.key)
                f.packed.clear()
                f.messages.clear()
                if follower.update():  # only the columns new data touched are recomputed
                    self.stats.frames_computed += 1
            if follower.version == 0 or c.queued(p.id) == follower.version:
                continue  # no data yet, or nothing new for this client
            since = c.have.get(p.id, 0)
            msg = f.messages.get((p.id, since))
            if msg is None:
                packed = f.packed.get(since)
                if packed is None:
                    packed = f.packed[since] = frames.pack_columns(follower.delta(since))
                msg = f.messages[(p.id, since)] = frames.message(p.id, *packed)
            c.offer_frame(p.id, msg, follower.version)


@dataclass(slots=True)
class _Followed:
    """A plot some client shows, followed once for every client that shows it; what a tick
    packed of it is shared by every client that holds the same version."""

    follower: PlotFollower
    packed: dict[int, tuple[JsonObject, bytes]] = field(default_factory=dict)
    messages: dict[tuple[str, int], bytes] = field(default_factory=dict)
