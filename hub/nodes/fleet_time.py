"""The fleet's time: every node's clock state, offset and grandmaster, side by side.

Fed by typed node health (its `TimeSyncStatus`, ~1 Hz) and, to react faster, by the nodes'
own clock events from the event bus (the edge raises ``clock_<state>`` and
``grandmaster_changed`` the moment its monitor sees the change; their structured fields carry
the state and the grandmasters). Each update carries the edge's time of reading, so an older
health message arriving after a newer event changes nothing.

Raises hub events (source ``fleet``) on the bus when a node loses or regains lock, changes
grandmaster, and when the locked nodes stop agreeing on one grandmaster (and when they agree
again). The view goes into the read model as ``fleet``.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any

from fleetdaq.contract.messages import Event, NodeHealth
from fleetdaq.hub.bus import EventBus
from fleetdaq.hub.read_model import FLEET, FleetDict, NodeTimeDict, ReadModel
from fleetdaq.ptp.time_status import GRANDMASTER_CHANGED, SyncState, format_ns, state_of_tag

Emit = Callable[..., None]
"""emit(level, source, tag, message, **fields): `EventBus.emit`."""

SOURCE = "fleet"


@dataclass(frozen=True, slots=True)
class NodeTime:
    node: str
    state: SyncState
    level: str
    """Worst check: "ok", "warn", "fail"."""
    source: str
    offset_ns: int | None
    grandmaster_id: str
    port_state: str | None
    as_of_ns: int
    """The edge's time of the reading this comes from."""

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> NodeTime:
        return cls(
            node=str(d["node"]),
            state=SyncState(d["state"]),
            level=str(d["level"]),
            source=str(d["source"]),
            offset_ns=None if d.get("offset_ns") is None else int(d["offset_ns"]),
            grandmaster_id=str(d.get("grandmaster_id") or ""),
            port_state=d.get("port_state"),
            as_of_ns=int(d["as_of_ns"]),
        )

    def to_dict(self) -> NodeTimeDict:
        return {
            "node": self.node,
            "state": self.state.value,
            "level": self.level,
            "source": self.source,
            "offset_ns": self.offset_ns,
            "grandmaster_id": self.grandmaster_id,
            "port_state": self.port_state,
            "as_of_ns": self.as_of_ns,
        }


@dataclass(frozen=True, slots=True)
class FleetView:
    nodes: tuple[NodeTime, ...]

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> FleetView:
        """The inverse of `to_dict` (what the hub's status request carries)."""
        return cls(tuple(NodeTime.from_dict(n) for n in d.get("nodes", [])))

    @property
    def grandmasters(self) -> tuple[str, ...]:
        """Grandmasters of the nodes that are LOCKED or in HOLDOVER, sorted."""
        return tuple(
            sorted(
                {
                    n.grandmaster_id
                    for n in self.nodes
                    if n.grandmaster_id and n.state is not SyncState.FREERUN
                }
            )
        )

    @property
    def same_grandmaster(self) -> bool:
        return len(self.grandmasters) <= 1

    @property
    def max_abs_offset_ns(self) -> int | None:
        offsets = [
            abs(n.offset_ns)
            for n in self.nodes
            if n.offset_ns is not None and n.state is SyncState.LOCKED
        ]
        return max(offsets, default=None)

    @property
    def locked(self) -> int:
        return sum(n.state is SyncState.LOCKED for n in self.nodes)

    @property
    def verdict(self) -> int:
        """0 ok (every node LOCKED on one grandmaster, checks ok), 1 warning, 2 failure."""
        if not self.nodes:
            return 2
        if not self.same_grandmaster or any(n.state is SyncState.FREERUN for n in self.nodes):
            return 2
        if any(n.level == "fail" for n in self.nodes):
            return 2
        if any(n.state is SyncState.HOLDOVER or n.level == "warn" for n in self.nodes):
            return 1
        return 0

    def to_dict(self) -> FleetDict:
        return {
            "nodes": [n.to_dict() for n in self.nodes],
            "grandmasters": list(self.grandmasters),
            "same_grandmaster": self.same_grandmaster,
            "max_abs_offset_ns": self.max_abs_offset_ns,
            "locked": self.locked,
            "verdict": self.verdict,
        }

    def format_table(self) -> str:
        rows = [("node", "state", "level", "offset", "grandmaster", "port")]
        for n in self.nodes:
            rows.append(
                (
                    n.node,
                    n.state.value.upper(),
                    n.level.upper(),
                    format_ns(n.offset_ns),
                    n.grandmaster_id or "-",
                    n.port_state or "-",
                )
            )
        widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]
        lines = ["  ".join(c.ljust(w) for c, w in zip(r, widths, strict=True)) for r in rows]
        gms = ", ".join(self.grandmasters) or "none"
        lines.append("")
        lines.append(
            f"{self.locked}/{len(self.nodes)} locked; grandmaster(s): {gms}"
            f"{'' if self.same_grandmaster else '  <- NOT THE SAME'}; "
            f"max |offset| {format_ns(self.max_abs_offset_ns)}"
        )
        return "\n".join(lines)


_LEVEL = {
    SyncState.LOCKED: logging.INFO,
    SyncState.HOLDOVER: logging.WARNING,
    SyncState.FREERUN: logging.ERROR,
}


class FleetTime:
    """The fleet view, updated from any thread; raises hub events on changes."""

    def __init__(
        self,
        emit: Emit,
        split_grace_s: float = 2.0,
        monotonic: Callable[[], float] = time.monotonic,
        on_change: Callable[[FleetView], None] | None = None,
    ) -> None:
        self._emit = emit
        self._on_change = on_change
        self._nodes: dict[str, NodeTime] = {}
        self._lock = threading.Lock()
        self._split = False
        self._split_since: float | None = None
        self._split_grace = split_grace_s
        self._now = monotonic

    def view(self) -> FleetView:
        with self._lock:
            return FleetView(tuple(self._nodes[k] for k in sorted(self._nodes)))

    def update(self, node: str, health: NodeHealth) -> None:
        """A NodeWatch health listener."""
        status = health.time_status()
        if status is None or status.source == "none":
            return  # no time-sync source, or a node still starting (no reading yet)
        self._apply(
            NodeTime(
                node=node,
                state=status.state,
                level=status.level.name.lower(),
                source=status.source,
                offset_ns=status.offset_ns,
                grandmaster_id=status.grandmaster_id,
                port_state=status.port_state,
                as_of_ns=status.time_ns,
            ),
            note="",
        )

    def on_event(self, e: Event) -> None:
        """An EventLog listener: the nodes' clock events, ahead of their next health."""
        if e.node == "hub" or e.source != "clock":
            return
        with self._lock:
            known = self._nodes.get(e.node)
        if known is None:
            return  # its first health message (within ~1 s) says more than an event can
        state = state_of_tag(e.tag)
        if state is not None:
            base = known
            if e.time_ns <= base.as_of_ns:
                return
            self._apply(
                replace(
                    base,
                    state=state,
                    as_of_ns=e.time_ns,
                    grandmaster_id=base.grandmaster_id if state is not SyncState.FREERUN else "",
                ),
                note=e.message,
            )
        elif e.tag == GRANDMASTER_CHANGED:
            new = e.get("new")
            if new is not None and e.time_ns > known.as_of_ns:
                self._apply(replace(known, grandmaster_id=new, as_of_ns=e.time_ns), "")

    def on_alive(self, node: str, alive: bool) -> None:
        """A NodeWatch alive listener: a node that left is no longer part of the view."""
        if not alive:
            with self._lock:
                gone = self._nodes.pop(node, None)
            if gone is not None and self._on_change is not None:
                self._on_change(self.view())

    def _apply(self, new: NodeTime, note: str) -> None:
        events: list[tuple[int, str, str]] = []
        with self._lock:
            old = self._nodes.get(new.node)
            if old is not None and new.as_of_ns < old.as_of_ns:
                return
            self._nodes[new.node] = new
            view = FleetView(tuple(self._nodes[k] for k in sorted(self._nodes)))
            n = new.node
            if old is None or old.state is not new.state:
                what = {
                    SyncState.LOCKED: f"locked to {new.grandmaster_id or 'its grandmaster'}",
                    SyncState.HOLDOVER: "lost lock (holdover)",
                    SyncState.FREERUN: "not synchronised (free-running)",
                }[new.state]
                # A node first seen LOCKED is news only at INFO; losing lock always is.
                events.append(
                    (
                        _LEVEL[new.state],
                        "node_clock_state" if old is None else f"node_{new.state.value}",
                        f"{n}: {what}; {view.locked}/{len(view.nodes)} nodes locked"
                        + (f" ({note})" if note and new.state is not SyncState.LOCKED else ""),
                    )
                )
            if (
                old is not None
                and old.grandmaster_id
                and new.grandmaster_id
                and old.grandmaster_id != new.grandmaster_id
            ):
                events.append(
                    (
                        logging.WARNING,
                        "node_grandmaster_changed",
                        f"{n}: grandmaster changed from {old.grandmaster_id} "
                        f"to {new.grandmaster_id}",
                    )
                )
            # Nodes switch grandmaster a few polls apart: only a split that lasts is news.
            split = not view.same_grandmaster
            if split and self._split_since is None:
                self._split_since = self._now()
            elif not split:
                self._split_since = None
            lasting = split and self._now() - (self._split_since or 0.0) >= self._split_grace
            if lasting != self._split and (lasting or not split):
                self._split = lasting
                if lasting:
                    per = ", ".join(
                        f"{x.node}: {x.grandmaster_id}" for x in view.nodes if x.grandmaster_id
                    )
                    events.append((logging.ERROR, "grandmasters_differ", f"nodes disagree: {per}"))
                else:
                    gm = ", ".join(view.grandmasters) or "none"
                    events.append(
                        (logging.INFO, "grandmasters_agree", f"nodes agree on grandmaster {gm}")
                    )
        if self._on_change is not None:
            self._on_change(view)
        for level, tag, message in events:
            self._emit(level, SOURCE, tag, message)


class FleetTimeService:
    """The fleet's time view as a hub service: fed by the node watch (`fleet.update` and
    `fleet.on_alive`, its listeners) and the event bus, published in the read model as
    ``fleet``."""

    name = "fleet-time"

    def __init__(self, bus: EventBus, model: ReadModel) -> None:
        self.fleet = FleetTime(bus.emit, on_change=lambda v: model.put(FLEET, v.to_dict()))
        self._sub = bus.subscribe(self.name, self.fleet.on_event)

    def start(self) -> None:
        pass

    def stop(self) -> None:
        self._sub.stop()

    def failure(self) -> str | None:
        return None
