"""Who gets a mail about which alarm transition, and when. Pure: no I/O, time passed in.

Per group (`hub.notify.groups.<name>` in the site file):

- **Matching.** A transition reaches a group when the alarm is at least `min_severity`, its
  node matches one of `nodes` and its name one of `alarms` (fnmatch), and its mail transition
  is in `on`. Mail transitions: ``raised``, ``cleared`` (returned to normal, or latched and
  waiting for an ack), ``acked``. An alarm that comes back from a shelve or from disabled
  (``unshelved``, ``shelve_expired``, ``enabled``) while its condition holds is active-unacked
  again: that is mailed as ``raised``. Coming back to normal, being shelved or disabled is an
  operator's own action, recorded in events and the journal, and not mailed.
- **Digest window** (`digest_s` > 0). In a quiet group the first transition is mailed at
  once and opens a window of `digest_s`; what comes during the window is collected and mailed
  as one digest when it closes (which opens the next window). A window that closes with
  nothing collected leaves the group quiet again.
- **Critical** alarms never wait for a window: each is mailed at once, and still listed (as
  "mailed at once") in the digest of the window it fell in.
- **Rate limit** (`max_per_hour`): a sliding hour. Past it, transitions are collected into the
  next digest, which goes out as soon as the limit allows; nothing is dropped. Critical alarms
  have their own budget of `max_per_hour`, so a flood of minor alarms never delays a critical
  one, and a flood of critical ones still ends in digests (sent when either budget allows: at
  most 2 × `max_per_hour` mails an hour per group).
- **Snooze** (`snooze_s` > 0, MODAQ 2's topicErrorEmailSnooze, per alarm name). After a mail
  about an alarm, further transitions of it for `snooze_s` are held back and counted. When
  the snooze ends, if any were held back, the latest is mailed with the count ("and 6 more
  transitions of this alarm: raised ×3, cleared ×3"), which starts the next snooze: a
  flapping alarm gives one mail per snooze period and its final state is never lost. Every
  mail of the group also lists the alarms being snoozed right now, with their counts.

Everything held (in a window, past a limit, or snoozed) is also reported through
`take_changes` so that the service keeps it on disk (`fleetdaq.hub.supervision.notify.held`): a hub
that is killed mails it after its restart (`recover`). `flush_all` mails everything held at once
(stopping)."""

from __future__ import annotations

import dataclasses
import fnmatch
from collections import Counter, deque
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from typing import Literal

from fleetdaq.contract.messages import AlarmState
from fleetdaq.hub.config.notify import GroupConfig

RATE_WINDOW_S = 3600.0
SEVERITY_RANK = {"info": 0, "minor": 1, "major": 2, "critical": 3}
MAIL_TRANSITIONS = ("raised", "cleared", "acked")
_BACK_IN_SERVICE = {"unshelved", "shelve_expired", "enabled"}


def mail_transition(state: AlarmState) -> str | None:
    """The mail transition of an alarm state change ("raised", "cleared", "acked"), None when
    it is not mailed (shelved, disabled, back in service and normal)."""
    if state.transition in MAIL_TRANSITIONS:
        return state.transition
    if state.transition in _BACK_IN_SERVICE and state.state == "active_unacked":
        return "raised"
    return None


def severity_rank(severity: str) -> int:
    """Higher is more severe; an unknown severity counts as critical (better told than not)."""
    return SEVERITY_RANK.get(severity, SEVERITY_RANK["critical"])


@dataclass(frozen=True, slots=True)
class Item:
    """One transition in a mail."""

    state: AlarmState
    description: str
    what: str
    """"raised", "cleared" or "acked"."""
    at_once: bool = False
    """Already mailed on its own (critical); listed in a digest for completeness."""
    held_back: tuple[tuple[str, int], ...] = ()
    """Transitions of this alarm held back by the snooze, by kind (this one included)."""

    @property
    def critical(self) -> bool:
        return severity_rank(self.state.severity) >= SEVERITY_RANK["critical"]

    @property
    def held_back_total(self) -> int:
        return sum(n for _, n in self.held_back)


@dataclass(frozen=True, slots=True)
class Snoozing:
    """An alarm being snoozed right now, with what was held back so far."""

    alarm: str
    count: int
    ends_in_s: float


@dataclass(frozen=True, slots=True)
class Outgoing:
    """One mail to compose: a single transition or a digest."""

    group: str
    to: tuple[str, ...]
    items: tuple[Item, ...]
    digest: bool
    span_s: float = 0.0
    """How long the digest collected."""
    reason: str = ""
    """Why a digest went out when it did: window, rate limit, critical, stopping, recovered."""
    snoozing: tuple[Snoozing, ...] = ()
    snooze_s: float = 0.0

    @property
    def fresh(self) -> tuple[Item, ...]:
        """The items not already mailed on their own."""
        return tuple(i for i in self.items if not i.at_once)


@dataclass(frozen=True, slots=True)
class Held:
    """One transition a group holds, as kept on disk: in a digest, or snoozed."""

    group: str
    kind: Literal["digest", "snoozed"]
    item: Item


@dataclass(slots=True)
class _Snooze:
    until: float
    count: int = 0
    by: Counter[str] = field(default_factory=Counter)
    latest: Item | None = None


@dataclass(slots=True)
class _Budget:
    """Mails sent in the last hour (a sliding window)."""

    limit: int
    sent: deque[float] = field(default_factory=deque)

    def _prune(self, now: float) -> None:
        while self.sent and self.sent[0] <= now - RATE_WINDOW_S:
            self.sent.popleft()

    def ok(self, now: float) -> bool:
        self._prune(now)
        return len(self.sent) < self.limit

    def release(self, now: float) -> float:
        """When the next mail is allowed."""
        self._prune(now)
        return now if len(self.sent) < self.limit else self.sent[0] + RATE_WINDOW_S

    def spend(self, now: float) -> None:
        self.sent.append(now)


@dataclass(slots=True)
class _Group:
    name: str
    cfg: GroupConfig
    normal: _Budget
    critical: _Budget
    window_end: float | None = None
    since: float | None = None
    """When what the next digest lists began (None: nothing held yet)."""
    """When the collection in `held` started (the window's opening, or the first held item)."""
    held: list[Item] = field(default_factory=list)
    rate_limited: bool = False
    snooze: dict[str, _Snooze] = field(default_factory=dict)

    def matches(self, state: AlarmState, what: str) -> bool:
        c = self.cfg
        return (
            what in c.on
            and severity_rank(state.severity) >= SEVERITY_RANK[c.min_severity]
            and any(fnmatch.fnmatchcase(state.node, p) for p in c.nodes)
            and any(fnmatch.fnmatchcase(state.name, p) for p in c.alarms)
        )

    def window_open(self, now: float) -> bool:
        return self.window_end is not None and now < self.window_end

    def fresh(self) -> list[Item]:
        return [i for i in self.held if not i.at_once]


class Policy:
    """The groups' state: feed it transitions (`offer`) and time (`due`); it says what to mail."""

    def __init__(self, groups: Mapping[str, GroupConfig]) -> None:
        self.groups = {
            name: _Group(name, cfg, _Budget(cfg.max_per_hour), _Budget(cfg.max_per_hour))
            for name, cfg in groups.items()
        }
        self.received = 0
        self.ignored = 0
        """Transitions no group takes (not mailed, or no group matches)."""
        self.suppressed = 0
        """Transitions held back by a snooze."""
        self.deferred = 0
        """Transitions put into a digest because a group was at its hourly limit."""
        self._new: list[Held] = []
        self._consumed = False

    # --- input ---------------------------------------------------------------------------------

    def offer(self, state: AlarmState, description: str, now: float) -> list[Outgoing]:
        """One transition from the supervisor at monotonic time `now`: the mails to send now."""
        self.received += 1
        what = mail_transition(state)
        taken = False
        out: list[Outgoing] = []
        if what is not None:
            for g in self.groups.values():
                if not g.matches(state, what):
                    continue
                taken = True
                item = Item(state, description, what)
                s = g.snooze.get(state.name)
                if s is not None and now < s.until:
                    s.count += 1
                    s.by[what] += 1
                    s.latest = item
                    self.suppressed += 1
                    snoozed = dataclasses.replace(item, held_back=((what, 1),))
                    self._new.append(Held(g.name, "snoozed", snoozed))
                    continue
                if s is not None:  # ended, and `due` has not run since: this one reports it
                    del g.snooze[state.name]
                    if s.count:
                        s.by[what] += 1
                        item = dataclasses.replace(item, held_back=tuple(sorted(s.by.items())))
                        self._consumed = True
                mail = self._route(g, item, now)
                if mail is not None:
                    out.append(mail)
        if not taken:
            self.ignored += 1
        return out

    def due(self, now: float) -> list[Outgoing]:
        """What time alone makes due at `now`: closed windows, freed limits, ended snoozes."""
        out: list[Outgoing] = []
        for g in self.groups.values():
            for alarm, s in list(g.snooze.items()):
                if now < s.until:
                    continue
                del g.snooze[alarm]
                if s.count and s.latest is not None:
                    self._consumed = True
                    item = dataclasses.replace(s.latest, held_back=tuple(sorted(s.by.items())))
                    mail = self._route(g, item, now)
                    if mail is not None:
                        out.append(mail)
            mail = self._flush_due(g, now)
            if mail is not None:
                out.append(mail)
        return out

    def next_deadline(self, now: float) -> float | None:
        """The earliest monotonic time at which `due` may have something to say."""
        times: list[float] = []
        for g in self.groups.values():
            times.extend(s.until for s in g.snooze.values() if s.count)
            fresh = g.fresh()
            if not fresh:
                continue
            if any(i.critical for i in fresh):
                times.append(g.critical.release(now))
            end = g.window_end if g.window_end is not None else now
            times.append(max(end, g.normal.release(now)))
        return min(times) if times else None

    def flush_all(self, now: float, reason: str) -> list[Outgoing]:
        """Mail everything held, whatever the windows and limits say (the hub is stopping)."""
        out: list[Outgoing] = []
        for g in self.groups.values():
            items = list(g.held)
            for s in g.snooze.values():
                if s.count and s.latest is not None:
                    items.append(
                        dataclasses.replace(s.latest, held_back=tuple(sorted(s.by.items())))
                    )
            if g.since is None:  # only snoozed repeats: they span the snoozes
                starts = [s.until - g.cfg.snooze_s for s in g.snooze.values() if s.count]
                g.since = min(starts, default=now)
            g.snooze.clear()
            if any(not i.at_once for i in items):
                g.held = items
                out.append(self._digest(g, now, reason, g.normal))
            else:
                g.held.clear()
        self._consumed = True
        return out

    def recover(self, held: Iterable[Held], now: float) -> list[Outgoing]:
        """Transitions held when the hub last stopped (read back from disk): one digest per
        group that still exists. Snoozed ones are summed per alarm, the latest kept."""
        by_group: dict[str, list[Held]] = {}
        for h in held:
            by_group.setdefault(h.group, []).append(h)
        out: list[Outgoing] = []
        for name, records in by_group.items():
            g = self.groups.get(name)
            if g is None:
                continue
            items = [h.item for h in records if h.kind == "digest"]
            snoozed: dict[str, tuple[Counter[str], Item]] = {}
            for h in records:
                if h.kind == "snoozed":
                    by, _ = snoozed.get(h.item.state.name, (Counter[str](), h.item))
                    by.update(dict(h.item.held_back))
                    snoozed[h.item.state.name] = (by, h.item)
            for by, latest in snoozed.values():
                items.append(dataclasses.replace(latest, held_back=tuple(sorted(by.items()))))
            if items:
                g.held = items + g.held
                g.since = now
                out.append(self._digest(g, now, "recovered", g.normal))
        self._consumed = True
        return out

    # --- what is held, for the disk ----------------------------------------------------------

    def take_changes(self) -> tuple[list[Held], bool]:
        """What was newly held since the last call, and whether anything held was mailed (or
        dropped) since: then the whole of `pending()` must replace what is on disk."""
        new, consumed = self._new, self._consumed
        self._new, self._consumed = [], False
        return new, consumed

    def pending(self) -> list[Held]:
        """Everything held now, as it would be kept on disk."""
        out: list[Held] = []
        for g in self.groups.values():
            out.extend(Held(g.name, "digest", i) for i in g.held if not i.at_once)
            for s in g.snooze.values():
                if s.count and s.latest is not None:
                    item = dataclasses.replace(s.latest, held_back=tuple(sorted(s.by.items())))
                    out.append(Held(g.name, "snoozed", item))
        return out

    def held_count(self) -> int:
        """Transitions waiting in a digest (snoozed ones are counted in `suppressed`)."""
        return sum(len(g.fresh()) for g in self.groups.values())

    # --- inside --------------------------------------------------------------------------------

    def _hold(self, g: _Group, item: Item, now: float) -> None:
        if not g.fresh() and not g.window_open(now):
            g.held = []  # what a closed window listed was mailed already
            g.since = now
        if g.since is None:
            g.since = now  # a digest's span starts with the first thing it holds
        g.held.append(item)
        self._new.append(Held(g.name, "digest", item))

    def _route(self, g: _Group, item: Item, now: float) -> Outgoing | None:
        """A transition past the snooze: mail it now, or hold it for the next digest."""
        if item.critical:
            if not g.critical.ok(now):
                g.rate_limited = True
                self.deferred += 1
                self._hold(g, item, now)
                return None
            budget = g.critical
        elif g.window_open(now):
            self._hold(g, item, now)
            return None
        elif not g.normal.ok(now):
            g.rate_limited = True
            self.deferred += 1
            self._hold(g, item, now)
            return None
        else:
            budget = g.normal
        budget.spend(now)
        listed = dataclasses.replace(item, at_once=True)
        if g.window_open(now) or g.fresh():
            g.held.append(listed)  # the digest to come lists it too
            if g.since is None:
                g.since = now
        elif g.cfg.digest_s > 0:  # a mail in a quiet group opens a window
            g.held = [listed]
            g.since = now
            g.window_end = now + g.cfg.digest_s
        self._snooze(g, [item], now)
        return Outgoing(
            g.name,
            tuple(g.cfg.to),
            (item,),
            digest=False,
            snoozing=self._snoozing(g, now, {item.state.name}),
            snooze_s=g.cfg.snooze_s,
        )

    def _flush_due(self, g: _Group, now: float) -> Outgoing | None:
        fresh = g.fresh()
        if not fresh:
            if not g.window_open(now):
                g.window_end = None
                g.held.clear()
            return None
        if any(i.critical for i in fresh) and g.critical.ok(now):
            return self._digest(g, now, "critical", g.critical)
        if not g.window_open(now) and g.normal.ok(now):
            reason = "rate limit" if g.rate_limited else "window"
            return self._digest(g, now, reason, g.normal)
        return None

    def _digest(self, g: _Group, now: float, reason: str, budget: _Budget) -> Outgoing:
        items = tuple(g.held)
        span = max(0.0, now - g.since) if g.since is not None else 0.0
        g.held = []
        g.rate_limited = False
        budget.spend(now)
        self._consumed = True
        fresh = [i for i in items if not i.at_once]
        self._snooze(g, fresh, now)
        if g.cfg.digest_s > 0:
            g.since = now
            g.window_end = now + g.cfg.digest_s
        else:
            g.window_end = None
        names = {i.state.name for i in fresh}
        return Outgoing(
            g.name,
            tuple(g.cfg.to),
            items,
            digest=True,
            span_s=span,
            reason=reason,
            snoozing=self._snoozing(g, now, names),
            snooze_s=g.cfg.snooze_s,
        )

    def _snooze(self, g: _Group, items: Iterable[Item], now: float) -> None:
        if g.cfg.snooze_s <= 0:
            return
        for i in items:
            g.snooze[i.state.name] = _Snooze(until=now + g.cfg.snooze_s)

    def _snoozing(self, g: _Group, now: float, skip: set[str]) -> tuple[Snoozing, ...]:
        return tuple(
            Snoozing(name, s.count, max(0.0, s.until - now))
            for name, s in sorted(g.snooze.items())
            if s.count and name not in skip
        )
