"""The live view's slots: anonymous viewers cannot take the ones kept for logged-in users, nor
more than their share from one address. Real service, real WebSockets from several loopback
addresses (127.0.0.2, 127.0.0.3, ... all reach 127.0.0.1 on Linux)."""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import AsyncIterator, Callable
from typing import Any

import aiohttp
import pytest

from fleetdaq.contract.errors import ConfigError
from fleetdaq.hub.config.load import parse_config
from tests.web.conftest import Http, Web
from tests.web.test_api import _receive

MakeWeb = Callable[..., Web]


class Viewers:
    """Live sockets opened and kept open until the test ends (each closed on the way out)."""

    def __init__(self, port: int) -> None:
        self.port = port
        self.sessions: list[aiohttp.ClientSession] = []
        self.open: list[aiohttp.ClientWebSocketResponse] = []

    async def connect(self, source: str = "127.0.0.1", cookie: str = "") -> int:
        """101 when the view opened (it is kept), else the HTTP status it was refused with."""
        s = aiohttp.ClientSession(connector=aiohttp.TCPConnector(local_addr=(source, 0)))
        self.sessions.append(s)
        headers = {"Cookie": cookie} if cookie else {}
        try:
            ws = await s.ws_connect(f"http://127.0.0.1:{self.port}/api/live", headers=headers)
        except aiohttp.WSServerHandshakeError as err:
            return err.status
        self.open.append(ws)
        return 101

    async def close(self) -> None:
        for ws in self.open:
            with contextlib.suppress(Exception):
                await ws.close()
        for s in self.sessions:
            await s.close()


@contextlib.asynccontextmanager
async def viewers(web: Web) -> AsyncIterator[Viewers]:
    v = Viewers(web.port)
    try:
        yield v
    finally:
        await v.close()


def logged_in(web: Web, user: str) -> Http:
    http = web.client()
    assert http.login(user)[0] == 200
    return http


def test_anonymous_viewers_filling_the_slots_cannot_lock_out_a_logged_in_user(make_web: MakeWeb):
    web = make_web()  # the defaults: 64 slots, 16 kept for logins, 8 per address
    alice = logged_in(web, "alice")
    vera = logged_in(web, "vera")

    async def run() -> dict[str, Any]:
        async with viewers(web) as v:
            anonymous = [
                await v.connect(f"127.0.0.{2 + i // 8}") for i in range(64)
            ]  # 8 addresses, 8 each: everything the old limit let one crowd take
            alice_status = await v.connect(cookie=alice.cookie)
            (state,) = await _receive(v.open[-1], "state")
            vera_status = await v.connect(cookie=vera.cookie)
            return {
                "anonymous": anonymous, "alice": alice_status, "vera": vera_status,
                "state": state, "clients": web.service.stats.ws_clients,
            }  # fmt: skip

    got = asyncio.run(run())
    assert got["anonymous"].count(101) == 48, "all but the 16 kept for logged-in users"
    assert got["anonymous"][48:] == [503] * 16
    assert got["alice"] == 101, "the logged-in operator still gets a live view"
    assert got["state"]["view"]["site"] == "webtest"
    assert got["vera"] == 101, "a view-role login is a login: it may look"
    assert web.service.stats.ws_refused == 16


def test_one_address_gets_its_share_of_anonymous_views_and_the_next_is_told_why(
    make_web: MakeWeb,
):
    web = make_web(live="{max_clients: 10, reserved: 2, per_address: 3}")
    alice = logged_in(web, "alice")

    async def run() -> dict[str, Any]:
        async with viewers(web) as v:
            mine = [await v.connect("127.0.0.2") for _ in range(4)]
            other = await v.connect("127.0.0.3")
            from_mine_logged_in = await v.connect("127.0.0.2", cookie=alice.cookie)
            await v.open.pop(0).close()  # one of 127.0.0.2's anonymous views closes
            freed = await v.connect("127.0.0.2")
            return {"mine": mine, "other": other, "logged_in": from_mine_logged_in,
                    "freed": freed}  # fmt: skip

    got = asyncio.run(run())
    assert got["mine"] == [101, 101, 101, 429]
    assert got["other"] == 101, "another address has its own share"
    assert got["logged_in"] == 101, "the cap is for anonymous views only"
    assert got["freed"] == 101, "a closed view frees its slot"


def test_a_refused_live_view_is_told_why_and_what_to_do(make_web: MakeWeb):
    web = make_web(live="{max_clients: 2, reserved: 1, per_address: 5}")
    bob = logged_in(web, "bob")
    anyone = web.client()

    async def run() -> list[tuple[int, Any]]:
        async with viewers(web) as v:
            assert await v.connect() == 101
            # The slot check answers before the upgrade: a plain GET reads the refusal.
            no_login = anyone.get("/api/live")
            assert await v.connect(cookie=bob.cookie) == 101
            return [no_login, anyone.get("/api/live"), bob.get("/api/live")]

    got = asyncio.run(run())
    assert [(status, answer["error"]) for status, answer in got] == [
        (503, "every live view open without a login is taken (1); log in for one of the 1 "
              "kept for logged-in users"),
        (503, "every live view is taken (at most 2)"),
        (503, "every live view is taken (at most 2)"),
    ]  # fmt: skip
    assert web.service.stats.ws_refused == 3


@pytest.mark.parametrize(
    ("live", "says"),
    [
        ("{max_clients: 4, reserved: 4}", "reserved (4) must be less than max_clients (4)"),
        ("{per_address: 0}", "per_address"),
        ("{max_clients: 0}", "max_clients"),
        ("{slots: 3}", "slots"),
    ],
)
def test_slots_that_cannot_work_are_refused_at_load_naming_the_key(live: str, says: str):
    text = (
        f"site: s\nhub:\n  dashboard:\n    live: {live}\nnodes:\n  wec:\n    streams:\n"
        "      t8: {driver: wave_sim, rate_hz: 10, channels: [{name: heave, unit: m}]}\n"
    )
    with pytest.raises(ConfigError) as err:
        parse_config(text, "site.yaml")
    line = str(err.value)
    assert "\n" not in line
    assert "hub.dashboard.live" in line
    assert says in line
