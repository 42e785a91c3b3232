"""Transitions a group holds (for a digest, or snoozed), kept on disk until they are mailed.

A mail in the outbox survives a kill -9; so must what waits for the next digest. Each newly
held transition is appended as one JSON line and fsynced (a batch at a time); when held ones
are mailed (their digest is in the outbox first), the file is replaced whole by what is still
held. At start, whatever is in the file is mailed as one digest per group. A torn last line
(the hub died while writing it) is skipped: that transition had not been confirmed held.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import os
from pathlib import Path
from typing import IO, Any

from fleetdaq.contract.messages import AlarmState
from fleetdaq.hub.supervision.notify.outbox import fsync_dir, write_atomically
from fleetdaq.hub.supervision.notify.policy import Held, Item

log = logging.getLogger("fleetdaq.notify")

_STATE_FIELDS = {
    f.name: f.type if isinstance(f.type, str) else f.type.__name__
    for f in dataclasses.fields(AlarmState)
}
_CASTS: dict[str, type] = {"int": int, "str": str, "float": float, "bool": bool}


def _encode(h: Held) -> bytes:
    i = h.item
    doc = {
        "group": h.group,
        "kind": h.kind,
        "what": i.what,
        "description": i.description,
        "held_back": [list(p) for p in i.held_back],
        "state": dataclasses.asdict(i.state),
    }
    return json.dumps(doc, ensure_ascii=True).encode("ascii") + b"\n"


def _decode(line: bytes) -> Held:
    doc: Any = json.loads(line)
    raw = doc["state"]
    fields: dict[str, Any] = {}
    for name, kind in _STATE_FIELDS.items():
        cast = _CASTS[kind]
        value = raw[name]
        if cast is float:
            value = float(value)
        elif not isinstance(value, cast) or (cast is int and isinstance(value, bool)):
            raise TypeError(f"{name}: expected {kind}")
        fields[name] = value
    kind = doc["kind"]
    if kind not in ("digest", "snoozed"):
        raise ValueError(f"unknown kind {kind!r}")
    held_back = tuple((str(k), int(n)) for k, n in doc["held_back"])
    item = Item(AlarmState(**fields), str(doc["description"]), str(doc["what"]), False, held_back)
    return Held(str(doc["group"]), kind, item)


class HeldJournal:
    """``<outbox>/held.jsonl``: one line per held transition."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self._file: IO[bytes] | None = None
        self.skipped = 0
        """Lines that could not be read back at `load` (a torn last line, damage)."""

    def load(self) -> list[Held]:
        """What was held when the hub last stopped."""
        try:
            data = self.path.read_bytes()
        except FileNotFoundError:
            return []
        out: list[Held] = []
        for n, line in enumerate(data.split(b"\n"), 1):
            if not line.strip():
                continue
            try:
                out.append(_decode(line))
            except (ValueError, KeyError, TypeError) as err:
                self.skipped += 1
                log.warning("%s line %d: skipped, cannot be read back: %s", self.path, n, err)
        return out

    def append(self, records: list[Held]) -> None:
        """Newly held transitions: on disk (fsynced) when this returns."""
        if not records:
            return
        f = self._open()
        f.write(b"".join(_encode(h) for h in records))
        f.flush()
        os.fsync(f.fileno())

    def rewrite(self, records: list[Held]) -> None:
        """Replace the file with `records` (what is still held), atomically."""
        self.close()
        if records:
            write_atomically(self.path, b"".join(_encode(h) for h in records))
        elif self.path.exists():
            self.path.unlink()
            fsync_dir(self.path.parent)

    def close(self) -> None:
        if self._file is not None:
            self._file.close()
            self._file = None

    def _open(self) -> IO[bytes]:
        if self._file is None:
            fd = os.open(self.path, os.O_WRONLY | os.O_CREAT | os.O_APPEND | os.O_CLOEXEC, 0o600)
            self._file = os.fdopen(fd, "ab")
        return self._file
