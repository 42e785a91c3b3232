"""Operators' requests to the hub: a Zenoh query on ``fleetdaq/<site>/hub/<what>`` whose payload
is a JSON object and whose reply is JSON. The parsing every such service shares (size bound,
JSON object, no unknown field, bounded text) and `RequestService`, which declares the queryable
and answers each request on a small pool, never on a Zenoh thread (an answer may block: a
recorder flushing, an edge being asked). The dashboard calls the same `handle` directly, so
the command line and the page are the same path with the same checks.

Also the services' actions as StrEnums (`AlarmAction`, `RecorderAction`, `ControlAction`: their
values are the strings on the wire), and the outputs' request: parsed once, by
`parse_control_request`, into a frozen `ControlRequest` that the ``hub/out`` queryable
(`fleetdaq.hub.control.commands.CommandService.handle`) and the dashboard
(`fleetdaq.hub.live.web.api`) both hand to `CommandService.act`. It lives here, below both wings,
because the control wing already uses the live view (its layer waits read the live plots).
"""

from __future__ import annotations

import contextlib
import json
import logging
import math
from collections.abc import Callable, Iterable, Mapping
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace
from enum import StrEnum
from typing import Any, Final

import zenoh

from fleetdaq.contract.config.security import SecurityConfig
from fleetdaq.contract.requester_text import TextRefused, checked_text, text_problem
from fleetdaq.hub.read_model import JsonObject, to_jsonable
from fleetdaq.hub.routing.router import Router, undeclare
from fleetdaq.runtime.threads import name_os_thread

log = logging.getLogger("fleetdaq.hub")

MAX_REQUEST_BYTES = 64 * 1024
MAX_USER_CHARS = 100
MAX_HOST_CHARS = 255
MAX_NOTE_CHARS = 500
FAILED = "the hub failed while answering (see its log); ask for the state to see what was done"


class BadRequest(ValueError):
    pass


def json_object(raw: bytes, max_bytes: int, empty: bytes = b"") -> dict[str, Any]:
    """`raw` as a JSON object of at most `max_bytes` (`empty` stands for no payload); the
    ValueError says what it is instead: ``N bytes (at most M)``, ``not JSON`` (nesting too deep
    included), ``not a JSON object``. Whatever crosses the network is parsed this way first."""
    if len(raw) > max_bytes:
        raise ValueError(f"{len(raw)} bytes (at most {max_bytes})")
    try:
        obj = json.loads(raw or empty)
    except (ValueError, RecursionError):
        raise ValueError("not JSON") from None
    if not isinstance(obj, dict):
        raise ValueError("not a JSON object")
    return obj


def parse_object(raw: bytes, allowed: Iterable[str]) -> JsonObject:
    """The request as a dict: at most 64 KiB, a JSON object, only `allowed` keys."""
    try:
        req = json_object(raw, MAX_REQUEST_BYTES, empty=b"{}")
    except ValueError as err:
        raise BadRequest(f"the request is {err}") from None
    unknown = set(req) - set(allowed)
    if unknown:
        raise BadRequest(f"unknown field(s): {', '.join(sorted(map(str, unknown)))}")
    return req


def text(
    req: Mapping[str, object], key: str, limit: int = MAX_NOTE_CHARS, default: str = ""
) -> str:
    """The request's `key` as requester text (`fleetdaq.contract.requester_text`: one line, no lone
    surrogate or control character, at most `limit` characters), `default` when empty."""
    try:
        value = checked_text(req.get(key, ""), key, limit)
    except TextRefused as err:
        raise BadRequest(str(err)) from None
    return value or default


@dataclass(frozen=True, slots=True)
class Caller:
    """Who asked, as the router vouches for it (security on: the key's ``by/NAME`` is the name
    in the certificate that sent the query) and what they may do."""

    name: str
    role: str
    """"view" or "control"."""

    @property
    def may_act(self) -> bool:
        return self.role == "control"


Handler = Callable[[bytes, "Caller | None"], Mapping[str, object]]


class OperatorQueryable:
    """A hub service's queryable: ``hub/<service>`` and ``hub/<service>/by/<name>``.

    With the site's security on, only the second is answered (the router admits an operator's
    query there only for the name in its certificate): the handler gets that `Caller`, whose
    name is the user to record, whatever the request says. Off, the first is answered with no
    caller (the request's own user is recorded). Answers run on a small pool (`workers`), or
    in the Zenoh callback when `workers` is 0 (quick, non-blocking answers only).
    """

    def __init__(
        self,
        router: Router,
        key: str,
        handler: Handler,
        security: SecurityConfig | None,
        name: str,
        workers: int = 2,
        hubs_only: bool = False,
    ) -> None:
        self.router = router
        self.key = key
        self.handler = handler
        self.secure = security is not None and security.tls
        self.hubs_only = hubs_only
        """A partition hub's service: with security on, the key itself is answered too, with
        the request's own user, because the router's access control admits only the site's
        other hubs there (the main hub passing an operator's or a rule's request on)."""
        self.operators = dict(security.operators) if security is not None else {}
        self.name = name
        self.workers = workers
        self._queryables: list[zenoh.Queryable[None]] = []
        self._pool: ThreadPoolExecutor | None = None

    def start(self) -> None:
        if self.workers:
            self._pool = ThreadPoolExecutor(
                self.workers, thread_name_prefix=self.name, initializer=name_os_thread
            )
        session = self.router.session
        self._queryables = [
            session.declare_queryable(self.key, self._on_query),
            session.declare_queryable(f"{self.key}/by/*", self._on_query),
        ]

    def stop(self) -> None:
        for q in self._queryables:
            undeclare(q)
        self._queryables = []
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool = None

    def caller(self, key: str) -> Caller | str | None:
        """Who asked on `key`; a string says why the request is refused."""
        if key == self.key:
            if self.secure and not self.hubs_only:
                return "security is on: ask as an operator (fleetdaq with your certificate)"
            return None
        name = key.removeprefix(f"{self.key}/by/")
        why = text_problem(name, MAX_USER_CHARS)
        if why is not None:  # security off: the key's name is the requester's own choice
            return f"the user name in the key {why}"
        role = self.operators.get(name)
        if self.secure and role is not None:
            return Caller(name, role)
        if self.secure:
            return f"operator {name!r} is not in security.operators"
        return Caller(name, role or "control")

    def _on_query(self, query: zenoh.Query) -> None:
        payload = query.payload
        raw = payload.to_bytes() if payload is not None else b""
        key = str(query.key_expr)

        def answer() -> None:
            try:
                who = self.caller(key)
                reply = (
                    {"ok": False, "error": who} if isinstance(who, str) else self.handler(raw, who)
                )
                body = json.dumps(to_jsonable(reply)).encode()
            except Exception:  # one request must never take the service down
                log.exception("answering a request on %s failed", key)
                # The requester is told, never left waiting for a reply that does not come.
                body = json.dumps({"ok": False, "error": FAILED}).encode()
            try:
                query.reply(key, body)
            except Exception:
                log.exception("replying to a request on %s failed", key)

        pool = self._pool
        if pool is None:
            answer()
            return
        with contextlib.suppress(RuntimeError):  # the pool is shutting down: the hub stops
            pool.submit(answer)


def as_caller(req: JsonObject, caller: Caller | None, action: object, read_only: tuple[str, ...]
              ) -> str | None:  # fmt: skip
    """Put the caller's name as the request's user; a reason when the caller may not `action`."""
    if caller is None:
        return None
    req["user"] = caller.name
    return refusal(caller, action, read_only)


def refusal(caller: Caller, action: object, read_only: Iterable[object]) -> str | None:
    """Why `caller` may not `action` (None: it may): only the control role acts."""
    if action not in read_only and not caller.may_act:
        return f"operator {caller.name} has the view role: {action} needs control"
    return None


# --- the services' actions ---------------------------------------------------------------------


class AlarmAction(StrEnum):
    """What an operator asks of the alarms (``hub/alarms``,
    `fleetdaq.hub.supervision.alarms.requests`)."""

    LIST = "list"
    ACK = "ack"
    SHELVE = "shelve"
    UNSHELVE = "unshelve"
    DISABLE = "disable"
    ENABLE = "enable"


class RecorderAction(StrEnum):
    """What an operator asks of the recorder (``hub/recorder``,
    `fleetdaq.hub.recording.requests`)."""

    STATUS = "status"
    START = "start"
    STOP = "stop"
    SPLIT = "split"
    SNAPSHOT = "snapshot"


# --- the outputs' requests ----------------------------------------------------------------------


class ControlAction(StrEnum):
    """What an operator asks of the outputs (``hub/out``): the list, or one of the commands an
    `OutputCommand` carries (`fleetdaq.contract.messages.ACTIONS`, the same strings)."""

    LIST = "list"
    SET = "set"
    PULSE = "pulse"
    ARM = "arm"
    DISARM = "disarm"
    READ = "read"


VALUED: Final = frozenset({ControlAction.SET, ControlAction.PULSE})
"""The actions that carry a value (and that a hub interlock holds back)."""
CONTROL_FIELDS: Final = (
    "action", "output", "value", "pulse_s", "reason", "user", "host", "command_id",
)  # fmt: skip
MAX_PULSE_S = 3600.0
_CONTROL_ACTIONS: Final = frozenset(a.value for a in ControlAction)


@dataclass(frozen=True, slots=True)
class ControlRequest:
    """An operator's request to the outputs, parsed once and checked in full
    (`parse_control_request`): the command line's (a Zenoh query) and the dashboard's alike."""

    action: ControlAction
    output: str = ""
    """``NODE/OUTPUT`` ("" for `ControlAction.LIST`)."""
    value: float = math.nan
    pulse_s: float = 0.0
    reason: str = ""
    user: str = "unknown"
    host: str = "unknown"
    command_id: str | None = None
    """The requester's own id for the command (None: the hub makes one)."""

    @property
    def node(self) -> str:
        return self.output.split("/", 1)[0]

    @property
    def output_name(self) -> str:
        return self.output.split("/", 1)[1]

    def by(self, user: str) -> ControlRequest:
        """This request as `user`'s (the name the router vouches for)."""
        return replace(self, user=user)


def parse_control_request(req: Mapping[str, object]) -> ControlRequest:
    """The JSON object `req` as a `ControlRequest`; BadRequest says what is wrong. Every text
    is checked before anything is sent, so that what is done can be recorded."""
    unknown = set(req) - set(CONTROL_FIELDS)
    if unknown:
        raise BadRequest(f"unknown field(s): {', '.join(sorted(map(str, unknown)))}")
    asked = req.get("action", ControlAction.LIST)
    if not isinstance(asked, str) or asked not in _CONTROL_ACTIONS:
        raise BadRequest(f"unknown action {asked!r} (one of {', '.join(ControlAction)})")
    action = ControlAction(asked)
    if action is ControlAction.LIST:
        return ControlRequest(action)
    output = text(req, "output", 200)
    if output.count("/") != 1:
        raise BadRequest("output must be NODE/OUTPUT")
    numbers: dict[str, float] = {}
    for key, default in (("value", math.nan), ("pulse_s", 0.0)):
        v = req.get(key, default)
        if (
            isinstance(v, bool)
            or not isinstance(v, int | float)
            or not math.isfinite(v if key != "value" or action in VALUED else 0.0)
        ):
            raise BadRequest(f"{key} must be a finite number")
        numbers[key] = float(v)
    value, pulse_s = numbers["value"], numbers["pulse_s"]
    if action in VALUED and math.isnan(value):
        raise BadRequest(f"{action} needs a value")
    if action is ControlAction.PULSE and not 0 < pulse_s <= MAX_PULSE_S:
        raise BadRequest("a pulse lasts more than 0 s and at most 3600 s")
    return ControlRequest(
        action,
        output,
        value,
        pulse_s,
        reason=text(req, "reason", MAX_NOTE_CHARS),
        user=text(req, "user", MAX_USER_CHARS, "unknown"),
        host=text(req, "host", MAX_HOST_CHARS, "unknown"),
        command_id=text(req, "command_id", 128) or None,
    )


def read_control_request(raw: bytes) -> ControlRequest:
    """A request on ``hub/out`` (JSON bytes) as a `ControlRequest` (`parse_object`, then
    `parse_control_request`)."""
    return parse_control_request(parse_object(raw, CONTROL_FIELDS))


class RequestService:
    """A hub service answering operators' requests (`OperatorQueryable`) with `handle`."""

    name = "requests"

    def __init__(
        self,
        router: Router,
        key: str,
        workers: int = 2,
        security: SecurityConfig | None = None,
        hubs_only: bool = False,
    ) -> None:
        self.router = router
        self.key = key
        self.queryable = OperatorQueryable(
            router, key, self.handle, security, self.name, workers, hubs_only
        )

    def handle(self, raw: bytes, caller: Caller | None = None) -> Mapping[str, object]:
        raise NotImplementedError

    def start(self) -> None:
        self.queryable.start()

    def stop(self) -> None:
        self.queryable.stop()

    def failure(self) -> str | None:
        return None
