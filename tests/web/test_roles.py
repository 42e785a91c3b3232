"""Dashboard roles and what a login records: a view-role login looks but every action is refused
(403, with the reason) before it reaches the hub; a failed login with a name that is nobody's
never records the name typed (it may be a password typed into the wrong field). The real
service, plain HTTP and a real WebSocket."""

from __future__ import annotations

import asyncio
import json
import logging
from collections.abc import Callable
from typing import Any

import aiohttp
import pytest

from fleetdaq.hub.live.web.api import ALARM_ACTIONS, OUTPUT_ACTIONS, RECORDER_ACTIONS
from tests.procs import wait_until
from tests.web.conftest import Web

MakeWeb = Callable[..., Web]

ACTIONS = [
    *(("/api/alarms", a, {"names": ["substrate_hot"], "note": "checked"}) for a in ALARM_ACTIONS),
    # A pulse says how long: the page parses a request with the hub's own parser.
    *(
        ("/api/outputs", a, {"output": "wec/valve", "value": 1.0, "pulse_s": 1.0})
        for a in OUTPUT_ACTIONS
    ),
    *(("/api/recorder", a, {}) for a in RECORDER_ACTIONS),
]

TYPED = "Tide-Gauge-42!secret"
"""A password typed into the user-name field."""


def handled(web: Web) -> int:
    return len(web.alarms.requests) + len(web.commands.requests) + len(web.recorder.requests)


@pytest.mark.parametrize(
    ("path", "action", "body"), ACTIONS, ids=[f"{p}:{a}" for p, a, _ in ACTIONS]
)
def test_a_view_role_login_is_refused_every_action_with_403_and_the_reason(
    make_web: MakeWeb, path: str, action: str, body: dict[str, Any]
):
    web = make_web()
    vera = web.client()
    assert vera.login("vera")[0] == 200
    status, answer = vera.post(path, {"action": action, **body})
    assert status == 403
    assert answer["error"] == (
        "refused: vera has the view role; acting needs the control role "
        "(on the hub: fleetdaq users role vera control)"
    )
    assert handled(web) == 0, "nothing reached the hub"
    alice = web.client()
    assert alice.login("alice")[0] == 200
    assert alice.post(path, {"action": action, **body})[0] == 200, "control may"
    assert handled(web) == 1


def test_the_session_says_the_role_so_the_page_can_disable_what_it_may_not_do(
    make_web: MakeWeb,
):
    web = make_web()
    vera, alice = web.client(), web.client()
    assert vera.login("vera")[1]["role"] == "view"
    assert alice.login("alice")[1]["role"] == "control"
    assert vera.get("/api/session")[1]["role"] == "view"
    assert alice.get("/api/session")[1]["role"] == "control"
    assert web.client().get("/api/session")[1]["role"] is None
    assert vera.get("/api/view")[0] == 200, "a view login looks"


def test_a_role_changed_in_the_users_file_counts_at_the_next_click(make_web: MakeWeb):
    from fleetdaq.hub.live.web.users import read_users, write_users

    web = make_web()
    vera = web.client()
    vera.login("vera")
    assert vera.post("/api/recorder", {"action": "split"})[0] == 403
    write_users(web.users_file, read_users(web.users_file), {"vera": "control"})
    assert vera.post("/api/recorder", {"action": "split"})[0] == 200
    assert web.recorder.requests[-1]["user"] == "vera"


def test_a_failed_login_with_a_name_that_is_nobodys_never_records_the_name_typed(
    make_web: MakeWeb, caplog: pytest.LogCaptureFixture
):
    web = make_web()

    async def run() -> list[dict[str, Any]]:
        async with (
            aiohttp.ClientSession() as s,
            s.ws_connect(f"http://127.0.0.1:{web.port}/api/live") as ws,
        ):
            loop = asyncio.get_running_loop()
            status, _ = await loop.run_in_executor(
                None, lambda: web.client().login(TYPED, "alice-password")
            )
            assert status == 401
            await loop.run_in_executor(None, lambda: web.client().login("alice", "not hers"))
            seen: list[dict[str, Any]] = []
            while sum(e["tag"] == "login_failed" for e in seen) < 2:
                msg = await asyncio.wait_for(ws.receive(), 20)
                if msg.type == aiohttp.WSMsgType.TEXT:
                    data = json.loads(msg.data)
                    if data["type"] == "events":
                        seen.extend(data["events"])
            return seen

    with caplog.at_level(logging.INFO, logger="fleetdaq"):
        live = asyncio.run(run())
    failed = [e for e in live if e["tag"] == "login_failed"]
    unknown, known = failed
    assert unknown["message"].startswith(
        "dashboard login refused for an unknown user name from 127.0.0.1 ("
    )
    assert known["message"].startswith("dashboard login refused for 'alice' from 127.0.0.1 (")
    assert known["fields"]["user"] == "alice", "a user's own name may be recorded"
    assert TYPED not in json.dumps(live), "not in the live view"
    _, tail = web.client().get("/api/events?limit=2000")
    assert TYPED not in json.dumps(tail), "not in the event tail"
    wait_until(lambda: "login refused for 'alice'" in caplog.text, 10, "the hub's log line")
    assert "login refused for an unknown user name from 127.0.0.1" in caplog.text
    assert TYPED not in caplog.text, "not in the hub's log"
