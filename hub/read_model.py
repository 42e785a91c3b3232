"""The hub's read model: immutable snapshots of nodes, streams, the recorder and the fleet's
time, which the services publish and everyone else reads (the demo's table, the status
request, and later the dashboard and /metrics) without touching a lock or an internal.

Each service replaces its own part whole (one reference swap); `snapshot()` hands out the current
parts together."""

from __future__ import annotations

import dataclasses
import enum
import math
import threading
import typing
from dataclasses import dataclass, field
from typing import Any

from fleetdaq.contract.messages import Event, NodeHealth


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
    notifier: dict[str, Any] = field(default_factory=dict)
    """The notifier's counters (queued, sent, oldest_queued_age_s, ...)."""
    certificates: dict[str, Any] = field(default_factory=dict)
    """With security.tls: this hub's certificate and the site CA's, each ``{path, cn,
    not_after_ns}`` (`fleetdaq.hub.supervision.certificates`)."""
    rules: dict[str, Any] = field(default_factory=dict)
    """Every rule's and hub interlock's state (`fleetdaq.hub.control.rules.RuleEngine.states`)."""
    snapshots: dict[str, Any] = field(default_factory=dict)
    """The snapshot buffer (`fleetdaq.hub.recording.snapshots.SnapshotBuffer.counters`); empty when
    switched off."""
    commands: dict[str, int] = field(default_factory=dict)
    """Commands sent, applied, refused, timed out."""
    fleet: dict[str, Any] = field(default_factory=dict)
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
    bus: tuple[dict[str, Any], ...] = ()
    failures: tuple[tuple[str, str], ...] = ()
    partitions: dict[str, Any] = field(default_factory=dict)
    """The main hub's view of each partition hub (`fleetdaq.hub.partitions.watch.PartitionWatch`):
    alive, when its last report came, its recorder."""
    partition_hubs: tuple[NodeView, ...] = ()
    """Each partition hub as the fleet sees a machine (``hub/<name>``): alive (its liveliness
    token) and its own health (CPU, memory, disks, temperature), from `PartitionWatch`."""

    def node(self, name: str) -> NodeView | None:
        return next((n for n in self.nodes if n.node == name), None)

    def stream(self, node: str, stream: str) -> StreamView | None:
        return next((s for s in self.streams if (s.node, s.stream) == (node, stream)), None)


class ReadModel:
    def __init__(self, site: str) -> None:
        self.site = site
        self._parts: dict[str, Any] = {}
        self._lock = threading.Lock()

    def put(self, part: str, value: Any) -> None:
        """Replace one part (``nodes``, ``streams``, ``recorder``, ``fleet``, ...) whole."""
        with self._lock:
            self._parts[part] = value

    def snapshot(self, time_ns: int = 0) -> HubView:
        with self._lock:
            parts = dict(self._parts)
        remote = parts.pop("partition_streams", ())
        if remote:  # the partitions' streams, as their hubs report them, after this hub's own
            parts["streams"] = (*parts.get("streams", ()), *remote)
        return HubView(site=self.site, time_ns=time_ns, **parts)


def to_jsonable(value: Any) -> Any:
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


MAX_JSON_TEXT = 4096
MAX_JSON_ITEMS = 100_000
_INT_LIMIT = 1 << 63


def from_jsonable(cls: type[Any], obj: Any) -> Any:
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


def _checked(value: Any, hint: Any, where: str) -> Any:
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
        if type(value) in (int, float) and abs(value) < _INT_LIMIT:
            return float(value)
    if hint is str and isinstance(value, str) and len(value) <= MAX_JSON_TEXT:
        return value
    listed = typing.get_origin(hint) is tuple and typing.get_args(hint) == (str, ...)
    if listed and isinstance(value, list) and len(value) <= MAX_JSON_ITEMS:
        return tuple(_checked(v, str, f"{where}[]") for v in value)
    wanted = {
        bool: "true or false",
        int: "an integer within 64 bits",
        float: "a number within 64 bits",
        str: f"text of at most {MAX_JSON_TEXT} characters",
    }.get(hint, f"a list of at most {MAX_JSON_ITEMS} texts")
    raise ValueError(f"{where}: {type(value).__name__} is not {wanted}")
