"""Rules and cross-node interlocks on the hub: conditions on live values, alarm states, node
liveliness and output readbacks, turned into commands on any node.

A rule: when `when` has held for `for_s` and `precondition` holds, do `do` once (an episode),
and `on_clear` when `when` stops holding; a new episode not within `cooldown_s` of the last
firing. An interlock: while `when` holds, the command service refuses commands to its outputs,
and with `force_safe` they are set to their safe values when it trips.

Channel conditions are evaluated on every batch as it arrives (`fleetdaq.hub.recording.batch_feed`,
on this service's own thread), sample by sample in numpy
(`fleetdaq.hub.supervision.alarms.conditions.SampleCondition`), in acquisition time; a rule whose
`when` is one channel condition counts `for_s` in acquisition time too, so it fires within a batch
of the moment the samples allow. Alarm, node and output conditions are read from the hub's read
model five times a second. Actions run on a small pool (a command waits for its edge's reply):
evaluation never waits for the network."""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from enum import StrEnum

import numpy as np

from fleetdaq.contract.keys import SiteKeys
from fleetdaq.contract.wire import batch_values
from fleetdaq.hub.bus import EventBus
from fleetdaq.hub.config.control import (
    Action,
    AlarmCondition,
    AllCondition,
    AnyCondition,
    ChannelCondition,
    Condition,
    EventAction,
    InterlockConfig,
    NodeCondition,
    NotCondition,
    OutputCondition,
    PulseAction,
    RecordAction,
    RuleConfig,
    SetAction,
)
from fleetdaq.hub.config.site import SiteConfig
from fleetdaq.hub.control.commands import CommandService
from fleetdaq.hub.read_model import (
    RULES,
    HubView,
    InterlockDict,
    ReadModel,
    RuleDict,
    RulesDict,
)
from fleetdaq.hub.recording.batch_feed import BatchFeed, FedBatch
from fleetdaq.hub.requests import Caller, ControlAction, OperatorQueryable
from fleetdaq.hub.routing.router import Router
from fleetdaq.hub.supervision.alarms.conditions import SampleCondition
from fleetdaq.runtime.threads import NamedThread, name_os_thread

log = logging.getLogger("fleetdaq.rules")

TICK_S = 0.2
_IN_ALARM = {"active_unacked", "active_acked", "returned_unacked"}
_LEVELS = {
    "info": logging.INFO,
    "warning": logging.WARNING,
    "error": logging.ERROR,
    "critical": logging.CRITICAL,
}


class ChannelLeaf:
    """A channel condition's current truth, from the batches (and, for a rule that counts
    `for_s` on it, with that on-delay in acquisition time)."""

    def __init__(self, c: ChannelCondition, on_delay_ns: int = 0) -> None:
        node, stream, channel = c.channel.split("/")
        self.node, self.stream, self.channel = node, stream, channel
        check = "above" if c.above is not None else "below"
        limit = c.above if c.above is not None else c.below
        assert limit is not None
        self.cond = SampleCondition(check, limit, c.deadband, on_delay_ns, 0)
        self.value = math.nan
        self.since_ns = 0

    @property
    def holds(self) -> bool:
        return self.cond.active


def _state_matches(state: str, wanted: str) -> bool:
    if wanted == "in_alarm":
        return state in _IN_ALARM
    if wanted == "active":
        return state in ("active_unacked", "active_acked")
    if wanted == "unacked":
        return state in ("active_unacked", "returned_unacked")
    return state == wanted


class Tree:
    """A condition tree with its channel leaves; evaluated against the latest read model."""

    def __init__(self, cond: Condition, on_delay_ns: int = 0) -> None:
        self.cond = cond
        self.leaves: dict[int, ChannelLeaf] = {}
        self._build(cond, on_delay_ns if isinstance(cond, ChannelCondition) else 0)

    def _build(self, c: Condition, delay: int) -> None:
        if isinstance(c, ChannelCondition):
            self.leaves[id(c)] = ChannelLeaf(c, delay)
        elif isinstance(c, AllCondition):
            for x in c.all:
                self._build(x, 0)
        elif isinstance(c, AnyCondition):
            for x in c.any:
                self._build(x, 0)
        elif isinstance(c, NotCondition):
            self._build(c.not_, 0)

    def holds(self, view: HubView) -> bool:
        return self._eval(self.cond, view)

    def _eval(self, c: Condition, view: HubView) -> bool:
        if isinstance(c, ChannelCondition):
            return self.leaves[id(c)].holds
        if isinstance(c, AlarmCondition):
            alarm = next((a for a in view.alarms if a.name == c.alarm), None)
            return alarm is not None and _state_matches(alarm.state, c.state)
        if isinstance(c, NodeCondition):
            node = view.node(c.node)
            return (node is not None and node.alive) == c.alive
        if isinstance(c, OutputCondition):
            node_name, output = c.output.split("/")
            node = view.node(node_name)
            health = node.health if node is not None else None
            state = next((o for o in health.outputs if o.name == output), None) if health else None
            if state is None or math.isnan(state.readback):
                return False
            if c.above is not None:
                return state.readback > c.above
            if c.below is not None:
                return state.readback < c.below
            return bool(state.readback == c.equals)
        if isinstance(c, AllCondition):
            return all(self._eval(x, view) for x in c.all)
        if isinstance(c, AnyCondition):
            return any(self._eval(x, view) for x in c.any)
        if isinstance(c, NotCondition):
            return not self._eval(c.not_, view)
        raise TypeError(f"not a condition: {c!r}")


class RulePhase(StrEnum):
    """Where a rule is: waiting for `when` (idle), `when` holds but not yet for `for_s`, the
    precondition or the cooldown (pending), fired until `when` clears (active), or off."""

    IDLE = "idle"
    PENDING = "pending"
    ACTIVE = "active"
    DISABLED = "disabled"


@dataclass(slots=True)
class RuleState:
    name: str
    cfg: RuleConfig
    when: Tree
    precondition: Tree | None
    channel_timed: bool
    """`for_s` counted in acquisition time by the single channel condition itself."""
    state: RulePhase = RulePhase.IDLE
    since_ns: int = 0
    when_since_ns: int | None = None
    fired: int = 0
    last_fired_ns: int = 0
    last_result: str = ""
    results: list[str] = field(default_factory=list)


@dataclass(slots=True)
class InterlockState:
    name: str
    cfg: InterlockConfig
    when: Tree
    active: bool = False
    since_ns: int = 0
    trips: int = 0


class Interlocks:
    """The hub's cross-node interlocks (`hub.interlocks`) and whether each holds now: the rules
    engine evaluates them and the command service asks `blocked` before it sends. The
    composition root makes one and hands it to both."""

    def __init__(self, site: SiteConfig) -> None:
        self.states = [
            InterlockState(name, lock, Tree(lock.when))
            for name, lock in site.hub.interlocks.items()
        ]

    def blocked(self, node: str, output: str) -> str | None:
        """The hub interlock holding `node/output`, if one is active."""
        ref = f"{node}/{output}"
        for lock in self.states:
            if lock.active and ref in lock.cfg.outputs:
                return lock.name
        return None


class RuleEngine:
    name = "rules"

    def __init__(
        self,
        router: Router,
        site: SiteConfig,
        bus: EventBus,
        model: ReadModel,
        feed: BatchFeed,
        commands: CommandService,
        snapshot: Callable[[], HubView],
        record: Callable[[str, str], str] | None = None,
        interlocks: Interlocks | None = None,
        also_from: Sequence[BatchFeed] = (),
    ) -> None:
        """`record(action, who)` starts, stops or splits the recording (returns a result).
        `interlocks`: the states the command service checks (`Interlocks.blocked`).
        `also_from`: feeds of batches the recorder never takes (a partition's watched streams:
        `fleetdaq.hub.partitions.live`), evaluated on the same thread."""
        self.router = router
        self.site = site
        self.keys = SiteKeys(site.site)
        self.bus = bus
        self.model = model
        self.commands = commands
        self.snapshot = snapshot
        self.record = record
        self.rules = [
            RuleState(
                name,
                r,
                Tree(r.when, round(r.for_s * 1e9)),
                Tree(r.precondition) if r.precondition is not None else None,
                isinstance(r.when, ChannelCondition),
                state=RulePhase.IDLE if r.enabled else RulePhase.DISABLED,
            )
            for name, r in site.rules.items()
        ]
        self._interlocks = interlocks or Interlocks(site)
        self.interlocks = self._interlocks.states
        self.by_stream: dict[tuple[str, str], list[tuple[int, ChannelLeaf]]] = {}
        for tree in self._trees():
            for leaf in tree.leaves.values():
                names = [c.name for c in site.nodes[leaf.node].streams[leaf.stream].channels]
                col = names.index(leaf.channel)
                self.by_stream.setdefault((leaf.node, leaf.stream), []).append((col, leaf))
        self.lock = threading.Lock()
        self._consumer = feed.subscribe(self.name, self._on_batch, max_bytes=64 << 20)
        for other in also_from:
            other.attach(self._consumer)
        self._pool = ThreadPoolExecutor(
            max_workers=4, thread_name_prefix="rule-actions", initializer=name_os_thread
        )
        self._stop = threading.Event()
        self._thread = NamedThread(target=self._run, name="rules", daemon=True)
        self.queryable = OperatorQueryable(
            router, self.keys.hub("rules"), self._answer, site.security, "rules", workers=0
        )
        self._died: str | None = None

    def _trees(self) -> list[Tree]:
        out: list[Tree] = []
        for r in self.rules:
            out.append(r.when)
            if r.precondition is not None:
                out.append(r.precondition)
        out += [i.when for i in self.interlocks]
        return out

    # --- lifecycle ------------------------------------------------------------------------------

    def start(self) -> None:
        self._publish()
        self._consumer.start()
        self._thread.start()
        self.queryable.start()

    def stop(self) -> None:
        self.queryable.stop()
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(5.0)
        self._consumer.stop()
        self._pool.shutdown(wait=True, cancel_futures=False)

    def failure(self) -> str | None:
        if self._died:
            return self._died
        if self._thread.ident is not None and not self._stop.is_set() and not self._consumer.alive:
            return "the rules' batch thread died"
        return None

    # --- evaluation -----------------------------------------------------------------------------

    def _on_batch(self, b: FedBatch) -> None:
        if b.late:
            return
        leaves = self.by_stream.get((b.node, b.stream))
        if not leaves:
            return
        h = b.header
        columns = batch_values(h, b.payload)
        changed = False
        for col, leaf in leaves:
            x = np.ascontiguousarray(columns[:, col])
            for flip in leaf.cond.evaluate(x, h.first_sample_time_ns, h.sample_period_ns):
                leaf.value, leaf.since_ns = flip.value, flip.time_ns
                changed = True
            leaf.value = float(x[-1])
        if changed:
            self._evaluate(time.time_ns())

    def _run(self) -> None:
        try:
            while not self._stop.wait(TICK_S):
                self._evaluate(time.time_ns())
                self._publish()
        except Exception as err:
            self._died = f"the rules' thread died: {err!r}"
            log.critical("%s", self._died, exc_info=True)
            self.bus.emit(logging.CRITICAL, "rules", "rules_died", self._died)

    def _evaluate(self, now: int) -> None:
        view = self.snapshot()
        with self.lock:
            for lock in self.interlocks:
                holds = lock.when.holds(view)
                if holds != lock.active:
                    lock.active, lock.since_ns = holds, now
                    self._interlock_changed(lock)
            for r in self.rules:
                self._step(r, view, now)

    def _step(self, r: RuleState, view: HubView, now: int) -> None:
        if r.state is RulePhase.DISABLED:
            return
        when = r.when.holds(view)
        if not when:
            r.when_since_ns = None
            if r.state is RulePhase.ACTIVE:
                r.state, r.since_ns = RulePhase.IDLE, now
                self._fire(r, r.cfg.on_clear, "cleared")
            elif r.state is RulePhase.PENDING:
                r.state, r.since_ns = RulePhase.IDLE, now
            return
        if r.state is RulePhase.ACTIVE:
            return
        if r.when_since_ns is None:
            r.when_since_ns = now
        held = r.channel_timed or now - r.when_since_ns >= round(r.cfg.for_s * 1e9)
        pre = r.precondition is None or r.precondition.holds(view)
        cooled = now - r.last_fired_ns >= round(r.cfg.cooldown_s * 1e9) or not r.fired
        if held and pre and cooled:
            r.state, r.since_ns = RulePhase.ACTIVE, now
            r.fired += 1
            r.last_fired_ns = now
            self._fire(r, r.cfg.do, "fired")
        elif r.state is RulePhase.IDLE:
            r.state, r.since_ns = RulePhase.PENDING, now

    def _fire(self, r: RuleState, actions: list[Action], why: str) -> None:
        self.bus.emit(
            logging.INFO,
            "rules",
            f"rule_{why}",
            f"rule {r.name} {why} (firing {r.fired}): {len(actions)} action(s)",
            rule=r.name,
            firing=r.fired,
        )
        if actions:
            self._pool.submit(self._run_actions, r, actions, why)

    def _run_actions(self, r: RuleState, actions: list[Action], why: str) -> None:
        results: list[str] = []
        for action in actions:
            try:
                results.append(self._act(action, f"rule:{r.name}", f"rule {r.name} {why}"))
            except Exception as err:  # an action's failure is its result, never a crash
                log.exception("rule %s: action %r failed", r.name, action)
                results.append(f"failed: {err!r}")
        with self.lock:
            r.last_result = "; ".join(results)
            r.results = (r.results + results)[-20:]

    def _act(self, action: Action, who: str, reason: str) -> str:
        if isinstance(action, SetAction | PulseAction):
            target = action.set if isinstance(action, SetAction) else action.pulse
            node, output = target.split("/")
            pulse = action.for_s if isinstance(action, PulseAction) else 0.0
            kind = ControlAction.SET if isinstance(action, SetAction) else ControlAction.PULSE
            _, reply = self.commands.send(
                node, output, kind, action.value, pulse, "rule", who, reason
            )
            return f"{target} {kind} {action.value:g}: " + (
                "applied" if reply.applied else f"refused ({reply.refusal}: {reply.message})"
            )
        if isinstance(action, RecordAction):
            if self.record is None:
                return f"record {action.record}: not available"
            return self.record(action.record, who)
        if isinstance(action, EventAction):
            self.bus.emit(_LEVELS[action.level], "rules", "rule_event", action.event, by=who)
            return "event raised"
        raise TypeError(f"not an action: {action!r}")

    def _interlock_changed(self, lock: InterlockState) -> None:
        if lock.active:
            lock.trips += 1
        self.bus.emit(
            logging.WARNING if lock.active else logging.INFO,
            "rules",
            "interlock_tripped" if lock.active else "interlock_cleared",
            f"interlock {lock.name} {'active' if lock.active else 'cleared'}: "
            f"{', '.join(lock.cfg.outputs)}"
            + (" forced safe" if lock.active and lock.cfg.force_safe else ""),
            interlock=lock.name,
        )
        if lock.active and lock.cfg.force_safe:
            self._pool.submit(self._force_safe, lock)

    def _force_safe(self, lock: InterlockState) -> None:
        for ref in lock.cfg.outputs:
            node, output = ref.split("/")
            cfg = getattr(self.site.nodes[node], "outputs", {}).get(output)
            if cfg is None:
                continue
            # Sent past the interlock itself (it is the interlock that sends it).
            self.commands.send_unblocked(
                node, output, ControlAction.SET, float(cfg.safe), 0.0, "rule",
                f"interlock:{lock.name}", f"interlock {lock.name} tripped",
            )  # fmt: skip

    def blocked(self, node: str, output: str) -> str | None:
        """The hub interlock holding `node/output`, if one is active."""
        return self._interlocks.blocked(node, output)

    # --- what others see ----------------------------------------------------------------------

    def states(self) -> RulesDict:
        with self.lock:
            rules: list[RuleDict] = [
                {
                    "name": r.name,
                    "state": r.state,
                    "since_ns": r.since_ns,
                    "fired": r.fired,
                    "last_fired_ns": r.last_fired_ns,
                    "last_result": r.last_result,
                    "description": r.cfg.description,
                    "when": r.cfg.when.model_dump(mode="json", by_alias=True),
                    "values": {
                        f"{leaf.node}/{leaf.stream}/{leaf.channel}": leaf.value
                        for leaf in r.when.leaves.values()
                    },
                }
                for r in self.rules
            ]
            interlocks: list[InterlockDict] = [
                {
                    "name": i.name,
                    "active": i.active,
                    "since_ns": i.since_ns,
                    "trips": i.trips,
                    "outputs": list(i.cfg.outputs),
                    "force_safe": i.cfg.force_safe,
                }
                for i in self.interlocks
            ]
        return {"rules": rules, "interlocks": interlocks}

    def _publish(self) -> None:
        self.model.put(RULES, self.states())

    def _answer(self, raw: bytes, caller: Caller | None) -> RulesDict:
        """``hub/rules``: every rule's and interlock's state (read only: any operator)."""
        return self.states()
