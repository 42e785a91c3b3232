"""fleetdaq's messages other than sample batches, as typed Python objects.

Each class is the Python form of a ``.msg`` definition shipped in `edge/fleetdaq_msgs/msg`
(the field lists are checked against each other at import). `encode` turns one into CDR bytes;
`decode(payload, Class)` checks a payload completely and returns the typed object or raises
`WireError`. Nothing reads these messages by string keys: node health, for one, is decoded in one
place (here) into `NodeHealth`."""

from __future__ import annotations

from dataclasses import dataclass
from enum import StrEnum
from typing import Final

from fleetdaq.contract.cdr import decode, define, encode, load_definition, message, schema_text
from fleetdaq.ptp.time_status import Check, Level, SyncState, TimeStatus

__all__ = [
    "AlarmState",
    "CommandRecord",
    "DiskUsage",
    "Event",
    "HostMetrics",
    "HubHeartbeat",
    "KeyValue",
    "NodeHealth",
    "OutputCommand",
    "OutputReply",
    "OutputState",
    "StreamHealth",
    "TimeCheck",
    "TimeSyncStatus",
    "decode",
    "encode",
    "schema_text",
]

define(
    "diagnostic_msgs/msg/KeyValue",
    """\
# What to label this value when viewing.
string key
# A value to track over time.
string value
""",
)
for _name in (
    "Event",
    "NodeHealth",
    "HostMetrics",
    "DiskUsage",
    "StreamHealth",
    "TimeSyncStatus",
    "TimeCheck",
    "HubHeartbeat",
    "AlarmState",
    "OutputCommand",
    "OutputReply",
    "CommandRecord",
    "OutputState",
):
    load_definition(f"fleetdaq_msgs/msg/{_name}")

EVENT_TYPE: Final = "fleetdaq_msgs/msg/Event"
NODE_HEALTH_TYPE: Final = "fleetdaq_msgs/msg/NodeHealth"
HUB_HEARTBEAT_TYPE: Final = "fleetdaq_msgs/msg/HubHeartbeat"
ALARM_STATE_TYPE: Final = "fleetdaq_msgs/msg/AlarmState"
COMMAND_RECORD_TYPE: Final = "fleetdaq_msgs/msg/CommandRecord"


@message("diagnostic_msgs/msg/KeyValue")
@dataclass(frozen=True, slots=True)
class KeyValue:
    key: str
    value: str


def key_values(pairs: dict[str, object]) -> tuple[KeyValue, ...]:
    return tuple(KeyValue(str(k), str(v)) for k, v in pairs.items())


_LEVEL_NAMES = {10: "debug", 20: "info", 30: "warning", 40: "error", 50: "critical"}


@message(EVENT_TYPE)
@dataclass(frozen=True, slots=True)
class Event:
    """A system message. `fields` carries what code reacts to (never parse `message`)."""

    time_ns: int
    node: str
    level: int
    source: str
    tag: str
    message: str
    fields: tuple[KeyValue, ...] = ()

    def __post_init__(self) -> None:
        if self.level not in _LEVEL_NAMES:
            raise ValueError(f"event level {self.level} is not a logging level")

    @property
    def level_name(self) -> str:
        return _LEVEL_NAMES[self.level]

    def get(self, key: str) -> str | None:
        """The value of structured field `key`, None when absent."""
        for kv in self.fields:
            if kv.key == key:
                return kv.value
        return None


def make_event(
    time_ns: int,
    node: str,
    level: int,
    source: str,
    tag: str,
    text: str,
    /,
    **fields: object,
) -> Event:
    """An Event with its structured fields given as keywords."""
    return Event(time_ns, node, level, source, tag, text, key_values(fields))


# --- Health --------------------------------------------------------------------------------------


@message("fleetdaq_msgs/msg/DiskUsage")
@dataclass(frozen=True, slots=True)
class DiskUsage:
    role: str
    path: str
    free_bytes: int
    total_bytes: int


@message("fleetdaq_msgs/msg/HostMetrics")
@dataclass(frozen=True, slots=True)
class HostMetrics:
    cpu_percent: float
    load_1m: float
    load_5m: float
    load_15m: float
    memory_total_bytes: int
    memory_available_bytes: int
    disks: tuple[DiskUsage, ...]
    cpu_temperature_c: float
    """NaN where the OS exposes none."""
    process_rss_bytes: int
    host_uptime_s: float

    def disk(self, role: str) -> DiskUsage | None:
        return next((d for d in self.disks if d.role == role), None)


@message("fleetdaq_msgs/msg/StreamHealth")
@dataclass(frozen=True, slots=True)
class StreamHealth:
    name: str
    batches: int
    scans: int
    invalid_samples: int
    read_errors: int
    next_sequence: int
    replayed: int
    sample_period_ns: float
    spool_bytes: int
    spool_acked: int
    spool_floor: int
    spool_dropped_batches: int
    oldest_unacked_age_s: float
    acks_refused: int
    device: tuple[KeyValue, ...] = ()
    late_polls: int = 0
    """Polls of a polled device the host was too late for (busy or stopped): their slots
    passed with no scan; nothing made up, nothing marked invalid."""

    def device_value(self, key: str) -> str | None:
        return next((kv.value for kv in self.device if kv.key == key), None)


@message("fleetdaq_msgs/msg/TimeCheck")
@dataclass(frozen=True, slots=True)
class TimeCheck:
    name: str
    level: str
    message: str


_TRI = {False: 0, True: 1, None: 2}
_FROM_TRI = {0: False, 1: True}


@message("fleetdaq_msgs/msg/TimeSyncStatus")
@dataclass(frozen=True, slots=True)
class TimeSyncStatus:
    """`fleetdaq.ptp.time_status.TimeStatus` on the wire (`known` False: no source, or nothing read
    yet)."""

    known: bool
    source: str
    state: str
    level: str
    time_ns: int
    has_offset: bool
    offset_ns: int
    has_mean_path_delay: bool
    mean_path_delay_ns: int
    grandmaster_id: str
    grandmaster_class: int
    steps_removed: int
    clock_identity: str
    is_grandmaster: bool
    port_state: str
    last_sync_age_ns: int
    timestamping: str
    interface: str
    interface_hardware: int
    kernel_synchronised: int
    kernel_maxerror_us: int
    checks: tuple[TimeCheck, ...]
    ignored: tuple[str, ...]

    @classmethod
    def unknown(cls, source: str = "none") -> TimeSyncStatus:
        return cls(
            False, source, "", "", 0, False, 0, False, 0, "", -1, -1, "", False, "", -1, "",
            "", 2, 2, -1, (), ()
        )  # fmt: skip

    @classmethod
    def of(cls, s: TimeStatus) -> TimeSyncStatus:
        return cls(
            known=True,
            source=s.source,
            state=s.state.value,
            level=s.level.name.lower(),
            time_ns=s.time_ns,
            has_offset=s.offset_ns is not None,
            offset_ns=s.offset_ns or 0,
            has_mean_path_delay=s.mean_path_delay_ns is not None,
            mean_path_delay_ns=s.mean_path_delay_ns or 0,
            grandmaster_id=s.grandmaster_id,
            grandmaster_class=-1 if s.grandmaster_class is None else s.grandmaster_class,
            steps_removed=-1 if s.steps_removed is None else s.steps_removed,
            clock_identity=s.clock_identity,
            is_grandmaster=s.is_grandmaster,
            port_state=s.port_state or "",
            last_sync_age_ns=-1 if s.last_sync_age_ns is None else s.last_sync_age_ns,
            timestamping=s.timestamping or "",
            interface=s.interface or "",
            interface_hardware=_TRI[s.interface_hardware],
            kernel_synchronised=_TRI[s.kernel_synchronised],
            kernel_maxerror_us=-1 if s.kernel_maxerror_us is None else s.kernel_maxerror_us,
            checks=tuple(TimeCheck(c.name, c.level.name.lower(), c.message) for c in s.checks),
            ignored=tuple(sorted(s.ignored)),
        )

    def status(self) -> TimeStatus | None:
        """The `TimeStatus` this carries; None when not known. Raises ValueError for a state
        or level that is not one."""
        if not self.known:
            return None
        return TimeStatus(
            source=self.source,
            state=SyncState(self.state),
            checks=tuple(Check(c.name, Level[c.level.upper()], c.message) for c in self.checks),
            time_ns=self.time_ns,
            offset_ns=self.offset_ns if self.has_offset else None,
            mean_path_delay_ns=self.mean_path_delay_ns if self.has_mean_path_delay else None,
            grandmaster_id=self.grandmaster_id,
            grandmaster_class=None if self.grandmaster_class < 0 else self.grandmaster_class,
            steps_removed=None if self.steps_removed < 0 else self.steps_removed,
            clock_identity=self.clock_identity,
            is_grandmaster=self.is_grandmaster,
            port_state=self.port_state or None,
            last_sync_age_ns=None if self.last_sync_age_ns < 0 else self.last_sync_age_ns,
            timestamping=self.timestamping or None,
            interface=self.interface or None,
            interface_hardware=_FROM_TRI.get(self.interface_hardware),
            kernel_synchronised=_FROM_TRI.get(self.kernel_synchronised),
            kernel_maxerror_us=None if self.kernel_maxerror_us < 0 else self.kernel_maxerror_us,
            ignored=frozenset(self.ignored),
        )


@message("fleetdaq_msgs/msg/OutputState")
@dataclass(frozen=True, slots=True)
class OutputState:
    name: str
    kind: str
    unit: str
    value: float
    readback: float
    readback_ns: int
    readback_source: str
    armed: bool
    safe_state: bool
    interlocks: tuple[str, ...]
    commands: int
    refused: int


@message(NODE_HEALTH_TYPE)
@dataclass(frozen=True, slots=True)
class NodeHealth:
    time_ns: int
    node: str
    version: str
    uptime_s: float
    host: HostMetrics
    streams: tuple[StreamHealth, ...]
    clock: TimeSyncStatus
    outputs: tuple[OutputState, ...] = ()
    certificate_not_after_ns: int = 0
    """When the TLS certificate it connects with expires (0: no TLS, or it cannot tell)."""

    def stream(self, name: str) -> StreamHealth | None:
        return next((s for s in self.streams if s.name == name), None)

    def time_status(self) -> TimeStatus | None:
        """The node's clock status, None when it has none (or sent one that makes no sense)."""
        try:
            return self.clock.status()
        except (KeyError, ValueError):
            return None


@message(HUB_HEARTBEAT_TYPE)
@dataclass(frozen=True, slots=True)
class HubHeartbeat:
    time_ns: int
    version: str
    session: str
    sequence: int


@message(ALARM_STATE_TYPE)
@dataclass(frozen=True, slots=True)
class AlarmState:
    """One alarm after a transition (recorded on ``/alarms``)."""

    time_ns: int
    name: str
    kind: str
    node: str
    stream: str
    channel: str
    condition: str
    severity: str
    state: str
    active: bool
    transition: str
    value: float
    unit: str
    since_ns: int
    count: int
    user: str
    host: str
    note: str
    shelved_until_ns: int


class RefusalReason(StrEnum):
    """Why a command can be refused (`OutputReply.refusal`; `timeout`: the hub heard no
    reply). The wire carries the value."""

    UNKNOWN_OUTPUT = "unknown_output"
    NOT_ARMED = "not_armed"
    OUT_OF_LIMITS = "out_of_limits"
    TOO_FAST = "too_fast"
    INTERLOCK = "interlock"
    SAFE_STATE = "safe_state"
    TOO_OLD = "too_old"
    NOT_ALLOWED = "not_allowed"
    DEVICE_ERROR = "device_error"
    TIMEOUT = "timeout"


class OutputAction(StrEnum):
    """What an `OutputCommand` asks of an output. The wire carries the value."""

    SET = "set"
    PULSE = "pulse"
    ARM = "arm"
    DISARM = "disarm"
    READ = "read"


class CommandSender(StrEnum):
    """Who sent an `OutputCommand`: a person, or one of the hub's rules."""

    OPERATOR = "operator"
    RULE = "rule"


REFUSALS: Final = tuple(RefusalReason)
"""Every `RefusalReason`, in that order."""
ACTIONS: Final = tuple(OutputAction)
"""Every `OutputAction`, in that order."""


@message("fleetdaq_msgs/msg/OutputCommand")
@dataclass(frozen=True, slots=True)
class OutputCommand:
    command_id: str
    output: str
    action: str
    value: float
    pulse_s: float
    sender: str
    who: str
    reason: str
    issued_ns: int
    max_age_s: float

    def __post_init__(self) -> None:
        if self.action not in ACTIONS:
            raise ValueError(f"unknown action {self.action!r}")
        if self.sender not in tuple(CommandSender):
            raise ValueError(f"unknown sender {self.sender!r}")
        if not self.command_id or len(self.command_id) > 128:
            raise ValueError("a command id is 1 to 128 characters")


@message("fleetdaq_msgs/msg/OutputReply")
@dataclass(frozen=True, slots=True)
class OutputReply:
    command_id: str
    output: str
    action: str
    applied: bool
    refusal: str
    message: str
    requested: float
    readback: float
    readback_ns: int
    readback_source: str
    armed: bool
    safe_state: bool
    interlocks: tuple[str, ...]
    replied_ns: int
    replay: bool = False
    """A command id the edge had answered before: this is that reply, nothing was done again."""

    def __post_init__(self) -> None:
        if self.refusal and self.refusal not in REFUSALS:
            raise ValueError(f"unknown refusal {self.refusal!r}")
        if self.applied == bool(self.refusal):
            raise ValueError("a reply is applied or refused with a reason, not both")


@message(COMMAND_RECORD_TYPE)
@dataclass(frozen=True, slots=True)
class CommandRecord:
    command: OutputCommand
    reply: OutputReply
    node: str
    sent_ns: int
    answered_ns: int


SCHEMAS: Final = {
    name: schema_text(name)
    for name in (
        EVENT_TYPE,
        NODE_HEALTH_TYPE,
        HUB_HEARTBEAT_TYPE,
        ALARM_STATE_TYPE,
        COMMAND_RECORD_TYPE,
    )
}
"""The ros2msg schema (with dependencies) of every message here that the hub records."""
