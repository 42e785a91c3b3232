"""The outbox: one file per mail, on disk until the SMTP server has accepted it.

A mail counts as queued only once its file is complete on disk: written under a temporary
name, fsynced, renamed into place, and the directory fsynced. It is deleted only after the
server accepted it. So a mail survives a crash, a kill -9 or a power cut at any moment, and a
hub that starts with mails in its outbox sends them (at least once: see
`fleetdaq.hub.supervision.notify.delivery`
for when a mail can arrive twice).

A file is one JSON line (the envelope: group, when it was queued, sender, recipients, subject)
and then the message exactly as it goes on the wire. Names sort in the order mails were
queued: ``<queued ns>-<seq>-<random>.mail``. A mail the server refused for good is moved to
``failed/`` beside a ``.reason`` file; moving it back into the outbox directory sends it again after
the next restart."""

from __future__ import annotations

import json
import logging
import os
import threading
import uuid
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

log = logging.getLogger("fleetdaq.notify")

SUFFIX = ".mail"
FAILED = "failed"


class OutboxError(Exception):
    """A mail file that cannot be read back (truncated by hand, not ours)."""


@dataclass(frozen=True, slots=True)
class Envelope:
    group: str
    created: float
    """When the mail was queued (seconds since the epoch): its age survives restarts."""
    sender: str
    to: tuple[str, ...]
    subject: str

    def to_json(self) -> bytes:
        doc = {
            "fleetdaq_mail": 1,
            "group": self.group,
            "created": self.created,
            "from": self.sender,
            "to": list(self.to),
            "subject": self.subject,
        }
        return json.dumps(doc, ensure_ascii=True).encode("ascii")

    @staticmethod
    def from_json(line: bytes) -> Envelope:
        try:
            doc: Any = json.loads(line)
            if not isinstance(doc, dict) or doc.get("fleetdaq_mail") != 1:
                raise ValueError("not a fleetdaq mail")
            to = doc["to"]
            if not isinstance(to, list) or not to or not all(isinstance(a, str) for a in to):
                raise ValueError("no recipients")
            return Envelope(
                str(doc["group"]),
                float(doc["created"]),
                str(doc["from"]),
                tuple(to),
                str(doc["subject"]),
            )
        except (ValueError, KeyError, TypeError) as err:
            raise OutboxError(f"bad envelope: {err}") from None


@dataclass(slots=True)
class Entry:
    """One queued mail, as the sender sees it."""

    name: str
    envelope: Envelope
    attempts: int = 0
    """Attempts at this mail that failed for a reason of its own (not a server outage)."""
    next_try: float = 0.0
    """Monotonic time before which it is not tried again (0: at once)."""


def fsync_dir(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY | os.O_DIRECTORY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def write_atomically(path: Path, data: bytes) -> None:
    """`data` complete at `path`, or nothing there: temporary file, fsync, rename, fsync dir."""
    tmp = path.with_name(f".{path.name}.tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC | os.O_CLOEXEC, 0o600)
    try:
        view = memoryview(data)
        while view:
            view = view[os.write(fd, view) :]
        os.fsync(fd)
    finally:
        os.close(fd)
    os.replace(tmp, path)
    fsync_dir(path.parent)


class Outbox:
    """The directory of queued mails and an index of them in memory (thread-safe)."""

    def __init__(self, directory: Path) -> None:
        self.dir = directory
        self.failed_dir = directory / FAILED
        self._entries: dict[str, Entry] = {}
        self._lock = threading.Lock()
        self._seq = 0

    def open(self) -> list[str]:
        """Create the directory, drop half-written files, index what is queued. Returns the
        names of files that were not mails and were moved to ``failed/``."""
        self.dir.mkdir(parents=True, exist_ok=True, mode=0o700)
        bad: list[str] = []
        for path in sorted(self.dir.iterdir()):
            if path.name.startswith(".") and path.name.endswith(".tmp"):
                path.unlink(missing_ok=True)  # never counted as queued: the write did not finish
                continue
            if not path.is_file() or not path.name.endswith(SUFFIX):
                continue
            try:
                envelope = self._read_envelope(path)
            except (OSError, OutboxError) as err:
                self._move_to_failed(path.name, f"cannot read it back: {err}")
                bad.append(path.name)
                continue
            self._entries[path.name] = Entry(path.name, envelope)
        return bad

    def put(self, envelope: Envelope, message: bytes) -> Entry:
        """Queue one mail: returns once its file is durable. Raises OSError (disk full...)."""
        with self._lock:
            self._seq += 1
            seq = self._seq
        name = f"{round(envelope.created * 1e9):020d}-{seq:06d}-{uuid.uuid4().hex[:8]}{SUFFIX}"
        write_atomically(self.dir / name, envelope.to_json() + b"\n" + message)
        # indexed (so counted as queued) only now that the file and its name are synced
        entry = Entry(name, envelope)
        with self._lock:
            self._entries[name] = entry
        return entry

    def read(self, entry: Entry) -> bytes:
        """The message of `entry`, as it goes on the wire."""
        data = (self.dir / entry.name).read_bytes()
        _, sep, message = data.partition(b"\n")
        if not sep or not message:
            raise OutboxError("no message after the envelope")
        return message

    def due(self, now: float) -> list[Entry]:
        """Queued mails whose retry time has come, oldest first."""
        with self._lock:
            return sorted(
                (e for e in self._entries.values() if e.next_try <= now), key=lambda e: e.name
            )

    def next_try(self) -> float | None:
        with self._lock:
            return min((e.next_try for e in self._entries.values()), default=None)

    def delivered(self, entry: Entry) -> None:
        """The server accepted it: its file and its index entry go together (`len` never
        counts a file that is gone), then the directory is synced."""
        with self._lock:
            (self.dir / entry.name).unlink(missing_ok=True)
            self._entries.pop(entry.name, None)
        fsync_dir(self.dir)

    def narrow(self, entry: Entry, to: tuple[str, ...]) -> None:
        """Some recipients got it: keep the mail for the others only."""
        message = self.read(entry)
        envelope = replace(entry.envelope, to=to)
        write_atomically(self.dir / entry.name, envelope.to_json() + b"\n" + message)
        with self._lock:
            entry.envelope = envelope

    def reject(self, entry: Entry, reason: str) -> None:
        """Refused for good: moved to ``failed/`` with the reason beside it."""
        self._move_to_failed(entry.name, reason)

    def oldest_created(self) -> float | None:
        with self._lock:
            return min((e.envelope.created for e in self._entries.values()), default=None)

    def failed_count(self) -> int:
        if not self.failed_dir.is_dir():
            return 0
        return sum(1 for p in self.failed_dir.iterdir() if p.name.endswith(SUFFIX))

    def __len__(self) -> int:
        """Mails whose file is complete and synced on disk: each one survives a kill -9. This
        is what the notifier reports as ``queued``."""
        with self._lock:
            return len(self._entries)

    def _read_envelope(self, path: Path) -> Envelope:
        with path.open("rb") as f:
            line = f.readline(1 << 20)
            if not line.endswith(b"\n") or not f.read(1):
                raise OutboxError("truncated")
        return Envelope.from_json(line)

    def _move_to_failed(self, name: str, reason: str) -> None:
        self.failed_dir.mkdir(exist_ok=True, mode=0o700)
        with self._lock:
            try:
                os.replace(self.dir / name, self.failed_dir / name)
            except FileNotFoundError:
                self._entries.pop(name, None)
                log.error("mail %s vanished from %s: %s", name, self.dir, reason)
                return
            self._entries.pop(name, None)
        (self.failed_dir / f"{name}.reason").write_text(reason + "\n", encoding="utf-8")
        fsync_dir(self.failed_dir)
        fsync_dir(self.dir)
        log.error("mail %s moved to %s: %s", name, self.failed_dir, reason)
