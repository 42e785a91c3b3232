"""The e-mail notifier as a hub service: takes the supervisor's transitions, mails them.

    supervisor ──submit()──▶ queue ──▶ policy thread: policy → compose → outbox (fsync)
                                                          │ held for a digest → held.jsonl sender
                                        thread ◀───┘ (fleetdaq.hub.supervision.notify.delivery) ──▶
                                        SMTP

`submit` puts the transition in a bounded in-memory queue and returns: it never blocks and
never raises (past 100 000 waiting transitions it drops, counts and says so). The policy
thread decides, composes and queues mails on disk; the sender thread delivers them. Neither
thread dies of one bad transition or one bad server: errors are counted, logged, raised as
events, and work goes on. If a thread dies anyway, `failure()` says so and the hub stops.

Without ``smtp:`` the notifier still decides and composes (the counters show what would
have been mailed) but sends nothing and writes nothing; it says so once, as an INFO event,
at start.

The read model's ``notifier`` part (see `counters`) is what the dashboard shows and what the
supervisor's universal alarm ``notifications_failing`` watches (``oldest_queued_age_s``). Its
``queued`` is the outbox's own count of mails complete on disk, never a tally kept beside it:
a mail composed but not yet written (or that the outbox cannot take) is ``unwritten``.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from pathlib import Path

from fleetdaq.hub.bus import EventBus
from fleetdaq.hub.config.notify import NotifyConfig
from fleetdaq.hub.errors import NotifyError
from fleetdaq.hub.read_model import NOTIFIER, NotifierCounters, ReadModel
from fleetdaq.hub.supervision.notification import Notification
from fleetdaq.hub.supervision.notify.clock import SYSTEM_CLOCK, Clock
from fleetdaq.hub.supervision.notify.compose import Letterhead, compose
from fleetdaq.hub.supervision.notify.credentials import Secret, read_password
from fleetdaq.hub.supervision.notify.delivery import RETRY_MIN_S, Delivery
from fleetdaq.hub.supervision.notify.held import HeldJournal
from fleetdaq.hub.supervision.notify.outbox import Envelope, Outbox
from fleetdaq.hub.supervision.notify.policy import Outgoing, Policy
from fleetdaq.hub.supervision.notify.transport import describe
from fleetdaq.runtime.threads import NamedThread

log = logging.getLogger("fleetdaq.notify")

QUEUE_LIMIT = 100_000
PUBLISH_S = 1.0
"""The counters are published at least this often (`oldest_queued_age_s` grows on its own)."""
MIN_WAIT_S = 0.01
REPORT_EVERY_S = 60.0
"""Repeated trouble of one kind (drops, internal errors) is raised at most this often."""
BATCH = 5_000
"""Transitions handled per pass before the held ones are synced to disk."""


class EmailNotifier:
    """The `notifier` service (a `fleetdaq.hub.supervision.notification.Notifier` for the
    supervisor)."""

    name = "notifier"

    def __init__(
        self,
        cfg: NotifyConfig,
        site: str,
        outbox_dir: Path,
        bus: EventBus,
        model: ReadModel,
        *,
        clock: Clock = SYSTEM_CLOCK,
        retry_min_s: float = RETRY_MIN_S,
        queue_limit: int = QUEUE_LIMIT,
    ) -> None:
        """`outbox_dir`: where mails wait (the runtime passes ``cfg.outbox_dir`` or
        ``<data_dir>/outbox``). `clock` and `retry_min_s` are for tests."""
        self.cfg = cfg
        self.site = site
        self.bus = bus
        self.model = model
        self.clock = clock
        self.retry_min_s = retry_min_s
        sender = cfg.smtp.sender if cfg.smtp is not None else f"fleetdaq@{site}.invalid"
        self.head = Letterhead(site, sender, cfg.dashboard_url)
        self.policy = Policy(cfg.groups)
        self.outbox = Outbox(outbox_dir) if cfg.smtp is not None else None
        self.held = HeldJournal(outbox_dir / "held.jsonl") if cfg.smtp is not None else None
        self.delivery: Delivery | None = None
        self._queue: queue.Queue[Notification] = queue.Queue(queue_limit)
        self._secrets: list[Secret] = []
        self._unwritten: list[tuple[Envelope, bytes]] = []
        """Composed mails not in the outbox yet (in memory: a kill -9 loses them). Normally
        only while a pass writes them; when the outbox cannot take them (disk full,
        read-only), until it can: retried every pass."""
        self._outbox_failing = False
        """The last write to the outbox failed."""
        self._held_dirty = False
        self._held_now = 0
        """Transitions held for digests, as last synced to disk (what `held` publishes)."""
        self._lock = threading.Lock()
        self._wake = threading.Event()
        self._stopping = threading.Event()
        self._thread = NamedThread(target=self._main, name="notify-policy", daemon=True)
        self._started = False
        self._started_wall = 0.0
        self._stopped = False
        self._died: str | None = None
        self.received = 0
        self.dropped = 0
        self.composed = 0
        self.digests = 0
        self.errors = 0
        self.last_error = ""
        self.last_error_ns = 0
        self.last_subject = ""
        self._dropped_reported = 0
        self._last_report: dict[str, float] = {}

    # --- the seam ------------------------------------------------------------------------------

    def submit(self, n: Notification) -> None:
        """Take one transition. Never blocks, never raises."""
        try:
            self.received += 1
            self._queue.put_nowait(n)
            self._wake.set()
        except queue.Full:
            self.dropped += 1
        except Exception:  # submit must never raise into the supervisor
            self.errors += 1

    # --- lifecycle -----------------------------------------------------------------------------

    def start(self) -> None:
        """Read the password, open the outbox, mail what a previous run left, start the threads.

        Raises SecretError (the password) or NotifyError (the outbox, the CA file): the hub
        then refuses to start, with that one line.
        """
        if self._started:
            return
        smtp = self.cfg.smtp
        self._started_wall = self.clock.time()
        recovered: list[Outgoing] = []
        if smtp is not None and self.outbox is not None and self.held is not None:
            secret = read_password(smtp)
            if secret is not None:
                self._secrets.append(secret)
            try:
                bad = self.outbox.open()
            except OSError as err:
                raise NotifyError(
                    f"e-mail outbox {self.outbox.dir}: {err.strerror or err}"
                ) from None
            self.delivery = Delivery(
                smtp,
                self._password,
                self.outbox,
                self.clock,
                self._event,
                self._publish,
                self.cfg.retry_max_s,
                self.retry_min_s,
            )
            for name in bad:
                self._event(
                    logging.ERROR,
                    "mail_unreadable",
                    f"e-mail: {name} in the outbox cannot be read; moved to "
                    f"{self.outbox.failed_dir}",
                )
            held = self.held.load()
            gone = sorted({h.group for h in held} - set(self.cfg.groups))
            if gone:
                self._event(
                    logging.WARNING,
                    "notify_groups_gone",
                    f"e-mail: transitions held for group(s) {', '.join(gone)} when the hub "
                    "stopped are dropped: the site file no longer has those groups",
                )
            recovered = self.policy.recover(held, self.clock.monotonic())
        self._started = True
        self._say_hello(sum(len(o.fresh) for o in recovered))
        if recovered:
            self._mail(recovered)
            self._sync_held()
        self._thread.start()
        if self.delivery is not None:
            self.delivery.start()
            self.delivery.kick()
        self._publish()

    def stop(self) -> None:
        """Mail everything held for a digest (into the outbox), then stop both threads.
        Idempotent; what is queued stays on disk for the next start."""
        if not self._started or self._stopped:
            return
        self._stopped = True
        self._stopping.set()
        self._wake.set()
        if self._thread.is_alive():
            self._thread.join(10.0)
        if self.delivery is not None:
            self.delivery.kick()
            self.delivery.stop()
        if self.held is not None:
            self.held.close()
        self._publish()

    def failure(self) -> str | None:
        if self._died is not None:
            return f"the notifier's policy thread died: {self._died}"
        d = self.delivery
        if d is not None and d.died is not None:
            return f"the notifier's sender thread died: {d.died}"
        if self._started and not self._stopped:
            if not self._thread.is_alive():
                return "the notifier's policy thread is not running"
            if d is not None and not d.alive:
                return "the notifier's sender thread is not running"
        return None

    # --- the policy thread ---------------------------------------------------------------------

    def _main(self) -> None:
        try:
            self._run()
        except BaseException as err:
            self._died = describe(err)
            log.critical("e-mail: the policy thread died: %s", self._died, exc_info=True)
            raise

    def _run(self) -> None:
        while True:
            self._wake.clear()
            stopping = self._stopping.is_set()
            try:
                self._pass()
                if stopping and self._queue.empty():
                    self._mail(self.policy.flush_all(self.clock.monotonic(), "stopping"))
                    self._sync_held()
            except Exception as err:
                self._trouble(
                    "notify_error", f"e-mail: a pass of the notifier failed: {describe(err)}"
                )
                log.debug("notifier pass failed", exc_info=True)
            self._publish()
            if stopping and self._queue.empty():
                return
            now = self.clock.monotonic()
            deadline = self.policy.next_deadline(now)
            timeout = PUBLISH_S if deadline is None else min(PUBLISH_S, deadline - now)
            # a deadline already passed is due at the next pass; never spin on one
            self.clock.wait(self._wake, max(MIN_WAIT_S, timeout))

    def _pass(self) -> None:
        now = self.clock.monotonic()
        self._write_unwritten()
        outs = self.policy.due(now)
        for _ in range(BATCH):
            try:
                n = self._queue.get_nowait()
            except queue.Empty:
                break
            try:
                outs.extend(self.policy.offer(n.state, n.description, now))
            except Exception as err:
                self._trouble(
                    "notify_error",
                    f"e-mail: a transition could not be handled "
                    f"({describe(err)}); it is not mailed",
                )
        else:
            self._wake.set()  # more waiting: come back at once
        self._mail(outs)
        self._sync_held()
        if self.dropped > self._dropped_reported and self._due_report("dropped"):
            lost = self.dropped - self._dropped_reported
            self._dropped_reported = self.dropped
            self._event(
                logging.ERROR,
                "notify_dropped",
                f"e-mail: {lost} transition(s) dropped: more than {self._queue.maxsize} were "
                "waiting",
                dropped=lost,
            )

    def _mail(self, outs: list[Outgoing]) -> None:
        """Compose each mail and queue it in the outbox (or only count it, without smtp:)."""
        for out in outs:
            try:
                group = self.cfg.groups.get(out.group)
                msg = compose(
                    self.head,
                    out,
                    self.clock.time(),
                    group.max_per_hour if group else 0,
                    group.digest_s if group else 0.0,
                )
                data = msg.as_bytes()
            except Exception as err:
                self._trouble(
                    "notify_error",
                    f"e-mail: a mail for group {out.group} could not be composed: {describe(err)}",
                )
                continue
            self.composed += 1
            self.digests += out.digest
            self.last_subject = str(msg["Subject"])
            if self.outbox is None:
                log.debug("not sent (no smtp: configured): %s", self.last_subject)
                continue
            envelope = Envelope(
                out.group, self.clock.time(), self.head.sender, out.to, self.last_subject
            )
            self._unwritten.append((envelope, data))
        self._write_unwritten()

    def _write_unwritten(self) -> None:
        if self.outbox is None or not self._unwritten:
            return
        while self._unwritten:
            envelope, data = self._unwritten[0]
            try:
                self.outbox.put(envelope, data)
            except OSError as err:
                self._outbox_failing = True
                self._trouble(
                    "outbox_error",
                    f"e-mail: cannot write to the outbox "
                    f"{self.outbox.dir}: {describe(err)}; "
                    f"{len(self._unwritten)} mail(s) wait in memory",
                )
                return
            self._unwritten.pop(0)
        self._outbox_failing = False
        if self.delivery is not None:
            self.delivery.kick()

    def _sync_held(self) -> None:
        """Keep on disk what the groups hold. A digest is in the outbox before the transitions
        it carries leave the held file."""
        new, consumed = self.policy.take_changes()
        if self.held is None:
            self._held_now = self.policy.held_count()
            return
        try:
            if (consumed or self._held_dirty) and not self._unwritten:
                self.held.rewrite(self.policy.pending())
                self._held_dirty = False
            else:
                self._held_dirty |= consumed
                self.held.append(new)
            self._held_now = self.policy.held_count()
        except OSError as err:
            self._held_dirty = True
            self._trouble("outbox_error", f"e-mail: cannot write {self.held.path}: {describe(err)}")

    # --- what the hub sees ---------------------------------------------------------------------

    def counters(self) -> NotifierCounters:
        """The read model's ``notifier`` part."""
        smtp, d = self.cfg.smtp, self.delivery
        now = self.clock.time()
        unwritten = list(self._unwritten)  # one look: the policy thread changes it meanwhile
        created = [e.created for e, _ in unwritten]
        if self.outbox is not None and (oldest := self.outbox.oldest_created()) is not None:
            created.append(oldest)
        # Mails a previous run left count from this start: the alarm on this age says that
        # delivery is failing now, not that the hub was off (they usually go in a moment).
        age = max(0.0, now - max(min(created), self._started_wall)) if created else 0.0
        # Only what the outbox holds on disk: an operator reading `queued` may count on each
        # of those mails surviving a kill -9. Adding the mails still in memory made it run
        # ahead of the disk while a pass was writing them.
        queued = len(self.outbox) if self.outbox is not None else 0
        if smtp is None:
            state = "off"
        elif (d is not None and d.failing) or self._outbox_failing:
            state = "failing"
        else:
            state = "sending" if queued or unwritten else "idle"
        next_in = 0.0
        if d is not None and d.failing:
            next_in = max(0.0, d.next_attempt - self.clock.monotonic())
        last_error = self.last_error
        if d is not None and d.last_error_ns > self.last_error_ns:
            last_error = d.last_error
        return {
            "enabled": bool(self.cfg.groups),
            "smtp": smtp is not None,
            "server": f"{smtp.host}:{smtp.port} ({smtp.security})" if smtp is not None else "",
            "state": state,
            "groups": sorted(self.cfg.groups),
            "received": self.received,
            "ignored": self.policy.ignored,
            "composed": self.composed,
            "digests": self.digests,
            "suppressed": self.policy.suppressed,
            "deferred": self.policy.deferred,
            "held": self._held_now,
            "queued": queued,
            "unwritten": len(unwritten),
            "sent": d.sent if d is not None else 0,
            "failed_attempts": d.failed_attempts if d is not None else 0,
            "rejected": d.rejected if d is not None else 0,
            "rejected_recipients": d.rejected_recipients if d is not None else 0,
            "dropped": self.dropped,
            "errors": self.errors + (d.errors if d is not None else 0),
            "oldest_queued_age_s": age,
            "next_attempt_in_s": next_in,
            "last_error": self._redact(last_error),
            "last_subject": self.last_subject,
            "outbox": str(self.outbox.dir) if self.outbox is not None else "",
        }

    def _publish(self) -> None:
        try:
            with self._lock:
                self.model.put(NOTIFIER, self.counters())
        except Exception:
            log.exception("e-mail: cannot publish the notifier's counters")

    # --- inside --------------------------------------------------------------------------------

    def _say_hello(self, recovered: int) -> None:
        smtp, groups = self.cfg.smtp, len(self.cfg.groups)
        if smtp is None:
            self._event(
                logging.INFO,
                "notify_off",
                f"e-mail: no SMTP server configured (hub.notify.smtp): {groups} group(s); "
                "mails are composed and counted, not sent",
                groups=groups,
            )
            return
        assert self.outbox is not None
        who = f" as {smtp.username}" if smtp.username else ""
        extra = (
            f"; {recovered} transition(s) held for digests at the last stop mailed now"
            if (recovered)
            else ""
        )
        self._event(
            logging.INFO,
            "notify_started",
            f"e-mail: {groups} group(s) via {smtp.host}:{smtp.port} ({smtp.security}{who}); "
            f"outbox {self.outbox.dir} holds {len(self.outbox)} mail(s){extra}",
            groups=groups,
            queued=len(self.outbox),
        )

    def _password(self) -> Secret | None:
        """Read again for every session: a rotated password file needs no restart."""
        assert self.cfg.smtp is not None
        secret = read_password(self.cfg.smtp)
        if secret is not None and all(s.reveal() != secret.reveal() for s in self._secrets):
            self._secrets.append(secret)
        return secret

    def _redact(self, text: str) -> str:
        for s in self._secrets:
            text = s.redact(text)
        return text

    def _event(self, level: int, tag: str, message: str, /, **fields: object) -> None:
        clean = {k: self._redact(v) if isinstance(v, str) else v for k, v in fields.items()}
        text = self._redact(message)
        log.log(level, "%s", text)
        self.bus.emit(level, "notifier", tag, text, **clean)

    def _due_report(self, kind: str) -> bool:
        now = self.clock.monotonic()
        last = self._last_report.get(kind)
        if last is not None and now - last < REPORT_EVERY_S:
            return False
        self._last_report[kind] = now
        return True

    def _trouble(self, tag: str, message: str) -> None:
        self.errors += 1
        self.last_error = self._redact(message)
        self.last_error_ns = time.time_ns()
        if self._due_report(tag):
            self._event(logging.ERROR, tag, message, errors=self.errors)
        else:
            log.error("%s", self._redact(message))
