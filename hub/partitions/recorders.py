"""Recorder control on a partitioned site: the main hub's start, stop and split reach every
partition hub, and each partition hub takes requests of its own.

Each partition hub answers recorder requests on ``fleetdaq/<site>/hub/partition/<name>/recorder``
with its own recorder and snapshot buffer (the same `RecorderRequests` as the main hub's, so the
same checks and events). The main hub asks every partition there whenever it is asked to start,
stop or split (`fleetdaq rec`, the dashboard): the partitions are asked first, all at once, then
the main hub acts, then their answers are collected. The main hub's reply carries each
partition's answer, and is `ok` only when every hub's is. A partition that does not answer (its
hub is down) is said by name; the other hubs have acted all the same. A snapshot asked of the
main hub goes the same way, so its reply names every hub's file. A rule's `record:` start, stop
or split is passed on without waiting: a partition that did not do it is a warning event. A
rule's snapshot and an alarm's reach the partitions by their trigger
(`fleetdaq.hub.partitions.snapshots`).

An answer comes from another machine across the mesh: it is checked in full (size, a JSON
object, `ok` a boolean, `result` and `error` bounded text); anything else is that partition's
failure in the reply, counted and raised as an event.
"""

from __future__ import annotations

import json
import logging
from typing import Any

from fleetdaq.contract.keys import SiteKeys
from fleetdaq.hub.bus import EventBus
from fleetdaq.hub.recording.seams import Collect
from fleetdaq.hub.requests import json_object
from fleetdaq.hub.routing.router import Router
from fleetdaq.runtime.threads import NamedThread

log = logging.getLogger("fleetdaq.hub")

ANSWER_S = 120.0
"""How long the main hub waits for a partition's answer (a stop closes and fsyncs its file)."""
MAX_ANSWER_BYTES = 4 * 1024 * 1024
MAX_TEXT = 2000


def recorder_key(keys: SiteKeys, partition: str) -> str:
    """``fleetdaq/<site>/hub/partition/<name>/recorder``: that partition hub's recorder requests."""
    return keys.hub(f"partition/{partition}/recorder")


def parse_answer(raw: bytes) -> dict[str, Any]:
    """A partition's answer reduced to ``{ok, result, error}``; ValueError says what is wrong."""
    obj = json_object(raw, MAX_ANSWER_BYTES)
    if not isinstance(obj.get("ok"), bool):
        raise ValueError("ok is not true or false")
    out: dict[str, Any] = {"ok": obj["ok"]}
    for k in ("result", "error"):
        v = obj.get(k, "")
        if not isinstance(v, str) or len(v) > MAX_TEXT:
            raise ValueError(f"{k} is not text of at most {MAX_TEXT} characters")
        out[k] = v
    out["ok"] = out["ok"] and not out["error"]
    return out


class PartitionRecorders:
    """The main hub's side: one recorder request to every partition hub at once."""

    def __init__(
        self,
        router: Router,
        keys: SiteKeys,
        partitions: list[str],
        bus: EventBus,
        timeout_s: float = ANSWER_S,
        snapshots_off: frozenset[str] = frozenset(),
    ) -> None:
        """`snapshots_off`: the partitions whose site file keeps no snapshot buffer on their
        hub; a snapshot is not asked of them, and their answer says why (not a failure)."""
        self.router = router
        self.keys = keys
        self.partitions = list(partitions)
        self.snapshots_off = snapshots_off
        self.bus = bus
        self.timeout_s = timeout_s
        self.asked = 0
        self.malformed = 0

    def ask(self, request: dict[str, str]) -> Collect:
        """Send `request` to every partition now; the returned call waits for their answers."""
        payload = json.dumps(request).encode()
        session = self.router.session
        off = self.snapshots_off if request.get("action") == "snapshot" else frozenset()
        pending = {
            name: session.get(
                recorder_key(self.keys, name), payload=payload, timeout=self.timeout_s
            )
            for name in self.partitions
            if name not in off
        }
        self.asked += 1
        kept_none = {
            name: {
                "ok": True,
                "result": f"no snapshot: this hub keeps no snapshot buffer "
                f"(hub.partitions.{name}.snapshot.enabled is false)",
                "error": "",
            }
            for name in self.partitions
            if name in off
        }
        return lambda: {
            **{name: self._answer(name, replies) for name, replies in pending.items()},
            **kept_none,
        }

    def pass_on(self, request: dict[str, str]) -> None:
        """`ask` without waiting (a rule's `record:` action: a rule never waits on another
        machine); a partition that did not do it is a warning event."""
        collect = self.ask(request)

        def report() -> None:
            try:
                answers = collect()
            except Exception:  # never silent: the operator must know the partition may not act
                log.exception("collecting the partitions' answers to %s failed", request)
                failed = {"ok": False, "error": "no answer collected"}
                answers = {name: failed for name in self.partitions}
            for name, a in answers.items():
                if not a["ok"]:
                    self.bus.emit(
                        logging.WARNING,
                        "hub",
                        "partition_not_done",
                        f"partition hub {name}: record {request['action']} for "
                        f"{request['user']} not done: {a['error'] or a['result']}",
                        partition=name,
                        action=request["action"],
                    )

        NamedThread(target=report, name="partition-recorders", daemon=True).start()

    def _answer(self, name: str, replies: Any) -> dict[str, Any]:
        for reply in replies:  # ends when the partition answered, or at the timeout
            if reply.ok is None:
                why = reply.err.payload.to_bytes().decode(errors="replace")[:MAX_TEXT]
                return {"ok": False, "result": "", "error": f"its hub refused: {why}"}
            try:
                return parse_answer(reply.ok.payload.to_bytes())
            except ValueError as err:
                self.malformed += 1
                self.bus.emit_counted(
                    self.malformed,
                    logging.WARNING,
                    "hub",
                    "malformed",
                    f"partition hub {name}: refused an answer to a recorder request that "
                    f"is not one ({err})",
                    partition=name,
                )
                return {"ok": False, "result": "", "error": f"its answer is not valid ({err})"}
        return {
            "ok": False,
            "result": "",
            # At once when no such hub is on the mesh; at the timeout when one never answers.
            "error": f"no answer (is its hub running and linked? waited at most "
            f"{self.timeout_s:g} s)",
        }
