"""Recorder control: ``fleetdaq/<site>/hub/recorder`` (`fleetdaq rec ...`, the dashboard).

Request: ``{"action": "status" | "start" | "stop" | "split" | "snapshot", "user": who,
"host": from where, "note": text}``. Reply: ``{"ok": bool, "error": text, "result": what was
done, "recorder": the recorder's view, "snapshots": the snapshot buffer's view, "partitions":
each partition hub as its report says (alive, its recorder), "partition_results": each
partition hub's answer to a start, stop, split or snapshot}``. Every action is an event naming
who asked (the recorder's and the snapshot buffer's own events). User, host and note follow the
rule for requester text (`fleetdaq.contract.requester_text`), checked before anything is done.

On a partitioned site the main hub passes start, stop, split and snapshot on to every partition
hub (`fleetdaq.hub.partitions.recorders`), and each partition hub answers these requests for its own
recorder on ``hub/partition/<name>/recorder``.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from fleetdaq.contract.config.security import SecurityConfig
from fleetdaq.contract.keys import SiteKeys
from fleetdaq.hub.read_model import HubView, to_jsonable
from fleetdaq.hub.recording.recorder import Recorder
from fleetdaq.hub.recording.seams import FORWARDED, OtherHubs
from fleetdaq.hub.requests import (
    MAX_HOST_CHARS,
    MAX_USER_CHARS,
    BadRequest,
    Caller,
    RequestService,
    as_caller,
    parse_object,
    text,
)
from fleetdaq.hub.routing.router import Router

ACTIONS = ("status", "start", "stop", "split", "snapshot")
Snapshot = Callable[[str, str], tuple[bool, str]]
"""snapshot(who, note) -> (written, what: the file or why not)."""


class RecorderRequests(RequestService):
    name = "recorder-requests"

    def __init__(
        self,
        router: Router,
        keys: SiteKeys,
        recorder: Recorder,
        view: Callable[[], HubView],
        snapshot: Snapshot | None,
        security: SecurityConfig | None = None,
        key: str | None = None,
        partitions: OtherHubs | None = None,
        snapshot_setting: str = "hub.snapshot.enabled",
    ) -> None:
        """`snapshot_setting`: the site file's key that switches this hub's snapshot buffer off
        (a partition hub's is its own), named when a snapshot is asked of a hub without one."""
        # A partition hub's (`key` given): the main hub passes requests on to its key itself.
        super().__init__(
            router,
            key or keys.hub("recorder"),
            workers=1,
            security=security,
            hubs_only=key is not None,
        )
        self.recorder = recorder
        self.view = view
        self.snapshot = snapshot
        self.snapshot_setting = snapshot_setting
        self.partitions = partitions
        """The main hub of a partitioned site: start, stop, split and snapshot reach every
        partition hub."""

    def handle(self, raw: bytes, caller: Caller | None = None) -> dict[str, Any]:
        try:
            req = parse_object(raw, ("action", "user", "host", "note"))
            action = req.get("action", "status")
            if action not in ACTIONS:
                raise BadRequest(f"unknown action {action!r} (one of {', '.join(ACTIONS)})")
            refused = as_caller(req, caller, action, ("status",))
            if refused:
                raise BadRequest(refused)
            # Every text before anything is done (`fleetdaq.contract.requester_text`).
            user = text(req, "user", MAX_USER_CHARS, "unknown")
            host = text(req, "host", MAX_HOST_CHARS, "unknown")
            note = text(req, "note")
            who = f"{user}@{host}"
        except BadRequest as err:
            return self._answer(False, str(err), "")
        collect = None
        # A snapshot buffer switched off is off on every hub of the site: nobody to ask.
        asks = action in FORWARDED and (action != "snapshot" or self.snapshot is not None)
        if self.partitions is not None and asks:
            # Asked first and all at once; they act while this hub does.
            collect = self.partitions.ask(
                {"action": action, "user": user, "host": host, "note": note}
            )  # fmt: skip
        rec = self.recorder
        ok, result = True, ""
        if action == "start":
            result = rec.start_recording(who, note)
        elif action == "stop":
            result = rec.stop_recording(who, note)
        elif action == "split":
            result = rec.split(who, note)
            ok = result.startswith("closed")
        elif action == "snapshot":
            if self.snapshot is None:
                ok, result = False, f"the snapshot buffer is switched off ({self.snapshot_setting})"
            else:
                ok, result = self.snapshot(who, note)
        answers = collect() if collect is not None else {}
        ok = ok and all(a["ok"] for a in answers.values())
        return self._answer(ok, "", result, answers)

    def _answer(
        self, ok: bool, error: str, result: str, answers: dict[str, Any] | None = None
    ) -> dict[str, Any]:
        view = self.view()
        return {
            "ok": ok and not error,
            "error": error,
            "result": result,
            "recorder": to_jsonable(view.recorder),
            "snapshots": to_jsonable(view.snapshots),
            "partitions": to_jsonable(view.partitions),
            "partition_results": answers or {},
        }
