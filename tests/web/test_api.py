"""The dashboard's HTTP API and WebSocket without a browser: the real service on a loopback port,
with plain HTTP and aiohttp's WebSocket client."""

from __future__ import annotations

import asyncio
import json
import logging
import math
import socket
from collections.abc import Callable
from pathlib import Path
from typing import Any

import aiohttp
import numpy as np
import pytest

from fleetdaq.hub.live.web import frames
from fleetdaq.hub.live.web.live import Client
from fleetdaq.hub.live.web.service import DashboardError, WebService
from fleetdaq.hub.live.web.stats import WebStats
from tests.procs import wait_until
from tests.web.conftest import Web

MakeWeb = Callable[..., Web]


def test_viewing_is_open_but_acting_needs_a_login(make_web: MakeWeb):
    web = make_web()
    http = web.client()
    status, view = http.get("/api/view")
    assert status == 200
    assert view["site"] == "webtest"
    status, answer = http.post("/api/alarms", {"action": "ack", "names": ["x"]})
    assert (status, answer["error"]) == (401, "log in first: actions need a login")
    assert web.alarms.requests == []


def test_with_open_view_off_even_looking_needs_a_login(make_web: MakeWeb):
    web = make_web(open_view=False)
    http = web.client()
    assert http.get("/api/view")[0] == 401
    assert http.get("/api/events")[0] == 401
    status, session = http.get("/api/session")
    assert status == 200
    assert session["open_view"] is False
    assert session["user"] is None
    assert http.get("/")[0] == 200, "the page itself loads, to show the login"
    http.login("alice")
    assert http.get("/api/view")[0] == 200


def test_an_action_names_the_logged_in_user_and_their_address_whatever_the_body_says(
    make_web: MakeWeb,
):
    web = make_web()
    http = web.client()
    assert http.login("alice")[0] == 200
    status, _ = http.post(
        "/api/alarms", {"action": "ack", "names": ["mooring_load"], "note": "seen", "user": "eve"}
    )
    assert status == 400, "a body may not name its own user"
    status, answer = http.post("/api/alarms", {"action": "ack", "names": ["mooring_load"]})
    assert (status, answer["ok"]) == (200, True)
    status, _ = http.post("/api/recorder", {"action": "split"})
    assert status == 200
    status, _ = http.post("/api/outputs", {"action": "set", "output": "wec/valve", "value": 2})
    assert status == 200
    (alarm,) = web.alarms.requests
    assert alarm == {
        "action": "ack", "names": ["mooring_load"], "user": "alice", "host": "127.0.0.1"
    }  # fmt: skip
    assert web.recorder.requests == [{"action": "split", "user": "alice", "host": "127.0.0.1"}]
    assert web.commands.requests[0]["user"] == "alice"


def test_an_output_request_reaches_the_hub_parsed_by_its_own_parser(make_web: MakeWeb):
    web = make_web()
    http = web.client()
    http.login("alice")
    status, answer = http.post(
        "/api/outputs", {"action": "pulse", "output": "wec/valve", "value": 1}
    )
    assert (status, answer) == (
        400, {"ok": False, "error": "a pulse lasts more than 0 s and at most 3600 s"}
    )  # fmt: skip
    assert web.commands.requests == [], "refused before the hub is asked"
    body = {"action": "pulse", "output": "wec/valve", "value": 1, "pulse_s": 2, "reason": "purge"}
    assert http.post("/api/outputs", body)[0] == 200
    assert web.commands.requests == [
        {"action": "pulse", "output": "wec/valve", "value": 1.0, "pulse_s": 2.0,
         "reason": "purge", "user": "alice", "host": "127.0.0.1", "command_id": None}
    ]  # fmt: skip


def test_an_action_without_the_sessions_csrf_token_or_from_another_origin_is_refused(
    make_web: MakeWeb,
):
    web = make_web()
    http = web.client()
    http.login("alice")
    token = http.csrf
    http.csrf = ""
    status, answer = http.post("/api/recorder", {"action": "split"})
    assert status == 403
    assert "X-CSRF-Token" in answer["error"]
    http.csrf = "x" * len(token)
    assert http.post("/api/recorder", {"action": "split"})[0] == 403
    http.csrf = token
    status, answer = http.post(
        "/api/recorder", {"action": "split"}, headers={"Origin": "http://evil.example"}
    )
    assert status == 403
    assert "evil.example" in answer["error"]
    other = web.client(origin="")  # neither Origin nor Referer
    other.cookie, other.csrf = http.cookie, http.csrf
    assert other.post("/api/recorder", {"action": "split"})[0] == 403
    assert web.recorder.requests == []
    assert http.post("/api/recorder", {"action": "split"})[0] == 200
    assert len(web.recorder.requests) == 1
    assert web.service.stats.forbidden == 4


def test_a_login_from_another_origin_is_refused(make_web: MakeWeb):
    web = make_web()
    http = web.client(origin="http://evil.example")
    status, _answer = http.login("alice")
    assert status == 403
    assert http.cookie == ""


def test_a_login_gives_an_httponly_samesite_strict_cookie_and_logout_ends_it(make_web: MakeWeb):
    web = make_web()
    http = web.client()
    status, answer = http.login("bob")
    assert status == 200
    assert answer["user"] == "bob"
    cookie = http.last_headers["set-cookie"]
    assert "HttpOnly" in cookie
    assert "SameSite=Strict" in cookie
    assert "Path=/" in cookie
    assert http.get("/api/session")[1]["user"] == "bob"
    cookie_value = http.cookie
    assert http.post("/api/logout")[0] == 200
    http.cookie = cookie_value  # a copy kept by someone: dead on the server all the same
    assert http.get("/api/session")[1]["user"] is None
    assert http.post("/api/recorder", {"action": "split"})[0] == 401


def test_wrong_passwords_are_refused_then_rate_limited(make_web: MakeWeb):
    web = make_web()
    http = web.client()
    statuses = [http.login("alice", "wrong password")[0] for _ in range(5)]
    assert statuses == [401] * 5
    status, answer = http.login("alice")
    assert status == 429
    assert "too many failed logins" in answer["error"]
    assert int(http.last_headers["retry-after"]) > 0
    assert web.service.auth.failures == 5


@pytest.mark.parametrize(
    ("path", "body", "raw", "headers", "status", "says"),
    [
        ("/api/alarms", None, b"{not json", None, 400, "not JSON"),
        ("/api/alarms", [1, 2], None, None, 400, "not a JSON object"),
        ("/api/alarms", {"action": "disable", "names": ["a"]}, None, None, 400, "ack, shelve"),
        ("/api/alarms", {"action": "ack", "names": ["a"], "x": 1}, None, None, 400, "x"),
        ("/api/outputs", {"action": "read", "output": "a/b"}, None, None, 400, "set, pulse"),
        ("/api/recorder", {"action": "erase"}, None, None, 400, "start, stop"),
        ("/api/recorder", None, b"action=split", {"Content-Type": "text/plain"}, 415, "json"),
        ("/api/recorder", None, b"{" + b" " * 70_000 + b"}", None, 413, "too large"),
        ("/api/nothing", {}, None, None, 404, "no such page"),
    ],
)
def test_bad_input_is_refused_with_one_clear_line_and_counted(
    make_web: MakeWeb,
    path: str,
    body: Any,
    raw: bytes | None,
    headers: dict[str, str] | None,
    status: int,
    says: str,
):
    web = make_web()
    http = web.client()
    http.login("alice")
    before = web.service.stats.bad_requests
    got, answer = http.request("POST", path, body, headers=headers, raw=raw)
    assert got == status, answer
    assert says in answer["error"]
    assert web.service.stats.bad_requests == before + 1
    assert web.alarms.requests == web.recorder.requests == web.commands.requests == []
    assert web.service.failure() is None
    assert http.get("/api/session")[0] == 200, "the service goes on"


def test_a_refusal_by_the_hub_is_passed_on_as_400_with_its_reason(make_web: MakeWeb):
    web = make_web()
    web.alarms.answer = {"ok": False, "error": "no alarm matches nope", "results": []}
    http = web.client()
    http.login("alice")
    status, answer = http.post("/api/alarms", {"action": "ack", "names": ["nope"]})
    assert (status, answer["error"]) == (400, "no alarm matches nope")


@pytest.mark.parametrize(
    ("query", "status", "says"),
    [
        ("stream=wec/t8&channels=heave&width=0&span_s=5", 400, "width"),
        ("stream=wec/t8&channels=heave&width=10&span_s=0", 400, "span"),
        ("stream=wec/t8&channels=heave&width=10&span_s=nan", 400, "finite"),
        ("stream=wec/t8&channels=heave&width=ten&span_s=5", 400, "integer"),
        ("stream=wec/none&width=10&span_s=5", 404, "no stream"),
        ("stream=wec/t8&channels=depth&width=10&span_s=5", 404, "no stream"),
    ],
)
def test_bad_plot_requests_are_refused(make_web: MakeWeb, query: str, status: int, says: str):
    web = make_web()
    got, answer = web.client().get(f"/api/plot?{query}")
    assert got == status
    assert says in answer["error"]


def test_a_plot_is_min_and_max_per_pixel_column_of_what_arrived(make_web: MakeWeb):
    web = make_web()
    web.feed_batches(3)
    status, frame = web.client().get("/api/plot?stream=wec/t8&channels=heave&width=3&span_s=0.3")
    assert status == 200
    assert frame["width"] == 3
    heave = frame["channels"]["heave"]
    assert heave["unit"] == "m"
    assert max(v for v in heave["max"] if v is not None) == 299.0


def test_the_event_tail_filters_by_level_node_source_and_text(make_web: MakeWeb):
    web = make_web()
    web.bus.emit(logging.INFO, "recorder", "split", "file closed")
    web.bus.emit(logging.WARNING, "alarms", "alarm_raised", "mooring_load raised")
    web.bus.emit(logging.ERROR, "alarms", "alarm_raised", "substrate_hot raised")
    http = web.client()
    wait_until(lambda: len(http.get("/api/events")[1]["events"]) == 3, 10, "three events")
    msgs = [e["message"] for e in http.get("/api/events?level=warning")[1]["events"]]
    assert msgs == ["mooring_load raised", "substrate_hot raised"]
    assert [e["message"] for e in http.get("/api/events?source=recorder")[1]["events"]] == [
        "file closed"
    ]
    assert [e["message"] for e in http.get("/api/events?text=SUBSTRATE")[1]["events"]] == [
        "substrate_hot raised"
    ]
    assert http.get("/api/events?node=wec")[1]["events"] == []
    assert http.get("/api/events?level=loud")[0] == 400
    assert http.get("/api/events?limit=0")[0] == 400


def test_metrics_need_no_login_even_when_viewing_does(make_web: MakeWeb):
    web = make_web(open_view=False)
    http = web.client()
    status, body = http.get("/metrics")
    assert status == 200
    assert b'fleetdaq_site_info{site="webtest"} 1.0' in body
    assert http.last_headers["content-type"].startswith("text/plain; version=")


def test_metrics_switched_off_are_not_served(make_web: MakeWeb):
    assert make_web(metrics=False).client().get("/metrics")[0] == 404


def test_a_taken_port_fails_the_start_with_one_line(make_web: MakeWeb):
    web = make_web()
    taken = web.port
    cfg = web.service.cfg.model_copy(update={"listen": f"127.0.0.1:{taken}"})
    second = WebService(_site_with(web, cfg), web.service.parts)  # a second one, same port
    with pytest.raises(DashboardError) as err:
        second.start()
    assert str(err.value).startswith(f"dashboard: cannot listen on 127.0.0.1:{taken}: ")
    assert "in use" in str(err.value)
    assert "\n" not in str(err.value)
    second.stop()  # idempotent after a failed start
    assert web.client().get("/api/session")[0] == 200, "the first one is untouched"


def _site_with(web: Web, cfg: Any) -> Any:
    from fleetdaq.hub.config.load import parse_config
    from tests.web.conftest import SITE

    text = SITE.format(users=web.users_file, open_view="true", metrics="true", tls="")
    site = parse_config(text, "<t>")
    return site.model_copy(update={"hub": site.hub.model_copy(update={"dashboard": cfg})})


def test_a_port_held_by_another_program_is_refused_too(make_web: MakeWeb):
    web = make_web()
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        port = s.getsockname()[1]
        cfg = web.service.cfg.model_copy(update={"listen": f"127.0.0.1:{port}"})
        with pytest.raises(DashboardError, match="the address is in use"):
            WebService(_site_with(web, cfg), web.service.parts).start()


def test_a_redirect_port_held_by_another_program_is_said_by_its_own_setting(
    make_web: MakeWeb, tmp_path: Path
) -> None:
    from fleetdaq import pki

    pki.init(tmp_path / "pki", "webtest", ["127.0.0.1"])
    tls = {
        "cert_file": str(tmp_path / "pki" / "hub.crt"),
        "key_file": str(tmp_path / "pki" / "hub.key"),
    }
    web = make_web()
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        port = s.getsockname()[1]
        cfg = web.service.cfg.model_validate(
            {**web.service.cfg.model_dump(), "tls": tls, "http_redirect": f"127.0.0.1:{port}"}
        )
        with pytest.raises(DashboardError) as err:
            WebService(_site_with(web, cfg), web.service.parts).start()
    assert str(err.value) == (
        f"dashboard: cannot listen on 127.0.0.1:{port}: the address is in use (another hub or "
        "program); set hub.dashboard.http_redirect to a free port, or hub.dashboard.enabled: false"
    )


# --- the WebSocket ----------------------------------------------------------------------------


SURGE_PLOT = json.dumps(
    {"type": "plots", "plots": [
        {"id": "a", "stream": "wec/t8", "channels": ["surge"], "width": 50, "span_s": 1}]}
)  # fmt: skip


async def _receive(
    ws: aiohttp.ClientWebSocketResponse,
    kind: str,
    n: int = 1,
    plot: frames.Assembler | None = None,
) -> list[Any]:
    """The next `n` messages of `kind`; frames also go to `plot`."""
    out: list[Any] = []
    while len(out) < n:
        msg = await asyncio.wait_for(ws.receive(), 20)
        if msg.type == aiohttp.WSMsgType.BINARY:
            data = frames.unpack(msg.data)
            if plot is not None:
                assert plot.apply(msg.data), "every frame applies to the one before"
        else:
            assert msg.type == aiohttp.WSMsgType.TEXT, msg
            data = json.loads(msg.data)
        if data["type"] == kind:
            out.append(data)
    return out


def test_the_live_socket_pushes_state_events_and_the_plots_asked_for(make_web: MakeWeb):
    web = make_web()
    web.feed_batches(2)
    web.bus.emit(logging.INFO, "hub", "hello", "hello from the test")

    async def run() -> dict[str, Any]:
        async with (
            aiohttp.ClientSession() as s,
            s.ws_connect(f"http://127.0.0.1:{web.port}/api/live") as ws,
        ):
            (state,) = await _receive(ws, "state")
            await ws.send_str(SURGE_PLOT)
            plot = frames.Assembler()
            (frame,) = await _receive(ws, "frame", plot=plot)
            web.feed_batches(3)  # newer data: more frames, one per batch
            (again,) = await _receive(ws, "frame", plot=plot)
            while again["latest_ns"] < web.plots.streams()["wec/t8"]["latest_ns"]:
                (again,) = await _receive(ws, "frame", plot=plot)
            async with s.ws_connect(f"http://127.0.0.1:{web.port}/api/live") as fresh:
                await fresh.send_str(SURGE_PLOT)
                whole = frames.Assembler()
                await _receive(fresh, "frame", plot=whole)
            await ws.send_str("{bad")
            (error,) = await _receive(ws, "error")
            await ws.send_str(json.dumps({"type": "plots", "plots": [{"id": "b", "stream": "x"}]}))
            (error2,) = await _receive(ws, "error")
            return {"state": state, "frame": frame, "again": again, "errors": [error, error2],
                    "assembled": plot.minmax, "whole": whole.minmax}  # fmt: skip

    got = asyncio.run(run())
    assert got["state"]["view"]["site"] == "webtest"
    assert got["state"]["streams"]["wec/t8"]["channels"] == ["heave", "surge"]
    assert got["frame"]["id"] == "a"
    (surge,) = got["frame"]["channels"]
    assert (surge["name"], surge["unit"]) == ("surge", "m")
    assert len(surge["min"]) == len(surge["max"]) == 50
    assert min(v for v in surge["min"] if not math.isnan(v)) == -99.0, "the batches' values"
    assert got["again"]["latest_ns"] > got["frame"]["latest_ns"]
    assert got["frame"]["base_col"] is None, "a plot's first frame is whole"
    assert got["again"]["base_col"] is not None, "then deltas"
    assert got["again"]["count"] < 50
    np.testing.assert_array_equal(got["assembled"], got["whole"])
    assert got["errors"][0]["error"] == "not JSON"
    assert "no stream 'x'" in got["errors"][1]["error"]
    assert web.service.stats.ws_bad_messages == 2


def test_the_live_socket_needs_a_login_when_viewing_does(make_web: MakeWeb):
    web = make_web(open_view=False)

    async def run() -> int:
        async with aiohttp.ClientSession() as s:
            try:
                async with s.ws_connect(f"http://127.0.0.1:{web.port}/api/live"):
                    return 101
            except aiohttp.WSServerHandshakeError as err:
                return err.status

    assert asyncio.run(run()) == 401


def test_stopping_the_hub_closes_every_live_socket_as_going_away(make_web: MakeWeb):
    web = make_web()

    async def run() -> int | None:
        async with (
            aiohttp.ClientSession() as s,
            s.ws_connect(f"http://127.0.0.1:{web.port}/api/live") as ws,
        ):
            await _receive(ws, "state")
            loop = asyncio.get_running_loop()
            stopping = loop.run_in_executor(None, web.service.stop)
            while True:
                msg = await asyncio.wait_for(ws.receive(), 20)
                if msg.type in (aiohttp.WSMsgType.CLOSE, aiohttp.WSMsgType.CLOSED):
                    break
            await stopping
            return ws.close_code

    code = asyncio.run(run())
    assert code == 1001
    assert web.service.failure() is None


def test_a_slow_client_gets_the_newest_state_and_frames_and_the_rest_is_counted_dropped():
    stats = WebStats()
    client = Client(ws=None, user="", stats=stats)  # type: ignore[arg-type]
    for i in range(1000):
        client.offer_state(f"state {i}")
        client.offer_frame("p1", f"frame {i}")
    client.offer_events([{"seq": i} for i in range(2000)])
    pending = client.take()
    assert pending[0] == "state 999"
    assert pending[-1] == "frame 999"
    assert len(pending) == 3, "one state, one events message, one frame per plot"
    assert len(json.loads(pending[1])["events"]) == 500
    assert stats.ws_dropped == 999 + 999 + 1500
    assert client.take() == []


def test_with_open_view_off_a_live_socket_ends_with_its_session(make_web: MakeWeb):
    web = make_web(open_view=False)
    http = web.client()
    http.login("alice")

    async def run() -> int | None:
        headers = {"Cookie": http.cookie, "Origin": http.origin or ""}
        async with (
            aiohttp.ClientSession() as s,
            s.ws_connect(f"http://127.0.0.1:{web.port}/api/live", headers=headers) as ws,
        ):
            await _receive(ws, "state")
            loop = asyncio.get_running_loop()
            await loop.run_in_executor(None, http.post, "/api/logout")
            while True:
                msg = await asyncio.wait_for(ws.receive(), 20)
                if msg.type in (aiohttp.WSMsgType.CLOSE, aiohttp.WSMsgType.CLOSED):
                    return ws.close_code

    assert asyncio.run(run()) == 4001
