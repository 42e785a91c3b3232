"""The recorder's memory of a refused write (a full disk, a failing card): until a flush goes
through again, nothing is acked, so the edges keep their spools and replay what was not acked.

A failed write abandons the open file (what is closed stays readable; `fleetdaq verify
--recover` makes the rest readable), rolls every stream back to its last ack and retries every
`RETRY_AFTER_ERROR_S`. Events and other messages are not replayed by anyone, so those written
since the last flush, and those that come while the disk refuses writes, are held here
(bounded by `MAX_HELD`; past it they are counted, and events are still in events.log) and
written again once a flush succeeds. The first failure raises one event, the recovery another.
"""

from __future__ import annotations

import errno
import logging
import time
from collections.abc import Callable
from pathlib import Path

from fleetdaq.contract.messages import EVENT_TYPE
from fleetdaq.hub.bus import EventBus

Held = tuple[str, bytes, int, int, str]
"""topic, payload, publish time, receive time, message type: as `RecordingSession.write`."""

RETRY_AFTER_ERROR_S = 2.0
MAX_HELD = 10_000


class WriteRecovery:
    def __init__(self, bus: EventBus, abandon: Callable[[], Path | None]) -> None:
        """`abandon`: give up the open file (returned, or None if none was open) and roll every
        stream back to its last ack."""
        self.bus = bus
        self._abandon = abandon
        self.write_errors = 0
        self.events_not_recorded = 0
        self.messages_not_recorded = 0
        self.held: list[Held] = []
        """Events and messages waiting for the disk to take writes again (bounded)."""
        self.unflushed: list[Held] = []
        """Events and messages written since the last successful flush: if the file they went
        into is abandoned, they are held again (data batches roll back and the edges resend)."""
        self._broken_until = 0.0
        self._failure_reported = False

    def writable(self) -> bool:
        return time.monotonic() >= self._broken_until

    def recovering(self) -> bool:
        """A write failed and no flush has succeeded since: what is written now may still go
        down with the next abandoned file, so events and messages wait."""
        return self._broken_until != 0.0

    def abandon(self) -> Path | None:
        """The open file is given up: what was written into it since the last flush is held
        again."""
        abandoned = self._abandon()
        lost_with_file, self.unflushed = self.unflushed, []
        self.held[:0] = lost_with_file
        return abandoned

    def abandon_after_unexpected(self) -> Path | None:
        """As `abandon`, after an error that was not the disk's: writable at once, resumed at
        the next flush."""
        abandoned = self.abandon()
        if not self.recovering():
            self._broken_until = time.monotonic()
        return abandoned

    def failed(self, what: str, err: OSError) -> None:
        """A write, flush or close refused: abandon the file, retry later, say so once."""
        self.write_errors += 1
        first = not self._failure_reported
        self._failure_reported = True
        self._broken_until = time.monotonic() + RETRY_AFTER_ERROR_S
        abandoned = self.abandon()
        if first:
            kept = f"abandoned {abandoned.name} (fleetdaq verify --recover); " if abandoned else ""
            full = err.errno in (errno.ENOSPC, errno.EDQUOT, errno.EFBIG)
            self.bus.emit(
                logging.CRITICAL if full else logging.ERROR,
                "recorder",
                "disk_full" if full else "write_error",
                f"{what} failed: {err}; {kept}not acking, so edges keep spooling; "
                f"retrying every {RETRY_AFTER_ERROR_S:g} s",
                errno=err.errno or 0,
            )

    def hold(self, item: Held) -> None:
        # Kept until writing resumes, so the recording still tells what happened. Past the
        # bound they are still in events.log (events) and counted here.
        if len(self.held) < MAX_HELD:
            self.held.append(item)
        elif item[4] == EVENT_TYPE:
            self.events_not_recorded += 1
        else:
            self.messages_not_recorded += 1

    def flushed(self) -> None:
        self.unflushed = []

    def resume(self, write: Callable[[Held], None]) -> None:
        """A flush succeeded after a write error: the disk takes writes again. Call it only
        after the flush (a write alone may land in MCAP's in-memory chunk and fail later).
        `write` writes each held item again (holding it anew if that fails)."""
        if not self.recovering():
            return
        self._broken_until = 0.0
        held, self.held = self.held, []
        for item in held:
            write(item)
        if self._failure_reported:
            self._failure_reported = False
            self.bus.emit(
                logging.WARNING,
                "recorder",
                "write_resumed",
                f"writing again ({len(held)} held event(s) and message(s) written now); edges "
                "replay what was not acked",
                held=len(held),
            )
