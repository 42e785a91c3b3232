"""The hub's read model: immutable snapshots of nodes, streams, the recorder and the fleet's
time, which the services publish and everyone else reads (the demo's table, the status
request, and later the dashboard and /metrics) without touching a lock or an internal.

Each service replaces its own part whole (one reference swap) through that part's `Part` key, whose
type mypy checks against the value (``model.put(STREAMS, views)``); `snapshot()` hands out the
current parts together. The parts shaped as JSON objects (the notifier's counters, the rules'
states, the fleet's time) are `TypedDict`s: plain dicts at run time, so their JSON is what it
was."""

from __future__ import annotations

import dataclasses
import enum
import math
import threading
import typing
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, Final, Generic, TypedDict, TypeVar

from fleetdaq.contract.messages import Event, NodeHealth

T = TypeVar("T")

JsonObject = dict[str, object]
"""A JSON object as the hub hands it on (to a reply, a page, a part): its values only passed
on or narrowed where read."""


@dataclass(frozen=True, slots=True)
class StreamView:
    node: str
    stream: str
    recorded: bool
    rate_hz: float
    """Configured scans per second."""
    scan_rate: float
    """Measured over the last batches."""
    batches: int = 0
    scans: int = 0
    samples: int = 0
    gaps: int = 0
    lost: int = 0
    missing: int = 0
    duplicates: int = 0
    late: int = 0
    deferred: int = 0
    malformed: int = 0
    overflow: int = 0
    implausible_times: int = 0
    acquisition_gaps: int = 0
    first_sequence: int | None = None
    last_sequence: int | None = None
    acked: int | None = None
    last_receive_ns: int = 0
    hub: str = ""
    """The partition hub that records this stream ("": this hub), as its report says."""


@dataclass(frozen=True, slots=True)
class NodeView:
    node: str
    alive: bool
    health: NodeHealth | None = None
    health_received_ns: int = 0


@dataclass(frozen=True, slots=True)
class RecorderView:
    state: str = "starting"
    """"recording", "stopped", "disk_error" or "failed" (its writer died)."""
    session: str = ""
    session_dir: str = ""
    current_file: str = ""
    current_file_bytes: int = 0
    bytes_written: int = 0
    """Bytes of every file this hub finished or is writing, since it started (all sessions)."""
    files: tuple[str, ...] = ()
    abandoned_files: tuple[str, ...] = ()
    write_errors: int = 0
    writer_errors: int = 0
    malformed: int = 0
    overflow: int = 0
    queued_bytes: int = 0
    events_not_recorded: int = 0


@dataclass(frozen=True, slots=True)
class DiskView:
    """A recording disk's space (a partition hub's, in its report)."""

    free_bytes: int = 0
    total_bytes: int = 0


@dataclass(frozen=True, slots=True)
class AlarmView:
    """One alarm in the read model (what `fleetdaq alarms` and the dashboard show)."""

    name: str
    kind: str
    node: str
    stream: str
    channel: str
    severity: str
    state: str
    active: bool
    since_ns: int
    value: float
    unit: str
    count: int
    condition: str
    description: str
    shelved_until_ns: int


class NotifierCounters(TypedDict, total=False):
    """The read model's ``notifier`` part (`fleetdaq.hub.supervision.notify.service`); empty
    until the notifier publishes."""

    enabled: bool
    smtp: bool
    server: str
    state: str
    """"off", "idle", "sending" or "failing"."""
    groups: list[str]
    received: int
    ignored: int
    composed: int
    digests: int
    suppressed: int
    deferred: int
    held: int
    queued: int
    unwritten: int
    sent: int
    failed_attempts: int
    rejected: int
    rejected_recipients: int
    dropped: int
    errors: int
    oldest_queued_age_s: float
    next_attempt_in_s: float
    last_error: str
    last_subject: str
    outbox: str


class NodeTimeDict(TypedDict):
    """One node's time in the ``fleet`` part (`fleetdaq.hub.nodes.fleet_time.NodeTime`)."""

    node: str
    state: str
    level: str
    source: str
    offset_ns: int | None
    grandmaster_id: str
    port_state: str | None
    as_of_ns: int


class FleetDict(TypedDict, total=False):
    """The read model's ``fleet`` part (`fleetdaq.hub.nodes.fleet_time.FleetView.to_dict`);
    empty until a node's time is known."""

    nodes: list[NodeTimeDict]
    grandmasters: list[str]
    same_grandmaster: bool
    max_abs_offset_ns: int | None
    locked: int
    verdict: int


class RuleDict(TypedDict):
    """One rule in the ``rules`` part (`fleetdaq.hub.control.rules.RuleEngine.states`)."""

    name: str
    state: str
    since_ns: int
    fired: int
    last_fired_ns: int
    last_result: str
    description: str
    when: JsonObject
    values: dict[str, float]


class InterlockDict(TypedDict):
    """One hub interlock in the ``rules`` part."""

    name: str
    active: bool
    since_ns: int
    trips: int
    outputs: list[str]
    force_safe: bool


class RulesDict(TypedDict, total=False):
    """The read model's ``rules`` part; empty until the rules engine publishes."""

    rules: list[RuleDict]
    interlocks: list[InterlockDict]


@dataclass(frozen=True, slots=True)
class HubView:
    site: str
    time_ns: int
    nodes: tuple[NodeView, ...] = ()
    streams: tuple[StreamView, ...] = ()
    recorder: RecorderView = RecorderView()
    hub_health: NodeHealth | None = None
    alarms: tuple[AlarmView, ...] = ()
    alarm_totals: dict[str, int] = field(default_factory=dict)
    """Transitions since the hub started: raised, cleared, acked, shelved, disabled."""
    notifier: NotifierCounters = field(default_factory=NotifierCounters)
    """The notifier's counters (queued, sent, oldest_queued_age_s, ...)."""
    certificates: dict[str, JsonObject] = field(default_factory=dict)
    """With security.tls: this hub's certificate and the site CA's, each ``{path, cn,
    not_after_ns}`` (`fleetdaq.hub.supervision.certificates`)."""
    rules: RulesDict = field(default_factory=RulesDict)
    """Every rule's and hub interlock's state (`fleetdaq.hub.control.rules.RuleEngine.states`)."""
    snapshots: JsonObject = field(default_factory=dict)
    """The snapshot buffer (`fleetdaq.hub.recording.snapshots.SnapshotBuffer.counters`); empty when
    switched off."""
    commands: dict[str, int] = field(default_factory=dict)
    """Commands sent, applied, refused, timed out."""
    fleet: FleetDict = field(default_factory=FleetDict)
    """The fleet's time (`fleetdaq.hub.nodes.fleet_time.FleetView.to_dict`)."""
    recent_events: tuple[Event, ...] = ()
    event_counts: dict[str, int] = field(default_factory=dict)
    refused_keys: tuple[tuple[str, int], ...] = ()
    """Keys the site file does not define that traffic arrived on, with counts."""
    refused_total: int = 0
    refused_acl: tuple[tuple[str, str, int], ...] = ()
    """Messages the router's access control list dropped: (peer host, certificate, count)."""
    refused_acl_total: int = 0
    refused_tls: tuple[tuple[str, int], ...] = ()
    """TLS handshakes the router refused: (reason, count)."""
    refused_tls_total: int = 0
    malformed: tuple[tuple[str, int], ...] = ()
    """Health and event payloads refused per node (batches: per stream, in `streams`)."""
    bus: tuple[JsonObject, ...] = ()
    """Each event bus subscriber's counters (name, delivered, dropped, errors, queued)."""
    failures: tuple[tuple[str, str], ...] = ()
    partitions: dict[str, JsonObject] = field(default_factory=dict)
    """The main hub's view of each partition hub (`fleetdaq.hub.partitions.watch.PartitionWatch`):
    alive, when its last report came, its recorder."""
    partition_hubs: tuple[NodeView, ...] = ()
    """Each partition hub as the fleet sees a machine (``hub/<name>``): alive (its liveliness
    token) and its own health (CPU, memory, disks, temperature), from `PartitionWatch`."""

    def node(self, name: str) -> NodeView | None:
        return next((n for n in self.nodes if n.node == name), None)

    def stream(self, node: str, stream: str) -> StreamView | None:
        return next((s for s in self.streams if (s.node, s.stream) == (node, stream)), None)


@dataclass(frozen=True, slots=True)
class Part(Generic[T]):
    """The key of one part of the read model: its name (a `HubView` field, or
    ``partition_streams``) and, for mypy, the type of its value."""

    name: str


NODES: Final[Part[tuple[NodeView, ...]]] = Part("nodes")
STREAMS: Final[Part[tuple[StreamView, ...]]] = Part("streams")
PARTITION_STREAMS: Final[Part[tuple[StreamView, ...]]] = Part("partition_streams")
"""The partition hubs' streams, as their reports say: shown after this hub's own `STREAMS`."""
RECORDER: Final[Part[RecorderView]] = Part("recorder")
HUB_HEALTH: Final[Part[NodeHealth | None]] = Part("hub_health")
ALARMS: Final[Part[tuple[AlarmView, ...]]] = Part("alarms")
ALARM_TOTALS: Final[Part[dict[str, int]]] = Part("alarm_totals")
NOTIFIER: Final[Part[NotifierCounters]] = Part("notifier")
CERTIFICATES: Final[Part[dict[str, JsonObject]]] = Part("certificates")
RULES: Final[Part[RulesDict]] = Part("rules")
SNAPSHOTS: Final[Part[JsonObject]] = Part("snapshots")
COMMANDS: Final[Part[dict[str, int]]] = Part("commands")
FLEET: Final[Part[FleetDict]] = Part("fleet")
RECENT_EVENTS: Final[Part[tuple[Event, ...]]] = Part("recent_events")
EVENT_COUNTS: Final[Part[dict[str, int]]] = Part("event_counts")
REFUSED_KEYS: Final[Part[tuple[tuple[str, int], ...]]] = Part("refused_keys")
REFUSED_TOTAL: Final[Part[int]] = Part("refused_total")
REFUSED_ACL: Final[Part[tuple[tuple[str, str, int], ...]]] = Part("refused_acl")
REFUSED_ACL_TOTAL: Final[Part[int]] = Part("refused_acl_total")
REFUSED_TLS: Final[Part[tuple[tuple[str, int], ...]]] = Part("refused_tls")
REFUSED_TLS_TOTAL: Final[Part[int]] = Part("refused_tls_total")
MALFORMED: Final[Part[tuple[tuple[str, int], ...]]] = Part("malformed")
PARTITIONS: Final[Part[dict[str, JsonObject]]] = Part("partitions")
PARTITION_HUBS: Final[Part[tuple[NodeView, ...]]] = Part("partition_hubs")


class ReadModel:
    def __init__(self, site: str) -> None:
        self.site = site
        # Each value was checked against its Part's type where it was put.
        self._parts: dict[str, Any] = {}
        self._lock = threading.Lock()

    def put(self, part: Part[T], value: T) -> None:
        """Replace one part (`NODES`, `STREAMS`, `RECORDER`, `FLEET`, ...) whole."""
        with self._lock:
            self._parts[part.name] = value

    def snapshot(self, time_ns: int = 0) -> HubView:
        with self._lock:
            parts = dict(self._parts)
        remote = parts.pop("partition_streams", ())
        if remote:  # the partitions' streams, as their hubs report them, after this hub's own
            parts["streams"] = (*parts.get("streams", ()), *remote)
        return HubView(site=self.site, time_ns=time_ns, **parts)


def number(obj: Mapping[str, object], key: str) -> float | None:
    """``obj[key]`` when it is a number (an int or a float, not a bool), else None: a part's
    JSON-shaped value narrowed where it is read."""
    value = obj.get(key)
    if isinstance(value, int | float) and not isinstance(value, bool):
        return value
    return None


def member(obj: Mapping[str, object], key: str) -> JsonObject:
    """``obj[key]`` when it is a JSON object (a dict with text keys), else an empty one."""
    value = obj.get(key)
    if isinstance(value, dict) and all(isinstance(k, str) for k in value):
        return value
    return {}


def to_jsonable(value: object) -> object:
    """Dataclasses, enums, tuples and non-finite floats into JSON-ready values."""
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {f.name: to_jsonable(getattr(value, f.name)) for f in dataclasses.fields(value)}
    if isinstance(value, dict):
        return {str(k): to_jsonable(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [to_jsonable(v) for v in value]
    if isinstance(value, enum.Enum):
        return value.value
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, bytes):
        return value.hex()
    return value


def to_json_object(value: object) -> JsonObject:
    """`to_jsonable` of a dataclass or a dict: a JSON object (TypeError for anything else)."""
    out = to_jsonable(value)
    if not isinstance(out, dict):
        raise TypeError(f"{type(value).__name__} is not a JSON object")
    return out


MAX_JSON_TEXT = 4096
MAX_JSON_ITEMS = 100_000
_INT_LIMIT = 1 << 63


V = TypeVar("V")


def from_jsonable(cls: type[V], obj: object) -> V:
    """The view `cls` (a dataclass of str, bool, int, float, ``X | None`` and ``tuple[str,
    ...]`` fields) from a JSON object another hub sent, checked in full: only its fields, each
    of its type (ints within 64 bits, text and lists bounded; a float may be null, as
    `to_jsonable` writes NaN). ValueError says which field is wrong. The reverse of
    `to_jsonable` for these views."""
    if not isinstance(obj, dict):
        raise ValueError(f"{cls.__name__}: not a JSON object")
    hints = typing.get_type_hints(cls)
    unknown = set(obj) - set(hints)
    if unknown:
        raise ValueError(f"{cls.__name__}: unknown field(s) {sorted(map(str, unknown))[:5]}")
    values = {k: _checked(v, hints[k], f"{cls.__name__}.{k}") for k, v in obj.items()}
    try:
        return cls(**values)
    except TypeError as err:  # a field without a default missing
        raise ValueError(f"{cls.__name__}: {err}") from None


def _checked(value: object, hint: object, where: str) -> object:
    args = typing.get_args(hint)
    if type(None) in args:  # X | None
        if value is None:
            return None
        (hint,) = [a for a in args if a is not type(None)]
    if hint is bool and isinstance(value, bool):
        return value
    if hint is int and type(value) is int and -_INT_LIMIT < value < _INT_LIMIT:
        return value
    if hint is float:
        if value is None:
            return math.nan
        if isinstance(value, int | float) and type(value) is not bool and abs(value) < _INT_LIMIT:
            return float(value)
    if hint is str and isinstance(value, str) and len(value) <= MAX_JSON_TEXT:
        return value
    listed = typing.get_origin(hint) is tuple and typing.get_args(hint) == (str, ...)
    if listed and isinstance(value, list) and len(value) <= MAX_JSON_ITEMS:
        return tuple(_checked(v, str, f"{where}[]") for v in value)
    kinds: dict[object, str] = {
        bool: "true or false",
        int: "an integer within 64 bits",
        float: "a number within 64 bits",
        str: f"text of at most {MAX_JSON_TEXT} characters",
    }
    wanted = kinds.get(hint, f"a list of at most {MAX_JSON_ITEMS} texts")
    raise ValueError(f"{where}: {type(value).__name__} is not {wanted}")
