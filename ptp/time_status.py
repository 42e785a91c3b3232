"""The time-sync status of one host: state, checks, and the numbers behind them.

`TimeStatus` is what `fleetdaq ptp status` prints, what node health carries (``to_dict``),
and what the hub's fleet view reads back (``from_dict``). `quality` is the small part every
batch carries on the wire.
"""

from __future__ import annotations

import datetime as dt
from collections.abc import Mapping
from dataclasses import dataclass, field
from enum import Enum, IntEnum
from typing import Final, TypeVar

from fleetdaq.ptp.quality import ClockQuality, ClockState


class Level(IntEnum):
    """A check's verdict; the worst one is ``fleetdaq ptp status``'s exit code."""

    OK = 0
    WARN = 1
    FAIL = 2


class SyncState(Enum):
    """How far a timestamp from this clock can be trusted.

    LOCKED: disciplined right now (port SLAVE with fresh syncs, or this clock is the
    grandmaster). HOLDOVER: was locked, lost it less than `holdover` ago: still close, drifting.
    FREERUN: not disciplined (never locked, or lost it longer ago than `holdover`).
    """

    LOCKED = "locked"
    HOLDOVER = "holdover"
    FREERUN = "freerun"

    @property
    def wire(self) -> ClockState:
        """The state on the wire: FREERUN travels as UNSYNCED."""
        return {
            SyncState.LOCKED: ClockState.LOCKED,
            SyncState.HOLDOVER: ClockState.HOLDOVER,
            SyncState.FREERUN: ClockState.UNSYNCED,
        }[self]


@dataclass(frozen=True, slots=True)
class Check:
    name: str
    """Stable identifier (``port_state``, ``offset``, ...): ``--ignore`` takes these."""
    level: Level
    message: str


@dataclass(frozen=True, slots=True)
class TimeStatus:
    source: str
    """"ptp4l", "chrony" or "none"."""
    state: SyncState
    checks: tuple[Check, ...]
    time_ns: int
    """CLOCK_REALTIME when this was read."""
    offset_ns: int | None = None
    """This clock minus the grandmaster's (ptp4l's offsetFromMaster; chrony's system time)."""
    mean_path_delay_ns: int | None = None
    grandmaster_id: str = ""
    """The grandmaster's clockIdentity (chrony: the reference name); "" when there is none."""
    grandmaster_class: int | None = None
    steps_removed: int | None = None
    clock_identity: str = ""
    is_grandmaster: bool = False
    port_state: str | None = None
    last_sync_age_ns: int | None = None
    timestamping: str | None = None
    """What ptp4l uses: "SOFTWARE", "HARDWARE", ..."""
    interface: str | None = None
    interface_hardware: bool | None = None
    """Whether the interface offers hardware timestamping (None: could not tell)."""
    kernel_synchronised: bool | None = None
    kernel_maxerror_us: int | None = None
    ignored: frozenset[str] = field(default_factory=frozenset)
    """Checks left out of `level` (``--ignore``)."""

    @property
    def level(self) -> Level:
        levels = [c.level for c in self.checks if c.name not in self.ignored]
        return max(levels, default=Level.OK)

    @property
    def quality(self) -> ClockQuality:
        """What a batch stamped now carries."""
        locked_or_holdover = self.state is not SyncState.FREERUN
        return ClockQuality(
            state=self.state.wire,
            offset_ns=self.offset_ns if self.offset_ns is not None and locked_or_holdover else 0,
            grandmaster_id=self.grandmaster_id if locked_or_holdover else "",
            source=self.source,
        )

    def to_dict(self) -> dict[str, object]:
        """JSON-ready (node health, ``--json``)."""
        return {
            "source": self.source,
            "state": self.state.value,
            "level": self.level.name.lower(),
            "time_ns": self.time_ns,
            "offset_ns": self.offset_ns,
            "mean_path_delay_ns": self.mean_path_delay_ns,
            "grandmaster_id": self.grandmaster_id,
            "grandmaster_class": self.grandmaster_class,
            "steps_removed": self.steps_removed,
            "clock_identity": self.clock_identity,
            "is_grandmaster": self.is_grandmaster,
            "port_state": self.port_state,
            "last_sync_age_ns": self.last_sync_age_ns,
            "timestamping": self.timestamping,
            "interface": self.interface,
            "interface_hardware": self.interface_hardware,
            "kernel_synchronised": self.kernel_synchronised,
            "kernel_maxerror_us": self.kernel_maxerror_us,
            "checks": [
                {"name": c.name, "level": c.level.name.lower(), "message": c.message}
                for c in self.checks
            ],
            "ignored": sorted(self.ignored),
        }

    @classmethod
    def from_dict(cls, d: Mapping[str, object]) -> TimeStatus:
        """The inverse of `to_dict` (the hub reads node health with it). Raises ValueError /
        KeyError / TypeError on something that is not a status."""

        def opt_int(key: str) -> int | None:
            v = d.get(key)
            if v is None:
                return None
            if isinstance(v, bool) or not isinstance(v, int):
                raise TypeError(f"{key} is not an integer")
            return v

        def opt_bool(key: str) -> bool | None:
            v = d.get(key)
            return None if v is None else bool(v)

        def opt_str(key: str) -> str | None:
            v = d.get(key)
            return v if v is None or isinstance(v, str) else str(v)

        checks = tuple(
            Check(str(c["name"]), Level[str(c["level"]).upper()], str(c["message"]))
            for c in _items(d.get("checks", []), dict)
        )
        return cls(
            source=str(d["source"]),
            state=SyncState(d["state"]),
            checks=checks,
            time_ns=_int(d["time_ns"]),
            offset_ns=opt_int("offset_ns"),
            mean_path_delay_ns=opt_int("mean_path_delay_ns"),
            grandmaster_id=str(d.get("grandmaster_id") or ""),
            grandmaster_class=opt_int("grandmaster_class"),
            steps_removed=opt_int("steps_removed"),
            clock_identity=str(d.get("clock_identity") or ""),
            is_grandmaster=bool(d.get("is_grandmaster", False)),
            port_state=opt_str("port_state"),
            last_sync_age_ns=opt_int("last_sync_age_ns"),
            timestamping=opt_str("timestamping"),
            interface=opt_str("interface"),
            interface_hardware=opt_bool("interface_hardware"),
            kernel_synchronised=opt_bool("kernel_synchronised"),
            kernel_maxerror_us=opt_int("kernel_maxerror_us"),
            ignored=frozenset(str(x) for x in _items(d.get("ignored", []), object)),
        )

    def format_table(self) -> str:
        """For people: the numbers, then one line per check."""
        when = dt.datetime.fromtimestamp(self.time_ns / 1e9, tz=dt.UTC)
        rows: list[tuple[str, str]] = [
            ("source", self.source),
            ("state", self.state.value.upper()),
            ("level", self.level.name),
        ]
        if self.port_state is not None:
            rows.append(("port state", self.port_state))
        if self.grandmaster_id or self.source != "none":
            gm = self.grandmaster_id or "-"
            if self.is_grandmaster:
                gm += " (this clock)"
            if self.grandmaster_class is not None:
                gm += f", class {self.grandmaster_class}"
            if self.steps_removed is not None and not self.is_grandmaster:
                gm += f", {self.steps_removed} step(s) away"
            rows.append(("grandmaster", gm))
        rows.append(("offset", format_ns(self.offset_ns)))
        if self.mean_path_delay_ns is not None:
            rows.append(("mean path delay", format_ns(self.mean_path_delay_ns)))
        if not self.is_grandmaster:
            rows.append(("last sync", _age(self.last_sync_age_ns)))
        if self.timestamping is not None or self.interface is not None:
            hw = {None: "", True: ", interface offers hardware", False: ", software only"}
            rows.append(
                (
                    "timestamping",
                    f"{self.timestamping or '?'} on {self.interface or '?'}"
                    f"{hw[self.interface_hardware]}",
                )
            )
        if self.kernel_synchronised is not None:
            rows.append(
                (
                    "kernel clock",
                    ("synchronised" if self.kernel_synchronised else "not synchronised")
                    + f", maxerror {self.kernel_maxerror_us} µs",
                )
            )
        rows.append(("read at", when.isoformat(timespec="milliseconds")))
        width = max(len(k) for k, _ in rows)
        out = [f"{k:<{width}}  {v}" for k, v in rows]
        out.append("")
        for c in self.checks:
            note = " (ignored)" if c.name in self.ignored else ""
            out.append(f"[{c.level.name:<4}] {c.name:<12} {c.message}{note}")
        return "\n".join(out)


def format_ns(ns: int | None) -> str:
    if ns is None:
        return "-"
    a = abs(ns)
    if a < 10_000:
        return f"{ns} ns"
    if a < 10_000_000:
        return f"{ns / 1000:.1f} µs"
    if a < 1_000_000_000:
        return f"{ns / 1e6:.1f} ms"
    return f"{ns / 1e9:.2f} s"


def _age(ns: int | None) -> str:
    return "unknown" if ns is None else f"{format_ns(ns)} ago"


# --- The clock events the edge raises and the hub's fleet view reads --------------------------

STATE_TAGS: Final = {s: f"clock_{s.value}" for s in SyncState}
"""Event tag for entering each state: "clock_locked", "clock_holdover", "clock_freerun"."""
GRANDMASTER_CHANGED: Final = "grandmaster_changed"


def state_of_tag(tag: str) -> SyncState | None:
    for state, t in STATE_TAGS.items():
        if t == tag:
            return state
    return None


def grandmaster_change_message(old: str, new: str, status: TimeStatus) -> str:
    return (
        f"grandmaster changed from {old or '-'} to {new or '-'} "
        f"(state {status.state.value}, offset {format_ns(status.offset_ns)})"
    )


_T = TypeVar("_T")


def _int(v: object) -> int:
    if isinstance(v, int | float | str):
        return int(v)
    raise TypeError(f"{v!r} is not an integer")


def _items(v: object, kind: type[_T]) -> list[_T]:
    if not isinstance(v, list | tuple) or not all(isinstance(x, kind) for x in v):
        raise TypeError(f"{v!r} is not a list of {kind.__name__}")
    return list(v)
