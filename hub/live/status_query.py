"""``fleetdaq/<site>/hub/status``: the hub's read model as JSON, to anyone who asks (a Zenoh
query with a reply). `fleetdaq ptp fleet`, the tests and operators' tools read the hub through
it instead of re-building what the hub already knows."""

from __future__ import annotations

import json
import logging
import time
from collections.abc import Callable

import zenoh

from fleetdaq.contract.config.security import SecurityConfig
from fleetdaq.contract.keys import SiteKeys
from fleetdaq.hub.read_model import HubView, JsonObject, to_json_object, to_jsonable
from fleetdaq.hub.requests import Caller, OperatorQueryable
from fleetdaq.hub.routing.router import Router

log = logging.getLogger("fleetdaq.hub")


def view_json(view: HubView) -> bytes:
    return json.dumps(to_jsonable(view), separators=(",", ":")).encode()


class StatusService:
    name = "status"

    def __init__(
        self,
        router: Router,
        keys: SiteKeys,
        snapshot: Callable[[], HubView],
        security: SecurityConfig | None = None,
        key: str | None = None,
    ) -> None:
        """`key`: where to answer (default ``hub/status``; a partition hub answers on its own)."""
        self.router = router
        self.key = key or keys.hub("status")
        self.snapshot = snapshot
        self.answered = 0
        # Answered in the Zenoh callback: a snapshot is a few reference copies.
        self.queryable = OperatorQueryable(
            router, self.key, self._answer, security, "status", workers=0
        )

    def start(self) -> None:
        self.queryable.start()

    def _answer(self, raw: bytes, caller: Caller | None) -> JsonObject:
        self.answered += 1
        return to_json_object(self.snapshot())

    def stop(self) -> None:
        self.queryable.stop()

    def failure(self) -> str | None:
        return None


def query_status(
    session: zenoh.Session, keys: SiteKeys, timeout_s: float = 5.0, key: str | None = None
) -> JsonObject | None:
    """Ask the hub (or at `key`, a partition hub) for its status; None when none answers within
    `timeout_s`."""
    deadline = time.monotonic() + timeout_s
    while True:
        for reply in session.get(
            key or keys.hub("status"), timeout=max(0.5, deadline - time.monotonic())
        ):
            if reply.ok is not None:
                out: JsonObject = json.loads(reply.ok.payload.to_bytes())
                return out
        if time.monotonic() >= deadline:
            return None
        time.sleep(0.2)
