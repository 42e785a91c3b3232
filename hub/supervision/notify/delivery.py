"""The sender thread: takes mails from the outbox to the SMTP server, retrying with backoff.

- **Sessions.** When mails are due, one SMTP session sends all of them, oldest first.
- **Server outages** (connection refused, TLS or AUTH failing, a timeout, our sender refused):
  every mail stays queued; the next session waits 30 s, then 60, 120, ... up to `retry_max_s`
  (exponential backoff, reset by the first session that works). A mail queued meanwhile gets
  one prompt attempt of its own if the last attempt is at least 30 s old, so a critical alarm
  does not wait out an hour of backoff for a server that came back; such an attempt that
  fails does not lengthen the backoff.
- **One mail's own trouble.** Refused for good (5yz to its content, or to every recipient):
  moved to ``outbox/failed/`` with the reason, an ERROR event, and the next mail goes on.
  Some recipients refused for good and the others accepted: it counts as sent, the refused
  ones are named in an ERROR event, and nobody gets it twice. Deferred (4yz) for some or all
  recipients: the mail is kept for those only and retried on its own backoff, without
  holding up the others.
- **At least once.** A mail leaves the outbox only after the server's 250 to its DATA.
  It can arrive twice when the hub dies, or the connection drops, between the server taking
  it and the file's deletion (the Message-ID is the same both times, so a receiving system
  that deduplicates drops the copy).

The thread never dies of one mail or one server: whatever a pass raises is counted, logged
and retried after the backoff.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from typing import Protocol

from fleetdaq.hub.config.notify import SmtpConfig
from fleetdaq.hub.errors import SecretError
from fleetdaq.hub.supervision.notify.clock import Clock
from fleetdaq.hub.supervision.notify.credentials import Secret
from fleetdaq.hub.supervision.notify.outbox import Entry, Outbox, OutboxError
from fleetdaq.hub.supervision.notify.transport import (
    Result,
    SessionError,
    SmtpSession,
    describe,
    tls_context,
)
from fleetdaq.runtime.threads import NamedThread

log = logging.getLogger("fleetdaq.notify")

RETRY_MIN_S = 30.0
STOP_GRACE_S = 5.0
"""At stop, the last pass may take this long (and no longer than the SMTP timeout)."""
IDLE_WAIT_S = 60.0
"""With nothing queued, the thread still wakes this often (a kick wakes it at once)."""


class Events(Protocol):
    def __call__(self, level: int, tag: str, message: str, /, **fields: object) -> None: ...


def _duration(seconds: float) -> str:
    s = round(seconds)
    return f"{s} s" if s < 120 else f"{round(s / 60)} min"


class Delivery:
    """The sender thread and its counters (read them from any thread)."""

    def __init__(
        self,
        smtp: SmtpConfig,
        password: Callable[[], Secret | None],
        outbox: Outbox,
        clock: Clock,
        events: Events,
        changed: Callable[[], None],
        retry_max_s: float,
        retry_min_s: float = RETRY_MIN_S,
    ) -> None:
        self.smtp = smtp
        self.password = password
        self.outbox = outbox
        self.clock = clock
        self.events = events
        self.changed = changed
        self.retry_min_s = retry_min_s
        self.retry_max_s = retry_max_s
        self.context = tls_context(smtp)
        self.sent = 0
        self.failed_attempts = 0
        self.rejected = 0
        """Mails refused for good (moved to failed/)."""
        self.rejected_recipients = 0
        """Recipients refused for good of mails the others got."""
        self.errors = 0
        self.last_error = ""
        self.last_error_ns = 0
        self.last_sent_ns = 0
        self.failing_since: float | None = None
        """Wall time of the first failed session of the current run of failures."""
        self.next_attempt = 0.0
        self.died: str | None = None
        self._streak = 0
        self._last_attempt = -float("inf")
        self._kicked = False
        self._stop = threading.Event()
        self._abort = threading.Event()
        self._wake = threading.Event()
        self._thread = NamedThread(target=self._main, name="notify-delivery", daemon=True)

    # --- lifecycle -----------------------------------------------------------------------------

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        """One last pass sends what is due (a few seconds at most), then the thread ends.
        What it could not send stays queued for the next start."""
        self._stop.set()
        self._wake.set()
        if self._thread.is_alive():
            self._thread.join(min(self.smtp.timeout_s, STOP_GRACE_S))
            self._abort.set()
            self._thread.join(1.0)
            if self._thread.is_alive():
                log.warning(
                    "e-mail: the sender is still waiting for %s:%d; leaving it (its "
                    "mail stays queued)",
                    self.smtp.host,
                    self.smtp.port,
                )

    def kick(self) -> None:
        """A mail was queued: try it soon (see the module's note on prompt attempts)."""
        self._kicked = True
        self._wake.set()

    @property
    def alive(self) -> bool:
        return self._thread.is_alive()

    @property
    def failing(self) -> bool:
        return self._streak > 0

    # --- the thread ----------------------------------------------------------------------------

    def _main(self) -> None:
        try:
            self._run()
        except BaseException as err:
            self.died = describe(err)
            log.critical("e-mail: the sender thread died: %s", self.died, exc_info=True)
            raise

    def _run(self) -> None:
        while True:
            self._wake.clear()
            try:
                self._pass()
            except Exception as err:
                # Not a server's doing (those are SessionErrors): a disk error on the outbox,
                # or a bug. Count it, say it, and wait like after a failed session.
                self.errors += 1
                self._failed(f"e-mail sender: {describe(err)}", prompt=False)
                log.debug("delivery pass failed", exc_info=True)
            self.changed()
            if self._stop.is_set():
                return
            self.clock.wait(self._wake, self._wait_s())

    def _wait_s(self) -> float:
        now = self.clock.monotonic()
        first = self.outbox.next_try()
        if first is None:
            return IDLE_WAIT_S
        return max(0.0, max(first, self.next_attempt) - now)

    def _pass(self) -> None:
        now = self.clock.monotonic()
        due = self.outbox.due(now)
        if not due:
            self._kicked = False
            return
        prompt = self._kicked and now - self._last_attempt >= self.retry_min_s
        self._kicked = False
        if now < self.next_attempt and not prompt:
            return
        self._last_attempt = now
        try:
            password = self.password()
            with SmtpSession(self.smtp, password, self.context) as session:
                sent = 0
                for entry in due:
                    if self._abort.is_set():
                        break
                    sent += self._send_one(session, entry)
                    if sent and sent % 100 == 0:
                        log.info("e-mail: %d sent, %d still queued", sent, len(self.outbox))
        except (SessionError, SecretError) as err:
            self._failed(str(err), prompt=now < self.next_attempt)
            return
        self._ok(sent)

    def _send_one(self, session: SmtpSession, entry: Entry) -> int:
        """Offer one mail; 1 when it is done. A SessionError goes up (the server is gone);
        anything else is this mail's own trouble: it waits its own backoff, the others go on."""
        try:
            return self._offer(session, entry)
        except SessionError:
            raise
        except Exception as err:
            self.errors += 1
            entry.attempts += 1
            delay = min(self.retry_min_s * 2 ** (entry.attempts - 1), self.retry_max_s)
            entry.next_try = self.clock.monotonic() + delay
            self._note_error(f"mail {entry.name}: {describe(err)}; trying it again later")
            log.debug("mail %s failed", entry.name, exc_info=True)
            return 0

    def _offer(self, session: SmtpSession, entry: Entry) -> int:
        env = entry.envelope
        try:
            message = self.outbox.read(entry)
        except (OSError, OutboxError) as err:
            self.rejected += 1
            self.outbox.reject(entry, f"cannot read it back: {describe(err)}")
            self._note_error(f"mail {entry.name}: cannot read it back: {describe(err)}")
            return 0
        result = session.send(env.sender, env.to, message)
        if result.refused:
            self.rejected_recipients += len(result.refused)
            who = "; ".join(f"{r}: {why}" for r, why in result.refused.items())
            self._note_error(f"refused for good: {who}")
            if result.outcome != "rejected":
                self.events(
                    logging.ERROR,
                    "mail_recipient_refused",
                    f"e-mail {env.subject!r}: refused for good for {who}; not retried for "
                    f"them{', the others got it' if result.accepted else ''}",
                    group=env.group,
                    refused=", ".join(result.refused),
                )
        if result.outcome == "sent":
            self.outbox.delivered(entry)
            self.sent += 1
            self.last_sent_ns = time.time_ns()
            self.changed()
            return 1
        if result.outcome == "rejected":
            self.rejected += 1
            self.outbox.reject(entry, result.reason)
            self._note_error(f"mail {entry.name}: {result.reason}")
            self.events(
                logging.ERROR,
                "mail_rejected",
                f"e-mail {env.subject!r} to {', '.join(env.to)} refused for good: "
                f"{result.reason}; kept in {self.outbox.failed_dir}, not retried",
                group=env.group,
                file=entry.name,
            )
            return 0
        self._defer(entry, result)
        return 0

    def _defer(self, entry: Entry, result: Result) -> None:
        if result.retry_to != entry.envelope.to:
            self.outbox.narrow(entry, result.retry_to)
        entry.attempts += 1
        delay = min(self.retry_min_s * 2 ** (entry.attempts - 1), self.retry_max_s)
        entry.next_try = self.clock.monotonic() + delay
        self.failed_attempts += 1
        self._note_error(
            f"mail {entry.name} deferred ({result.reason}); trying again in {_duration(delay)}"
        )

    def _note_error(self, text: str) -> None:
        self.last_error = text
        self.last_error_ns = time.time_ns()
        log.warning("e-mail: %s", text)

    def _failed(self, why: str, prompt: bool) -> None:
        """A session failed: everything stays queued until the backoff ends."""
        self.failed_attempts += 1
        self._note_error(why)
        if prompt:  # a prompt attempt for a new mail: the backoff's schedule stands
            return
        self._streak += 1
        delay = min(self.retry_min_s * 2 ** (self._streak - 1), self.retry_max_s)
        self.next_attempt = self.clock.monotonic() + delay
        if self._streak == 1:
            self.failing_since = self.clock.time()
            self.events(
                logging.WARNING,
                "mail_failing",
                f"e-mail: cannot deliver: {why}; {len(self.outbox)} mail(s) queued in "
                f"{self.outbox.dir}, trying again in {_duration(delay)} (backing off to "
                f"{_duration(self.retry_max_s)})",
                queued=len(self.outbox),
            )

    def _ok(self, sent: int) -> None:
        if self._streak:
            since = self.failing_since
            took = self.clock.time() - since if since is not None else 0.0
            self.events(
                logging.INFO,
                "mail_recovered",
                f"e-mail: delivering again after {_duration(took)} of failures; {sent} queued "
                f"mail(s) sent, {len(self.outbox)} left",
                sent=sent,
                queued=len(self.outbox),
            )
        self._streak = 0
        self.failing_since = None
        self.next_attempt = 0.0
