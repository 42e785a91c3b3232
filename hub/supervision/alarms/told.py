"""One alarm transition as everything that tells of it: the journal line, the ``/alarms`` record
(CDR), the event (events.log) and the notification. Built in full before any of them is
written, so a transition that cannot be encoded is refused whole instead of being journaled
and then lost on its way to the recording."""

from __future__ import annotations

import dataclasses
import logging
import math
from dataclasses import dataclass

from fleetdaq.contract.cdr import encode
from fleetdaq.contract.messages import AlarmState
from fleetdaq.hub.read_model import JsonObject
from fleetdaq.hub.supervision.alarms.definitions import AlarmDef
from fleetdaq.hub.supervision.alarms.states import AlarmStatus, Change
from fleetdaq.hub.supervision.notification import Notification

RAISED_LEVEL = {
    "critical": logging.CRITICAL,
    "major": logging.ERROR,
    "minor": logging.WARNING,
    "info": logging.INFO,
}


@dataclass(frozen=True, slots=True)
class Told:
    """One transition as the journal, the recording, events.log and the notifier get it."""

    journal: JsonObject
    record: bytes
    level: int
    tag: str
    message: str
    fields: dict[str, object]
    notification: Notification


def told(d: AlarmDef, s: AlarmStatus, change: Change) -> Told:
    """`change` of the alarm `d` (now in `s`) as it is told. Raises (UnicodeEncodeError,
    ValueError) on what cannot be encoded; nothing is written here."""
    state = AlarmState(
        time_ns=change.time_ns, name=d.name, kind=d.kind, node=d.node, stream=d.stream,
        channel=d.channel, condition=d.condition, severity=d.severity,
        state=change.state.value, active=s.active, transition=change.transition,
        value=change.value, unit=d.unit, since_ns=s.since_ns, count=s.count,
        user=change.user, host=change.host, note=change.note,
        shelved_until_ns=s.shelved_until_ns,
    )  # fmt: skip
    journal: JsonObject = {
        "name": d.name,
        "state": s.state.value,
        "active": s.active,
        "since_ns": s.since_ns,
        "count": s.count,
        # JSON has no NaN or infinity (a sensor may report either): no value is null.
        "value": s.value if math.isfinite(s.value) else None,
        "shelved_until_ns": s.shelved_until_ns,
        "transition": change.transition,
        "time_ns": change.time_ns,
        "user": change.user,
        "host": change.host,
        "note": change.note,
    }
    value = "" if math.isnan(change.value) else f" (value {change.value:.6g} {d.unit})".rstrip()
    who = f" by {change.user}@{change.host}" if change.user else ""
    note = f": {change.note}" if change.note else ""
    return Told(
        journal=journal,
        record=encode(state),
        level=RAISED_LEVEL[d.severity] if change.transition == "raised" else logging.INFO,
        tag=f"alarm_{change.transition}",
        message=f"{d.name} {change.transition}{who}{note} — {d.severity}, {d.condition}{value}; "
        f"now {change.state.value}",
        fields={
            "alarm": d.name,
            "severity": d.severity,
            "state": change.state.value,
            "transition": change.transition,
            "value": change.value,
        },
        notification=Notification(state, d.description),
    )


def put_back(status: AlarmStatus, before: AlarmStatus) -> None:
    """Undo an operator's action that could not be told: `status` as `before` was."""
    for f in dataclasses.fields(status):
        setattr(status, f.name, getattr(before, f.name))
