"""What the live view sends: JSON messages and the JSON Schemas Foxglove and Lichtblick read them
with (message encoding ``json``, schema encoding ``jsonschema``).

The schemas keep to what both apps' JSON-Schema readers accept: ``object`` with
``properties``, one ``type`` per field (``number``, ``integer``, ``string``, ``boolean``,
``object``, ``array``). A value that is not a number (NaN: no valid sample, an alarm with no
value) is left out of its message, never sent as ``null``: the Plot panel draws a gap for a
missing field as it would for ``null``, and every message then matches its schema for strict
readers too (a ``["number", "null"]`` type is not one both apps' schema readers take). Times
are ``{sec, nsec}`` (what both apps take as a time); every message that has one carries it as
``header.stamp``, so the Plot panel's "header stamp" mode plots against acquisition time.
"""

from __future__ import annotations

import datetime as dt
import json
import math
from collections.abc import Mapping, Sequence
from typing import Final

import numpy as np

from fleetdaq.contract.messages import Event
from fleetdaq.hub.live.foxglove.decimate import Intervals
from fleetdaq.hub.read_model import AlarmView, JsonObject
from fleetdaq.hub.recording.session import topic_of

STREAM_ENVELOPE: Final = ("min", "max")
_RESERVED: Final = frozenset({"header", "scans", *STREAM_ENVELOPE})

TIME: Final = {
    "type": "object",
    "properties": {
        "sec": {"type": "integer", "minimum": 0},
        "nsec": {"type": "integer", "minimum": 0},
    },
}
HEADER: Final = {
    "type": "object",
    "properties": {"stamp": TIME, "frame_id": {"type": "string"}},
}
KEY_VALUES: Final = {
    "type": "array",
    "items": {
        "type": "object",
        "properties": {"key": {"type": "string"}, "value": {"type": "string"}},
    },
}


def stamp(t_ns: int) -> dict[str, int]:
    sec, nsec = divmod(t_ns, 1_000_000_000)
    return {"sec": sec, "nsec": nsec}


def iso(t_ns: int) -> str:
    """UTC, to the microsecond: ``2026-11-21T05:04:06.123456Z``."""
    t = dt.datetime.fromtimestamp(t_ns // 1000 / 1e6, dt.UTC)
    return t.strftime("%Y-%m-%dT%H:%M:%S.%fZ")


def _number(x: float, key: str = "value") -> dict[str, float]:
    """``{key: x}``, or nothing when `x` is not a number (left out, never null)."""
    return {key: x} if math.isfinite(x) else {}


def dumps(msg: Mapping[str, object]) -> bytes:
    return json.dumps(msg, separators=(",", ":"), allow_nan=False).encode()


# --- streams -------------------------------------------------------------------------------------


def field_name(channel: str) -> str:
    """The message field of a channel: its name, unless it is one of the message's own."""
    return f"{channel}_" if channel in _RESERVED else channel


class StreamMessages:
    """One stream's decimated intervals as JSON messages (`fleetdaq.hub.live.foxglove.decimate`).

    A message: ``header`` (``stamp``: the interval's first scan, ``frame_id``: node/stream),
    ``scans`` (how many fell in the interval), one number per channel (the mean over the
    interval) and ``min`` / ``max`` objects with the same fields. Built from one text template
    per stream: per message one string formatting, never per sample.
    """

    def __init__(
        self,
        node: str,
        stream: str,
        channels: Sequence[str],
        units: Sequence[str],
        interval_ns: int,
    ) -> None:
        self.topic = topic_of(node, stream)  # the recording's topic (a valid ROS 2 name)
        self.schema_name = f"fleetdaq.LiveStream.{node}.{stream}"
        fields = [field_name(c) for c in channels]
        value = {
            f: {
                "type": "number",
                "title": f"{c} [{u}]" if u else c,
                "description": f"{c}, {u or 'no unit'}: mean over the interval "
                "(left out when no sample in it was valid)",
            }
            for f, c, u in zip(fields, channels, units, strict=True)
        }

        def envelope(which: str) -> JsonObject:
            return {
                "type": "object",
                "description": f"the {which} of each channel over the interval",
                "properties": {
                    f: {"type": "number", "title": f"{which} {c} [{u}]" if u else f"{which} {c}"}
                    for f, c, u in zip(fields, channels, units, strict=True)
                },
            }

        self.schema: JsonObject = {
            "title": self.schema_name,
            "description": (
                f"{node}/{stream} live, decimated on the hub: one message per "
                f"{interval_ns / 1e6:g} ms of acquisition time (or per scan when slower), "
                "each channel's mean, min and max over that interval; header.stamp is the "
                "acquisition time (PTP-disciplined) of the interval's first scan"
            ),
            "type": "object",
            "properties": {
                "header": HEADER,
                "scans": {"type": "integer", "minimum": 0, "title": "scans in the interval"},
                **value,
                "min": envelope("min"),
                "max": envelope("max"),
            },
        }
        frame = json.dumps(f"{node}/{stream}")
        keys = [json.dumps(f) for f in fields]

        def template(number: str) -> str:
            values = ",".join(f"{k}:{number}" for k in keys)
            return (
                '{"header":{"stamp":{"sec":%d,"nsec":%d},"frame_id":' + frame + '},"scans":%d,'
                + values + ',"min":{' + values + '},"max":{' + values + "}}"
            )  # fmt: skip

        # %.17g: every float64 round-trips exactly, formatted in C (no repr per value).
        self._finite = template("%.17g")
        self._keys = keys
        self._head = '{"header":{"stamp":{"sec":%d,"nsec":%d},"frame_id":' + frame + '},"scans":%d'

    def encode(self, rows: Intervals) -> list[tuple[int, bytes]]:
        """(acquisition time ns, JSON bytes) per interval."""
        if not len(rows):
            return []
        cells = np.hstack([rows.mean, rows.lo, rows.hi])
        finite = bool(np.isfinite(cells).all())
        out = []
        for t, n, row in zip(
            rows.time_ns.tolist(), rows.scans.tolist(), cells.tolist(), strict=True
        ):
            sec, nsec = divmod(t, 1_000_000_000)
            if finite:
                text = self._finite % (sec, nsec, n, *row)
            else:  # JSON has no NaN: such a field is left out (the Plot panel draws a gap)
                text = self._sparse(sec, nsec, n, row)
            out.append((t, text.encode()))
        return out

    def _sparse(self, sec: int, nsec: int, scans: int, row: list[float]) -> str:
        k = len(self._keys)

        def fields(part: list[float]) -> list[str]:
            return [f"{key}:{x!r}" for key, x in zip(self._keys, part, strict=True)
                    if math.isfinite(x)]  # fmt: skip

        mean, lo, hi = fields(row[:k]), fields(row[k : 2 * k]), fields(row[2 * k :])
        head = self._head % (sec, nsec, scans)
        return ",".join([head, *mean, '"min":{' + ",".join(lo) + "}",
                         '"max":{' + ",".join(hi) + "}"]) + "}"  # fmt: skip


# --- events, the log, alarms ---------------------------------------------------------------------

EVENT_SCHEMA: Final = {
    "title": "fleetdaq.Event",
    "description": "a fleetdaq event (system message) from a node or the hub",
    "type": "object",
    "properties": {
        "header": HEADER,
        "time": {"type": "string", "description": "UTC, ISO 8601"},
        "node": {"type": "string"},
        "level": {"type": "integer", "description": "Python logging level (10 debug .. 50)"},
        "level_name": {"type": "string"},
        "source": {"type": "string"},
        "tag": {"type": "string"},
        "message": {"type": "string"},
        "fields": KEY_VALUES,
    },
}


def event_message(e: Event, t_ns: int) -> JsonObject:
    """`t_ns`: the event's time, or the hub's when the event's cannot be true."""
    return {
        "header": {"stamp": stamp(t_ns), "frame_id": e.node},
        "time": iso(t_ns),
        "node": e.node,
        "level": e.level,
        "level_name": e.level_name,
        "source": e.source,
        "tag": e.tag,
        "message": e.message,
        "fields": [{"key": kv.key, "value": kv.value} for kv in e.fields],
    }


LOG_SCHEMA: Final = {
    "title": "foxglove.Log",
    "description": "every event, for the Log panel (foxglove.Log)",
    "type": "object",
    "properties": {
        "timestamp": TIME,
        "level": {"type": "integer", "minimum": 0, "description": "1 debug .. 5 fatal"},
        "message": {"type": "string"},
        "name": {"type": "string"},
        "file": {"type": "string"},
        "line": {"type": "integer", "minimum": 0},
    },
}
_LOG_LEVEL: Final = {10: 1, 20: 2, 30: 3, 40: 4, 50: 5}


def log_message(e: Event, t_ns: int) -> JsonObject:
    """An event as a `foxglove.Log`: name node/source, the tag before the text."""
    return {
        "timestamp": stamp(t_ns),
        "level": _LOG_LEVEL.get(e.level, 0),
        "message": f"[{e.tag}] {e.message}",
        "name": f"{e.node}/{e.source}",
        "file": "",
        "line": 0,
    }


_ALARM_PROPERTIES: Final = {
    "name": {"type": "string"},
    "kind": {"type": "string"},
    "node": {"type": "string"},
    "stream": {"type": "string"},
    "channel": {"type": "string"},
    "severity": {"type": "string"},
    "state": {"type": "string"},
    "active": {"type": "boolean"},
    "since": {"type": "string", "description": "UTC, ISO 8601; empty when normal"},
    "value": {"type": "number", "description": "left out when the alarm has no value"},
    "unit": {"type": "string"},
    "count": {"type": "integer", "minimum": 0},
    "condition": {"type": "string"},
    "description": {"type": "string"},
    "shelved_until": {"type": "string"},
}

ALARM_TRANSITION_SCHEMA: Final = {
    "title": "fleetdaq.AlarmTransition",
    "description": "one alarm transition (raised, cleared, acked, shelved, ...)",
    "type": "object",
    "properties": {
        "header": HEADER,
        "time": {"type": "string"},
        "transition": {"type": "string"},
        "message": {"type": "string"},
        **_ALARM_PROPERTIES,
    },
}

ALARM_TABLE_SCHEMA: Final = {
    "title": "fleetdaq.AlarmTable",
    "description": "every alarm and its state, once a second",
    "type": "object",
    "properties": {
        "header": HEADER,
        "in_alarm": {"type": "integer", "minimum": 0},
        "alarms": {"type": "array", "items": {"type": "object", "properties": _ALARM_PROPERTIES}},
    },
}


def alarm_fields(a: AlarmView) -> JsonObject:
    return {
        "name": a.name,
        "kind": a.kind,
        "node": a.node,
        "stream": a.stream,
        "channel": a.channel,
        "severity": a.severity,
        "state": a.state,
        "active": a.active,
        "since": iso(a.since_ns) if a.since_ns > 0 else "",
        "unit": a.unit,
        "count": a.count,
        "condition": a.condition,
        "description": a.description,
        "shelved_until": iso(a.shelved_until_ns) if a.shelved_until_ns > 0 else "",
        **_number(a.value),
    }


def alarm_transition(e: Event, t_ns: int, view: AlarmView | None) -> JsonObject:
    """An ``alarm_<transition>`` event, with what the read model knows of that alarm."""
    out: JsonObject = {"name": e.get("alarm") or ""}
    if view is not None:
        out.update(alarm_fields(view))
    value = e.get("value")
    try:
        number = float(value) if value is not None else math.nan
    except ValueError:
        number = math.nan
    out.update(
        header={"stamp": stamp(t_ns), "frame_id": "hub"},
        time=iso(t_ns),
        transition=e.get("transition") or e.tag.removeprefix("alarm_"),
        message=e.message,
        severity=e.get("severity") or out.get("severity", ""),
        state=e.get("state") or out.get("state", ""),
    )
    out.pop("value", None)
    out.update(_number(number))
    return out


def alarm_table(alarms: Sequence[AlarmView], now_ns: int, in_alarm: int) -> JsonObject:
    return {
        "header": {"stamp": stamp(now_ns), "frame_id": "hub"},
        "in_alarm": in_alarm,
        "alarms": [alarm_fields(a) for a in alarms],
    }
