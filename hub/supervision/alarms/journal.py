"""The alarm journal: every transition, one JSON line each, so a hub that restarts (or is
killed) comes back with the same active, acked, shelved and disabled alarms and the audit of
who did what.

Operator actions (ack, shelve, disable...) are fsynced before the operator gets the reply;
transitions the hub makes itself are fsynced at least every second (what the last second held
is re-evaluated from live data at the next start anyway). A line torn by a crash is skipped.
Past `max_bytes` the journal is rewritten with the last line of each alarm (atomically).
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import threading
from pathlib import Path
from typing import TextIO

from fleetdaq.hub.bus import worth_telling
from fleetdaq.hub.read_model import JsonObject

log = logging.getLogger("fleetdaq.alarms")


class Journal:
    def __init__(self, path: Path, max_bytes: int = 16 * 1024 * 1024) -> None:
        self.path = path
        self.max_bytes = max_bytes
        self._lock = threading.Lock()
        self._fh: TextIO | None = None
        self._dirty = False
        self.torn_lines = 0
        self.write_errors = 0
        self.last_error = ""
        self._opened = False

    def load(self) -> dict[str, JsonObject]:
        """The last record of every alarm in the journal (empty if there is none yet)."""
        last: dict[str, JsonObject] = {}
        try:
            with self.path.open("r", encoding="utf-8") as fh:
                for line in fh:
                    try:
                        rec = json.loads(line)
                    except ValueError:
                        self.torn_lines += 1
                        continue
                    if isinstance(rec, dict) and isinstance(rec.get("name"), str):
                        last[rec["name"]] = rec
        except FileNotFoundError:
            return {}
        return last

    def open(self) -> None:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        if self.path.exists() and self.path.stat().st_size > self.max_bytes:
            self._compact()
        self._fh = self.path.open("a", encoding="utf-8")
        self._opened = True

    def append(self, record: JsonObject, sync: bool = False) -> bool:
        """Add a line; `sync`: fsync before returning (operator actions). False when the disk
        refused it (counted in `write_errors`; alarms go on in memory)."""
        try:
            line = json.dumps(record, separators=(",", ":"), allow_nan=False) + "\n"
        except (TypeError, ValueError) as err:  # never half a line: nothing is written
            with self._lock:
                self.write_errors += 1
                self.last_error = f"a record that is not JSON: {err}"
            return False
        with self._lock:
            if self._fh is None:
                if not self._opened:
                    return False
                try:
                    self._fh = self.path.open("a", encoding="utf-8")
                except OSError as err:
                    self.write_errors += 1
                    self.last_error = str(err)
                    return False
            try:
                self._fh.write(line)
                self._fh.flush()
                if sync:
                    os.fsync(self._fh.fileno())
                    self._dirty = False
                else:
                    self._dirty = True
            except OSError as err:
                self._failed(err)
                return False
            return True

    def sync(self) -> None:
        with self._lock:
            if self._fh is not None and self._dirty:
                try:
                    os.fsync(self._fh.fileno())
                    self._dirty = False
                except OSError as err:
                    self._failed(err)

    def _failed(self, err: OSError) -> None:
        """The disk refused a write: reopen the file next time (a partial line is skipped
        as torn when the journal is read)."""
        self.write_errors += 1
        self.last_error = str(err)
        if worth_telling(self.write_errors):
            log.error("alarm journal %s: %s (%d so far)", self.path, err, self.write_errors)
        if self._fh is not None:
            with contextlib.suppress(OSError):
                self._fh.close()
        try:
            self._fh = self.path.open("a", encoding="utf-8")
        except OSError:
            self._fh = None

    def _compact(self) -> None:
        last = self.load()
        tmp = self.path.with_name(self.path.name + ".tmp")
        with tmp.open("w", encoding="utf-8") as fh:
            for rec in last.values():
                fh.write(json.dumps(rec, separators=(",", ":"), allow_nan=False) + "\n")
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, self.path)
        log.info("compacted the alarm journal to %d alarms", len(last))

    def close(self) -> None:
        self.sync()
        with self._lock:
            self._opened = False
            if self._fh is not None:
                try:
                    self._fh.close()
                except OSError as err:
                    log.error("closing the alarm journal: %s", err)
                self._fh = None


def as_int(value: object) -> int:
    """`int(value)` of a field of a journal's line (TypeError for what `int` does not take)."""
    if isinstance(value, int | float | str):
        return int(value)
    raise TypeError(f"not a number: {value!r}")


def as_float(value: object) -> float:
    """`float(value)` of a field of a journal's line (TypeError for what `float` does not take)."""
    if isinstance(value, int | float | str):
        return float(value)
    raise TypeError(f"not a number: {value!r}")
