"""The wire contract between edge and hub: Zenoh key space and the SampleBatch CDR codec.

Payloads are ROS 2 messages serialised as plain CDR (little-endian, XCDR1 alignment, the
4-byte encapsulation header ``00 01 00 00``), so the hub writes the received bytes into MCAP
untouched and rosbags / mcap-ros2-support / Foxglove decode them with the embedded schema.

The codec is hand-written on purpose: generic CDR serialisers (rosbags, mcap-ros2-support) walk
arrays element by element or build Python lists; here the scan array goes from numpy into the
buffer with one copy, and decoding returns numpy views over the payload (no per-sample Python).
"""

from __future__ import annotations

import struct
from dataclasses import dataclass, field
from typing import Final

import numpy as np
import numpy.typing as npt

from edge.errors import WireError
from ptp.quality import ClockQuality, ClockState

# --- Key space -------------------------------------------------------------------------------

ROOT: Final = "fleetdaq"


def data_key(site: str, node: str, stream: str) -> str:
    return f"{ROOT}/{site}/{node}/data/{stream}"


def data_selector(site: str) -> str:
    return f"{ROOT}/{site}/*/data/*"


def alive_key(site: str, node: str) -> str:
    return f"{ROOT}/{site}/{node}/alive"


def alive_selector(site: str) -> str:
    return f"{ROOT}/{site}/*/alive"


def health_key(site: str, node: str) -> str:
    return f"{ROOT}/{site}/{node}/health"


def events_key(site: str, node: str) -> str:
    return f"{ROOT}/{site}/{node}/events"


def events_selector(site: str) -> str:
    return f"{ROOT}/{site}/*/events"


def ack_key(site: str, node: str, stream: str) -> str:
    return f"{ROOT}/{site}/{node}/ack/{stream}"


def ack_selector(site: str, node: str) -> str:
    return f"{ROOT}/{site}/{node}/ack/*"


_U64 = struct.Struct("<Q")


def encode_u64(value: int) -> bytes:
    """Acks (highest contiguous sequence durably recorded) and the `floor` attachment of a
    data put (lowest sequence the edge still holds; below it everything was acked or dropped
    and reported) are one little-endian uint64."""
    return _U64.pack(value)


def decode_u64(raw: bytes | None) -> int | None:
    if raw is None or len(raw) != 8:
        return None
    return int(_U64.unpack(raw)[0])


def hub_key(site: str, what: str) -> str:
    return f"{ROOT}/{site}/hub/{what}"


def split_data_key(key: str) -> tuple[str, str, str]:
    """``fleetdaq/<site>/<node>/data/<stream>`` -> (site, node, stream)."""
    parts = key.split("/")
    if len(parts) != 5 or parts[0] != ROOT or parts[3] != "data":
        raise WireError(f"not a data key: {key!r}")
    return parts[1], parts[2], parts[4]


# --- Message definitions (ros2msg, embedded in every MCAP file) -----------------------------

CLOCK_QUALITY_TYPE: Final = "fleetdaq_msgs/msg/ClockQuality"
CLOCK_QUALITY_MSG: Final = """\
# Quality of the host clock that stamped a batch, at acquisition.
uint8 STATE_UNSYNCED=0
uint8 STATE_LOCKED=1
uint8 STATE_HOLDOVER=2
uint8 state
int64 offset_ns          # host clock offset from the grandmaster (ns), 0 when unknown
string grandmaster_id    # PTP clockIdentity of the grandmaster, "" when none
string source            # "ptp4l", "chrony" or "none"
"""

SAMPLE_BATCH_TYPE: Final = "fleetdaq_msgs/msg/SampleBatch"
SAMPLE_BATCH_MSG: Final = """\
# A batch of consecutive scans from one stream of one node. Every channel is sampled once per
# scan; sample i of channel c is data[i * channel_count + c].
string node
string stream
string[] channel_names
string[] channel_units
uint64 sequence              # per stream, +1 per batch, no gaps by construction
int64 first_sample_time_ns   # UTC (CLOCK_REALTIME), from the clock fit, of scan 0
float64 sample_period_ns     # as fitted; scan i is at first_sample_time_ns + i * sample_period_ns
uint32 scan_count
uint32 channel_count
fleetdaq_msgs/ClockQuality clock
uint8[] sample_status        # empty: all valid; else scan_count*channel_count codes (0 = valid)
float64[] data               # scan_count*channel_count values, scan-major; NaN where not valid
"""

SEPARATOR: Final = "=" * 80
SAMPLE_BATCH_SCHEMA: Final = (
    f"{SAMPLE_BATCH_MSG}{SEPARATOR}\nMSG: fleetdaq_msgs/ClockQuality\n{CLOCK_QUALITY_MSG}"
)
"""SampleBatch with its dependency, in the ros2msg concatenated form MCAP readers expect."""


EVENT_TYPE: Final = "fleetdaq_msgs/msg/Event"
EVENT_MSG: Final = """\
# A system message (like MODAQ 2's /system_messenger): recorded, logged, alerted on.
uint8 DEBUG=10
uint8 INFO=20
uint8 WARNING=30
uint8 ERROR=40
uint8 CRITICAL=50
int64 time_ns     # UTC ns when it happened
string node       # who raised it ("hub" for the hub)
uint8 level       # one of the constants above (Python logging levels)
string source     # the part that raised it: a stream name, "agent", "recorder", ...
string tag        # stable identifier of the kind of event, for alert snoozing
string message    # for people
"""


class SampleStatus:
    """Codes in `sample_status` (0 = valid). Invalid samples also hold NaN in `data`."""

    VALID: Final = 0
    SKIPPED_SCAN: Final = 1  # the device skipped the scan (LJM's dummy value)
    OPEN_CIRCUIT: Final = 2  # thermocouple open
    SHORT_GND: Final = 3
    SHORT_VCC: Final = 4
    COMM_ERROR: Final = 5  # NACK, CRC mismatch, bus error
    OUT_OF_RANGE: Final = 6
    DEVICE_FAULT: Final = 7


ENCAPSULATION: Final = b"\x00\x01\x00\x00"  # CDR_LE


@dataclass(frozen=True, slots=True)
class BatchHeader:
    """Everything in a batch but the arrays: what the hub needs for accounting."""

    node: str
    stream: str
    channel_names: tuple[str, ...]
    channel_units: tuple[str, ...]
    sequence: int
    first_sample_time_ns: int
    sample_period_ns: float
    scan_count: int
    channel_count: int
    clock: ClockQuality

    @property
    def samples(self) -> int:
        return self.scan_count * self.channel_count


@dataclass(frozen=True, slots=True)
class SampleBatch:
    header: BatchHeader
    data: npt.NDArray[np.float64]
    """(scan_count, channel_count) float64."""
    status: npt.NDArray[np.uint8] | None = field(default=None)
    """(scan_count, channel_count) uint8 codes, or None when every sample is valid."""


def _align(n: int, a: int) -> int:
    return (n + a - 1) & -a


def _put_string(out: bytearray, s: str) -> None:
    raw = s.encode("utf-8") + b"\x00"
    pad = _align(len(out) - 4, 4) - (len(out) - 4)
    out += b"\x00" * pad
    out += struct.pack("<I", len(raw))
    out += raw


def _put_string_seq(out: bytearray, items: tuple[str, ...]) -> None:
    pad = _align(len(out) - 4, 4) - (len(out) - 4)
    out += b"\x00" * pad
    out += struct.pack("<I", len(items))
    for s in items:
        _put_string(out, s)


class BatchEncoder:
    """Encodes the batches of one stream. The constant part (names, channels, units) is
    serialised once; each batch then costs a few struct packs and one copy of the data."""

    def __init__(
        self, node: str, stream: str, channel_names: tuple[str, ...], channel_units: tuple[str, ...]
    ) -> None:
        if len(channel_names) != len(channel_units) or not channel_names:
            raise ValueError("need one unit per channel and at least one channel")
        prefix = bytearray(ENCAPSULATION)
        _put_string(prefix, node)
        _put_string(prefix, stream)
        _put_string_seq(prefix, channel_names)
        _put_string_seq(prefix, channel_units)
        # sequence (uint64) comes next: align to 8 relative to the end of the encapsulation.
        prefix += b"\x00" * (_align(len(prefix) - 4, 8) - (len(prefix) - 4))
        self._prefix = bytes(prefix)
        self.channel_count = len(channel_names)

    def encode(
        self,
        sequence: int,
        first_sample_time_ns: int,
        sample_period_ns: float,
        data: npt.NDArray[np.float64],
        clock: ClockQuality,
        status: npt.NDArray[np.uint8] | None = None,
    ) -> bytearray:
        """Serialise one batch. `data` is (scans, channels); `status` None means all valid."""
        scans, channels = data.shape
        if channels != self.channel_count:
            raise ValueError(f"data has {channels} channels, stream has {self.channel_count}")
        gm = clock.grandmaster_id.encode() + b"\x00"
        src = clock.source.encode() + b"\x00"
        n = scans * channels
        n_status = 0 if status is None else n
        # Layout after the 8-aligned prefix (offsets relative to the encapsulation end).
        base = len(self._prefix) - 4
        off = base + 32  # uint64 seq, int64 t0, float64 period, uint32 scans, uint32 channels
        off += 1  # clock.state
        off = _align(off, 8) + 8  # clock.offset_ns
        off = _align(off, 4) + 4 + len(gm)
        off = _align(off, 4) + 4 + len(src)
        status_at = _align(off, 4)
        off = status_at + 4 + n_status
        data_len_at = _align(off, 4)
        data_at = _align(data_len_at + 4, 8)
        buf = bytearray(4 + data_at + 8 * n)
        buf[: len(self._prefix)] = self._prefix
        p = len(self._prefix)
        struct.pack_into(
            "<QqdIIB",
            buf,
            p,
            sequence,
            first_sample_time_ns,
            sample_period_ns,
            scans,
            channels,
            int(clock.state),
        )
        p = 4 + _align(base + 33, 8)
        struct.pack_into("<qI", buf, p, clock.offset_ns, len(gm))
        p += 12
        buf[p : p + len(gm)] = gm
        p = 4 + _align(p - 4 + len(gm), 4)
        struct.pack_into("<I", buf, p, len(src))
        buf[p + 4 : p + 4 + len(src)] = src
        struct.pack_into("<I", buf, 4 + status_at, n_status)
        if status is not None:
            buf[4 + status_at + 4 : 4 + status_at + 4 + n] = np.ascontiguousarray(
                status, dtype=np.uint8
            ).tobytes()
        struct.pack_into("<I", buf, 4 + data_len_at, n)
        np.frombuffer(buf, dtype="<f8", count=n, offset=4 + data_at)[:] = data.reshape(-1)
        return buf


class _Reader:
    """Bounds-checked CDR reader: every length is checked against what is left."""

    __slots__ = ("buf", "pos")

    def __init__(self, buf: bytes | bytearray | memoryview) -> None:
        if len(buf) < 4 or bytes(buf[:2]) != b"\x00\x01":
            raise WireError("not little-endian CDR (bad encapsulation header)")
        self.buf = memoryview(buf)
        self.pos = 4

    def align(self, a: int) -> None:
        self.pos = 4 + _align(self.pos - 4, a)

    def take(self, n: int) -> memoryview:
        if n < 0 or self.pos + n > len(self.buf):
            raise WireError(f"truncated: need {n} bytes at offset {self.pos}, have {len(self.buf)}")
        out = self.buf[self.pos : self.pos + n]
        self.pos += n
        return out

    def unpack(self, fmt: str, size: int, align: int) -> tuple[int | float, ...]:
        self.align(align)
        return struct.unpack_from(fmt, self.take(size))

    def u32(self) -> int:
        return int(self.unpack("<I", 4, 4)[0])

    def string(self) -> str:
        n = self.u32()
        if n == 0:
            raise WireError("string without terminator")
        raw = bytes(self.take(n))
        if raw[-1] != 0:
            raise WireError("string not NUL-terminated")
        try:
            return raw[:-1].decode("utf-8")
        except UnicodeDecodeError as err:
            raise WireError(f"string not UTF-8: {err}") from None

    def strings(self, limit: int = 4096) -> tuple[str, ...]:
        n = self.u32()
        if n > limit:
            raise WireError(f"{n} strings claimed, limit {limit}")
        return tuple(self.string() for _ in range(n))


def _read_header(r: _Reader) -> BatchHeader:
    node = r.string()
    stream = r.string()
    names = r.strings()
    units = r.strings()
    seq, t0, period, scans, channels = r.unpack("<QqdII", 32, 8)
    (state,) = r.unpack("<B", 1, 1)
    (offset,) = r.unpack("<q", 8, 8)
    gm = r.string()
    source = r.string()
    if len(names) != channels or len(units) != channels:
        raise WireError(f"{channels} channels but {len(names)} names and {len(units)} units")
    try:
        clock_state = ClockState(int(state))
    except ValueError:
        raise WireError(f"unknown clock state {state}") from None
    return BatchHeader(
        node=node,
        stream=stream,
        channel_names=names,
        channel_units=units,
        sequence=int(seq),
        first_sample_time_ns=int(t0),
        sample_period_ns=float(period),
        scan_count=int(scans),
        channel_count=int(channels),
        clock=ClockQuality(clock_state, int(offset), gm, source),
    )


def read_header(payload: bytes | bytearray | memoryview) -> BatchHeader:
    """Decode and check everything but the arrays, and check the arrays' lengths.

    Raises WireError for anything that is not a well-formed SampleBatch.
    """
    r = _Reader(payload)
    header = _read_header(r)
    _array_views(r, header)
    return header


def _array_views(r: _Reader, h: BatchHeader) -> tuple[memoryview, memoryview]:
    n = h.samples
    n_status = r.u32()
    if n_status not in (0, n):
        raise WireError(f"sample_status has {n_status} entries, expected 0 or {n}")
    status = r.take(n_status)
    n_data = r.u32()
    if n_data != n:
        raise WireError(f"data has {n_data} values, expected {n}")
    r.align(8)
    data = r.take(8 * n)
    if r.pos != len(r.buf):
        raise WireError(f"{len(r.buf) - r.pos} trailing bytes")
    return status, data


def decode_batch(payload: bytes | bytearray | memoryview) -> SampleBatch:
    """Decode a SampleBatch; arrays are read-only numpy views over `payload` (no copy)."""
    r = _Reader(payload)
    h = _read_header(r)
    status_mv, data_mv = _array_views(r, h)
    shape = (h.scan_count, h.channel_count)
    data = np.frombuffer(data_mv, dtype="<f8").reshape(shape)
    status = np.frombuffer(status_mv, dtype=np.uint8).reshape(shape) if len(status_mv) else None
    return SampleBatch(h, data, status)


# --- Events ------------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class Event:
    time_ns: int
    node: str
    level: int
    source: str
    tag: str
    message: str

    @property
    def level_name(self) -> str:
        return {10: "debug", 20: "info", 30: "warning", 40: "error", 50: "critical"}.get(
            self.level, str(self.level)
        )


def encode_event(e: Event) -> bytes:
    out = bytearray(ENCAPSULATION)
    out += struct.pack("<q", e.time_ns)
    _put_string(out, e.node)
    out += struct.pack("<B", e.level)
    _put_string(out, e.source)
    _put_string(out, e.tag)
    _put_string(out, e.message)
    return bytes(out)


def decode_event(payload: bytes | bytearray | memoryview) -> Event:
    """Raises WireError for anything that is not a well-formed Event."""
    r = _Reader(payload)
    (t,) = r.unpack("<q", 8, 8)
    node = r.string()
    (level,) = r.unpack("<B", 1, 1)
    source, tag, message = r.string(), r.string(), r.string()
    if r.pos != len(r.buf):
        raise WireError(f"{len(r.buf) - r.pos} trailing bytes")
    return Event(int(t), node, int(level), source, tag, message)
