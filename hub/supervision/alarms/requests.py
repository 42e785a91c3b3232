"""Operators' requests about alarms: ``fleetdaq/<site>/hub/alarms``, a Zenoh query whose payload
is a JSON request and whose reply is JSON.

Request: ``{"action": "list" | "ack" | "shelve" | "unshelve" | "disable" | "enable",
"names": [name or pattern, ...], "all": bool, "for_s": seconds (shelve), "note": text,
"user": who, "host": from where}``. ``all`` with ``ack`` means every unacked alarm. Names,
note, user and host follow the rule for requester text (`fleetdaq.contract.requester_text`).
Reply: ``{"ok": bool, "error": text, "results": [{"name", "done", "state" or "reason"}],
"alarms": [every alarm's view]}``. Everything in a request is checked before anything is done.
"""

from __future__ import annotations

import fnmatch
import logging
from typing import Final, TypedDict

from fleetdaq.contract.config.security import SecurityConfig
from fleetdaq.contract.keys import SiteKeys
from fleetdaq.contract.requester_text import text_problem
from fleetdaq.hub.read_model import JsonObject, to_jsonable
from fleetdaq.hub.requests import (
    MAX_HOST_CHARS,
    MAX_USER_CHARS,
    AlarmAction,
    BadRequest,
    Caller,
    RequestService,
    parse_object,
    refusal,
    text,
)
from fleetdaq.hub.routing.router import Router
from fleetdaq.hub.supervision.alarms.states import UNACKED, State
from fleetdaq.hub.supervision.alarms.supervisor import Supervisor

log = logging.getLogger("fleetdaq.alarms")

ACTIONS: Final = tuple(AlarmAction)
_ACTIONS: Final = frozenset(a.value for a in AlarmAction)
MAX_SHELVE_S = 30 * 24 * 3600.0
MAX_NAME_CHARS = 200


class AlarmRequest(TypedDict):
    """A request on ``hub/alarms``, checked in full (`parse_request`)."""

    action: AlarmAction
    names: list[str]
    all: bool
    for_s: float
    note: str
    user: str
    host: str


def parse_request(raw: bytes) -> AlarmRequest:
    req = parse_object(raw, ("action", "names", "all", "for_s", "note", "user", "host"))
    asked = req.get("action", AlarmAction.LIST)
    if not isinstance(asked, str) or asked not in _ACTIONS:
        raise BadRequest(f"unknown action {asked!r} (one of {', '.join(ACTIONS)})")
    action = AlarmAction(asked)
    names = req.get("names", [])
    if not isinstance(names, list) or not all(isinstance(n, str) and n for n in names):
        raise BadRequest("names must be a list of alarm names or patterns")
    names = [str(n) for n in names]
    if len(names) > 1000:
        raise BadRequest("at most 1000 names")
    for i, name in enumerate(names):
        # A name is echoed in replies and refusals: it follows the rule for requester text.
        why = text_problem(name, MAX_NAME_CHARS)
        if why is not None:
            raise BadRequest(f"names[{i}] {why}")
    if not isinstance(req.get("all", False), bool):
        raise BadRequest("all must be true or false")
    for_s = req.get("for_s", 0.0)
    if isinstance(for_s, bool) or not isinstance(for_s, int | float):
        raise BadRequest("for_s must be a number of seconds")
    if action is AlarmAction.SHELVE and not 0 < for_s <= MAX_SHELVE_S:
        raise BadRequest(f"a shelve lasts more than 0 s and at most {MAX_SHELVE_S:g} s")
    if action is not AlarmAction.LIST and not names and not req.get("all"):
        raise BadRequest("name the alarm(s), or ask for all")
    return {
        "action": action,
        "names": names,
        "all": bool(req.get("all", False)),
        "for_s": float(for_s),
        "note": text(req, "note"),
        "user": text(req, "user", MAX_USER_CHARS, "unknown"),
        "host": text(req, "host", MAX_HOST_CHARS, "unknown"),
    }


class AlarmRequests(RequestService):
    name = "alarm-requests"

    def __init__(
        self,
        router: Router,
        keys: SiteKeys,
        supervisor: Supervisor,
        security: SecurityConfig | None = None,
    ) -> None:
        # Answered in the Zenoh callback: an alarm action takes the supervisor's lock, no I/O
        # but the journal's fsync.
        super().__init__(router, keys.hub("alarms"), workers=1, security=security)
        self.supervisor = supervisor

    def handle(self, raw: bytes, caller: Caller | None = None) -> JsonObject:
        try:
            req = parse_request(raw)
            if caller is not None:
                req["user"] = caller.name
                why = refusal(caller, req["action"], (AlarmAction.LIST,))
                if why:
                    raise BadRequest(why)
        except BadRequest as err:
            return {"ok": False, "error": str(err), "results": [], "alarms": []}
        sup = self.supervisor
        names = self._resolve(req)
        results: list[JsonObject] = []
        ok = True
        if req["action"] is not AlarmAction.LIST:
            if not names:
                return {
                    "ok": False,
                    "error": "no alarm matches " + (", ".join(req["names"]) or "that"),
                    "results": [],
                    "alarms": self._alarms(),
                }
            for name, done, what in sup.operate(
                req["action"], names, req["user"], req["host"], req["note"], req["for_s"]
            ):
                results.append({"name": name, "done": done, "state" if done else "reason": what})
                ok = ok and done
        return {"ok": ok, "error": "", "results": results, "alarms": self._alarms()}

    def _resolve(self, req: AlarmRequest) -> list[str]:
        sup = self.supervisor
        if req["all"]:
            if req["action"] is AlarmAction.ACK:
                return [n for n, a in sup.alarms.items() if a.status.state in UNACKED]
            if req["action"] is AlarmAction.UNSHELVE:
                return [n for n, a in sup.alarms.items() if a.status.state is State.SHELVED]
            return list(sup.alarms)
        # A pattern takes the alarms it matches that the action applies to (acking
        # "node_down/*" acks the unacked ones and says nothing of the others); a plain name is
        # taken as given, so a refusal names its reason.
        wanted: set[State] | None = {
            AlarmAction.ACK: set(UNACKED),
            AlarmAction.UNSHELVE: {State.SHELVED},
            AlarmAction.ENABLE: {State.DISABLED},
        }.get(req["action"])
        out: list[str] = []
        for pattern in req["names"]:
            if any(c in pattern for c in "*?["):
                hits = [
                    n
                    for n in fnmatch.filter(sup.alarms, pattern)
                    if wanted is None or sup.alarms[n].status.state in wanted
                ]
            else:
                hits = [pattern]
            for n in hits:
                if n not in out:
                    out.append(n)
        return out

    def _alarms(self) -> object:
        """Every alarm's view, JSON-ready."""
        with self.supervisor.lock:
            views = [a.view() for a in self.supervisor.alarms.values()]
        return to_jsonable(views)
