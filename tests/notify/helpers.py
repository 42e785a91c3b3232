"""What the notifier's tests share: a clock the test moves, a read model and an event bus one
can wait on, alarm transitions, and configs."""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from fleetdaq.contract.messages import AlarmState, Event
from fleetdaq.hub.bus import EventBus
from fleetdaq.hub.config.notify import NotifyConfig
from fleetdaq.hub.read_model import ReadModel
from fleetdaq.hub.supervision.notification import Notification
from fleetdaq.hub.supervision.notify.service import EmailNotifier
from tests.notify.smtp_server import WAIT_S


class ManualClock:
    """Time moves only when the test says (`advance`), and wakes whoever waits on it."""

    def __init__(self) -> None:
        self._mono = 1000.0
        self._wall = float(int(time.time()))  # whole seconds: ages after whole advances are exact
        self._lock = threading.Lock()
        self._waiters: set[threading.Event] = set()

    def monotonic(self) -> float:
        with self._lock:
            return self._mono

    def time(self) -> float:
        with self._lock:
            return self._wall

    def advance(self, seconds: float) -> None:
        with self._lock:
            self._mono += seconds
            self._wall += seconds
            waiters = list(self._waiters)
        for event in waiters:
            event.set()

    def wait(self, event: threading.Event, timeout: float) -> bool:
        if timeout <= 0:
            return event.is_set()
        with self._lock:
            self._waiters.add(event)
        try:
            # `advance` sets the event; the short real-time bound only covers an advance that
            # lands between a caller reading the clock and getting here (it then looks again).
            return event.wait(0.2)
        finally:
            with self._lock:
                self._waiters.discard(event)


class WatchedModel(ReadModel):
    """A read model a test can wait on: `wait_notifier(pred)` returns once a published
    `notifier` part satisfies `pred`.

    Given the `outbox` directory, it also looks at the disk as each `notifier` part arrives
    and keeps every one whose ``queued`` was more than the mail files there (`ahead_of_disk`,
    as (queued, files)). Only meaningful while no mail is delivered: one deleted between the
    counting and the look would show up here."""

    def __init__(self, site: str, outbox: Path | None = None) -> None:
        super().__init__(site)
        self._cond = threading.Condition()
        self._outbox = outbox
        self.ahead_of_disk: list[tuple[int, int]] = []

    def put(self, part: str, value: Any) -> None:
        if part == "notifier" and self._outbox is not None:
            files = len(list(self._outbox.glob("*.mail"))) if self._outbox.is_dir() else 0
            if value["queued"] > files:
                self.ahead_of_disk.append((value["queued"], files))
        super().put(part, value)
        with self._cond:
            self._cond.notify_all()

    @property
    def notifier(self) -> dict[str, Any]:
        return self.snapshot().notifier

    def wait_notifier(
        self, pred: Callable[[dict[str, Any]], bool], timeout: float = WAIT_S
    ) -> dict[str, Any]:
        with self._cond:
            ok = self._cond.wait_for(lambda: bool(self.notifier) and pred(self.notifier), timeout)
        assert ok, f"the notifier never got there; it says {self.notifier}"
        return self.notifier


class Events:
    """Every event on the bus, to wait on."""

    def __init__(self, bus: EventBus) -> None:
        self.all: list[Event] = []
        self._cond = threading.Condition()
        bus.subscribe("test-events", self._on)

    def _on(self, event: Event) -> None:
        with self._cond:
            self.all.append(event)
            self._cond.notify_all()

    def tagged(self, tag: str) -> list[Event]:
        with self._cond:
            return [e for e in self.all if e.tag == tag]

    def wait_tag(self, tag: str, timeout: float = WAIT_S) -> Event:
        with self._cond:
            ok = self._cond.wait_for(lambda: any(e.tag == tag for e in self.all), timeout)
        assert ok, f"no {tag!r} event; got {[e.tag for e in self.all]}"
        return self.tagged(tag)[0]


def alarm(
    name: str = "substrate_hot",
    transition: str = "raised",
    severity: str = "major",
    node: str = "am-cell",
    state: str | None = None,
    value: float = 412.5,
    user: str = "",
    host: str = "",
    note: str = "",
    t_ns: int | None = None,
    description: str = "",
) -> Notification:
    """One transition as the supervisor hands it over."""
    now = t_ns if t_ns is not None else time.time_ns()
    default_state = {
        "raised": "active_unacked",
        "cleared": "normal",
        "acked": "active_acked",
        "shelved": "shelved",
        "disabled": "disabled",
    }.get(transition, "active_unacked")
    s = AlarmState(
        time_ns=now, name=name, kind="channel", node=node, stream="tc", channel="substrate",
        condition="substrate > 400 degC", severity=severity, state=state or default_state,
        active=transition != "cleared", transition=transition,
        value=value if transition == "raised" else math.nan, unit="degC", since_ns=now,
        count=1, user=user, host=host, note=note, shelved_until_ns=0,
    )  # fmt: skip
    return Notification(s, description)


def config(
    groups: dict[str, dict[str, Any]],
    smtp: dict[str, Any] | None = None,
    **extra: Any,
) -> NotifyConfig:
    doc: dict[str, Any] = {"groups": groups, **extra}
    if smtp is not None:
        doc["smtp"] = {"sender": "hub@buoy.example", "timeout_s": 5, **smtp}
    return NotifyConfig.model_validate(doc)


@contextmanager
def running(
    cfg: NotifyConfig,
    outbox: Path,
    clock: ManualClock | None = None,
    site: str = "buoy-1",
    *,
    watch_disk: bool = False,
) -> Iterator[tuple[EmailNotifier, WatchedModel, Events]]:
    """A started notifier with its bus and model; stopped (and the bus too) at the end.
    `watch_disk`: the model compares each ``queued`` with the outbox (see `WatchedModel`)."""
    bus = EventBus()
    events = Events(bus)
    model = WatchedModel(site, outbox if watch_disk else None)
    bus.start()
    kwargs: dict[str, Any] = {} if clock is None else {"clock": clock}
    notifier = EmailNotifier(cfg, site, outbox, bus, model, **kwargs)
    try:
        notifier.start()
        yield notifier, model, events
    finally:
        notifier.stop()
        bus.stop()
