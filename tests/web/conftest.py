"""Fixtures for the dashboard's tests without a browser: the real service on a loopback port,
with the real event bus, read model and live plots, and request handlers that keep what they
were asked (the hub's own are tested with the hub)."""

from __future__ import annotations

import dataclasses
import http.client
import json
import ssl
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from argon2 import PasswordHasher

from fleetdaq.contract.config.security import Role
from fleetdaq.contract.wire import BatchEncoder, read_header
from fleetdaq.hub.bus import EventBus
from fleetdaq.hub.config.load import parse_config
from fleetdaq.hub.live.plots import LivePlots
from fleetdaq.hub.live.web.parts import HubParts
from fleetdaq.hub.live.web.service import WebService
from fleetdaq.hub.live.web.users import write_users
from fleetdaq.hub.read_model import ReadModel
from fleetdaq.hub.recording.batch_feed import BatchFeed, FedBatch
from fleetdaq.hub.requests import ControlRequest
from fleetdaq.ptp.quality import UNSYNCED
from tests.procs import wait_until

CHEAP = PasswordHasher(time_cost=1, memory_cost=1024, parallelism=1)
"""Hashes that verify in about a millisecond: the parameters travel in the hash."""
PASSWORDS = {"alice": "alice-password", "bob": "bob-password", "vera": "vera-password"}
ROLES: dict[str, Role] = {"alice": "control", "bob": "control", "vera": "view"}
"""vera may look, not act."""

SITE = """\
site: webtest
hub:
  dashboard:
    enabled: true
    listen: 127.0.0.1:0
    users_file: {users}
    open_view: {open_view}
    metrics: {metrics}{tls}
nodes:
  wec:
    streams:
      t8:
        driver: wave_sim
        rate_hz: 1000
        scans_per_batch: 100
        channels: [{{name: heave, unit: m}}, {{name: surge, unit: m}}]
"""


class Recorded:
    """A request handler that keeps every request and answers as told."""

    def __init__(self, answer: dict[str, Any] | None = None) -> None:
        self.requests: list[dict[str, Any]] = []
        self.answer = answer or {"ok": True, "error": ""}

    def handle(self, raw: bytes) -> dict[str, Any]:
        self.requests.append(json.loads(raw))
        return self.answer


class Outputs(Recorded):
    """The outputs' handler: takes the request the page parsed (`ControlRequest`) and keeps
    it as a dict."""

    def act(self, request: ControlRequest) -> dict[str, Any]:
        self.requests.append(dataclasses.asdict(request))
        return self.answer

    def outputs(self) -> dict[str, Any]:
        return {}

    def listing(self) -> list[dict[str, Any]]:
        return []


@dataclass
class Http:
    """Plain HTTP to the service, with its session cookie and CSRF token once logged in."""

    port: int
    cookie: str = ""
    csrf: str = ""
    origin: str | None = None
    last_headers: dict[str, str] = field(default_factory=dict)
    tls: ssl.SSLContext | None = None
    """HTTPS, trusting what this context trusts."""
    set_cookie: str = ""
    """The last session cookie as the server set it, with its attributes."""

    def __post_init__(self) -> None:
        if self.origin is None:
            scheme = "https" if self.tls is not None else "http"
            self.origin = f"{scheme}://127.0.0.1:{self.port}"

    def request(
        self,
        method: str,
        path: str,
        body: Any = None,
        headers: dict[str, str] | None = None,
        raw: bytes | None = None,
    ) -> tuple[int, Any]:
        conn: http.client.HTTPConnection = (
            http.client.HTTPSConnection("127.0.0.1", self.port, timeout=20, context=self.tls)
            if self.tls is not None
            else http.client.HTTPConnection("127.0.0.1", self.port, timeout=20)
        )
        h = {"Content-Type": "application/json"} if (body is not None or raw is not None) else {}
        if self.origin and method == "POST":
            h["Origin"] = self.origin
        if self.cookie:
            h["Cookie"] = self.cookie
        if self.csrf and method == "POST":
            h["X-CSRF-Token"] = self.csrf
        h.update(headers or {})
        data = raw if raw is not None else (json.dumps(body).encode() if body is not None else None)
        conn.request(method, path, body=data, headers=h)
        r = conn.getresponse()
        text = r.read()
        self.last_headers = {k.lower(): v for k, v in r.getheaders()}
        cookie = r.getheader("Set-Cookie")
        if cookie and "fleetdaq_session=" in cookie:
            self.set_cookie = cookie
            value = cookie.split(";", 1)[0]
            self.cookie = "" if value.endswith("=") or '=""' in value else value
        conn.close()
        ctype = r.getheader("Content-Type") or ""
        return r.status, (json.loads(text) if "json" in ctype else text)

    def get(self, path: str) -> tuple[int, Any]:
        return self.request("GET", path)

    def post(self, path: str, body: Any = None, **kw: Any) -> tuple[int, Any]:
        return self.request("POST", path, body if body is not None else {}, **kw)

    def login(self, user: str, password: str | None = None) -> tuple[int, Any]:
        status, answer = self.post(
            "/api/login", {"user": user, "password": password or PASSWORDS[user]}
        )
        if status == 200:
            self.csrf = answer["csrf"]
        return status, answer


@dataclass
class Web:
    service: WebService
    bus: EventBus
    plots: LivePlots
    feed: BatchFeed
    alarms: Recorded
    commands: Outputs
    recorder: Recorded
    users_file: Path

    @property
    def port(self) -> int:
        assert self.service.bound_port is not None
        return self.service.bound_port

    def client(self, **kw: Any) -> Http:
        return Http(self.port, **kw)

    def feed_batches(self, count: int = 3) -> None:
        """Batches of the site's one stream into the live plots, as the recorder hands them."""
        enc = BatchEncoder("wec", "t8", ("heave", "surge"), ("m", "m"))
        t0 = time.time_ns() - count * 100_000_000
        for i in range(count):
            data = np.column_stack([np.arange(100.0) + 100 * i, -np.arange(100.0)])
            payload = bytes(enc.encode(i, t0 + i * 100_000_000, 1e6, data, UNSYNCED))
            self.feed.publish(
                FedBatch("wec", "t8", read_header(payload), payload, time.time_ns(), False)
            )
        wait_until(
            lambda: self.plots.streams()["wec/t8"]["latest_ns"] >= t0 + (count - 1) * 100_000_000,
            10,
            "the live plots to take the batches",
        )


def write_cheap_users(
    path: Path, passwords: dict[str, str], roles: dict[str, Role] | None = None
) -> None:
    write_users(path, {u: CHEAP.hash(p) for u, p in passwords.items()}, roles)


@pytest.fixture
def make_web(tmp_path: Path) -> Iterator[Callable[..., Web]]:
    started: list[tuple[WebService, EventBus, LivePlots]] = []

    def make(
        open_view: bool = True,
        metrics: bool = True,
        tls: tuple[Path, Path] | None = None,
        http_redirect: bool = False,
        live: str = "",
    ) -> Web:
        """`tls`: serve HTTPS with this certificate and key (`http_redirect`: and plain HTTP
        sent on to it from any free port); `live`: the live view's slots (YAML flow)."""
        users = tmp_path / "users"
        write_cheap_users(users, PASSWORDS, ROLES)
        text = SITE.format(
            users=users,
            open_view=str(open_view).lower(),
            metrics=str(metrics).lower(),
            tls=(f"\n    tls: {{cert_file: {tls[0]}, key_file: {tls[1]}}}" if tls else "")
            + ('\n    http_redirect: "127.0.0.1:0"' if http_redirect else "")
            + (f"\n    live: {live}" if live else ""),
        )
        site = parse_config(text, "<t>")
        bus = EventBus()
        feed = BatchFeed()
        plots = LivePlots(site, feed)
        model = ReadModel(site.site)
        alarms, commands, recorder = Recorded(), Outputs(), Recorded()
        parts = HubParts(
            snapshot=lambda: model.snapshot(time.time_ns()),
            alarm_requests=alarms,
            commands=commands,
            recorder_requests=recorder,
            live_plots=plots,
            bus=bus,
        )
        service = WebService(site, parts)
        bus.start()
        plots.start()
        service.start()
        started.append((service, bus, plots))
        return Web(service, bus, plots, feed, alarms, commands, recorder, users)

    yield make
    for service, bus, plots in started:
        service.stop()
        plots.stop()
        bus.stop()
