"""The SampleBatch codec: the high-rate message from edge to hub (keys: `fleetdaq.contract.keys`;
every other message: `fleetdaq.contract.messages`).

Payloads are ROS 2 messages serialised as plain CDR (little-endian, XCDR1 alignment, the
4-byte encapsulation header ``00 01 00 00``), so the hub writes the received bytes into MCAP
untouched and rosbags / mcap-ros2-support / Foxglove decode them with the embedded schema.

The codec is hand-written on purpose: generic CDR serialisers (rosbags, mcap-ros2-support) walk
arrays element by element or build Python lists; here the scan array goes from numpy into the
buffer with one copy, and decoding returns numpy views over the payload (no per-sample Python).
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass, field
from typing import Final, Literal, get_args

import numpy as np
import numpy.typing as npt

from fleetdaq.contract.cdr import (
    ENCAPSULATION,
    Reader,
    align,
    load_definition,
    put_string,
    schema_text,
)
from fleetdaq.contract.errors import WireError
from fleetdaq.ptp.quality import ClockQuality, ClockState

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


_MARK = struct.Struct("<QQ")


def encode_mark(sequence: int, epoch: int) -> bytes:
    """An ack or a data put's `floor`, with the spool's epoch: two little-endian uint64.

    The epoch is a random number a spool draws when its numbering starts (a new or wiped
    spool starts again at sequence 0): the hub sees a new epoch and counts the stream afresh
    instead of taking its batches for replays of what it already has, and an edge ignores
    an ack for another epoch's sequences."""
    return _MARK.pack(sequence, epoch)


def decode_mark(raw: bytes | None) -> tuple[int, int | None] | None:
    """(sequence, epoch) of `encode_mark`, or (sequence, None) from a peer that sends the
    sequence alone (`encode_u64`, before epochs); None when it is neither."""
    if raw is None:
        return None
    if len(raw) == 16:
        seq, epoch = _MARK.unpack(raw)
        return int(seq), int(epoch)
    if len(raw) == 8:
        return int(_U64.unpack(raw)[0]), None
    return None


_EVENT_MARK = struct.Struct("<QQQ")


def encode_event_mark(sequence: int, floor: int, epoch: int) -> bytes:
    """The attachment of an event an edge spooled: its sequence in the node's event spool, the
    spool's floor (lowest sequence it still holds) and epoch; three little-endian uint64.

    Events carry no sequence of their own (the `Event` message is the same from the hub's
    services), so it travels beside the payload, as a batch's floor does."""
    return _EVENT_MARK.pack(sequence, floor, epoch)


def decode_event_mark(raw: bytes) -> tuple[int, int, int] | None:
    """(sequence, floor, epoch) of `encode_event_mark`, None when `raw` is not one."""
    if len(raw) != _EVENT_MARK.size:
        return None
    seq, floor, epoch = _EVENT_MARK.unpack(raw)
    return int(seq), int(floor), int(epoch)


# --- The message (its definition ships in edge/fleetdaq_msgs/msg/SampleBatch.msg) ---------------

CLOCK_QUALITY_TYPE: Final = "fleetdaq_msgs/msg/ClockQuality"
SAMPLE_BATCH_TYPE: Final = "fleetdaq_msgs/msg/SampleBatch"
SAMPLE_BATCH32_TYPE: Final = "fleetdaq_msgs/msg/SampleBatch32"
"""SampleBatch with ``float32[] data`` (a stream's ``sample_format: float32``); every other
field, and their layout on the wire, is SampleBatch's."""
load_definition(CLOCK_QUALITY_TYPE)
load_definition(SAMPLE_BATCH_TYPE)
load_definition(SAMPLE_BATCH32_TYPE)
SAMPLE_BATCH_SCHEMA: Final = schema_text(SAMPLE_BATCH_TYPE)
"""SampleBatch with its dependency, in the ros2msg concatenated form MCAP readers expect."""
SAMPLE_BATCH32_SCHEMA: Final = schema_text(SAMPLE_BATCH32_TYPE)

SampleFormat = Literal["float64", "float32"]
"""How a stream's samples travel and are recorded: ``float64[]`` (SampleBatch) or
``float32[]`` (SampleBatch32). The payload does not say which: the stream's config does on the
hub, the MCAP channel's schema does in a recording."""
SAMPLE_FORMATS: Final[tuple[SampleFormat, ...]] = get_args(SampleFormat)
BATCH_TYPES: Final[dict[SampleFormat, str]] = {
    "float64": SAMPLE_BATCH_TYPE,
    "float32": SAMPLE_BATCH32_TYPE,
}
"""Sample format -> the message type its batches are recorded as."""
BATCH_SCHEMAS: Final[dict[str, str]] = {
    SAMPLE_BATCH_TYPE: SAMPLE_BATCH_SCHEMA,
    SAMPLE_BATCH32_TYPE: SAMPLE_BATCH32_SCHEMA,
}
"""Every sample-batch message type with its ros2msg schema."""
_DTYPES: Final[dict[SampleFormat, str]] = {"float64": "<f8", "float32": "<f4"}


def sample_format_of(msgtype: str) -> SampleFormat | None:
    """The sample format of a recorded message type; None when it is not a sample batch."""
    for fmt, name in BATCH_TYPES.items():
        if name == msgtype:
            return fmt
    return None


EARLIEST_PLAUSIBLE_NS: Final = 946_684_800_000_000_000
"""2000-01-01T00:00:00Z: an acquisition time before it comes from a clock that was never set."""
MAX_AHEAD_NS: Final = 24 * 3600 * 1_000_000_000
"""How far ahead of the hub's clock an acquisition time may be and still be believed."""


def plausible_time(t_ns: int, now_ns: int) -> bool:
    """Whether a time in a payload can be a real acquisition time (between 2000 and a day
    ahead of the receiver's clock). MCAP's times are unsigned: a negative one cannot be written."""
    return EARLIEST_PLAUSIBLE_NS <= t_ns <= now_ns + MAX_AHEAD_NS


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
    sample_format: SampleFormat = "float64"
    """How `data` was encoded (checked against the message type by whoever decoded it)."""

    @property
    def samples(self) -> int:
        return self.scan_count * self.channel_count

    @property
    def msgtype(self) -> str:
        """The message type this batch is (``fleetdaq_msgs/msg/SampleBatch`` or ``...32``)."""
        return BATCH_TYPES[self.sample_format]


@dataclass(frozen=True, slots=True)
class SampleBatch:
    header: BatchHeader
    data: npt.NDArray[np.float64] | npt.NDArray[np.float32]
    """(scan_count, channel_count), float64 or float32 as `header.sample_format` says."""
    status: npt.NDArray[np.uint8] | None = field(default=None)
    """(scan_count, channel_count) uint8 codes, or None when every sample is valid."""


def _put_string_seq(out: bytearray, items: tuple[str, ...]) -> None:
    pad = align(len(out) - 4, 4) - (len(out) - 4)
    out += b"\x00" * pad
    out += struct.pack("<I", len(items))
    for s in items:
        put_string(out, s)


class BatchEncoder:
    """Encodes the batches of one stream. The constant part (names, channels, units) is
    serialised once; each batch then costs a few struct packs and one copy of the data.

    With `sample_format` ``"float32"`` the batches are SampleBatch32: that one copy also
    rounds each value to the nearest float32 (NaN stays NaN)."""

    def __init__(
        self,
        node: str,
        stream: str,
        channel_names: tuple[str, ...],
        channel_units: tuple[str, ...],
        sample_format: SampleFormat = "float64",
    ) -> None:
        if len(channel_names) != len(channel_units) or not channel_names:
            raise ValueError("need one unit per channel and at least one channel")
        prefix = bytearray(ENCAPSULATION)
        put_string(prefix, node)
        put_string(prefix, stream)
        _put_string_seq(prefix, channel_names)
        _put_string_seq(prefix, channel_units)
        # sequence (uint64) comes next: align to 8 relative to the end of the encapsulation.
        prefix += b"\x00" * (align(len(prefix) - 4, 8) - (len(prefix) - 4))
        self._prefix = bytes(prefix)
        self.channel_count = len(channel_names)
        if sample_format not in _DTYPES:
            raise ValueError(f"unknown sample format {sample_format!r}")
        self.sample_format: SampleFormat = sample_format
        self.msgtype = BATCH_TYPES[sample_format]
        self._dtype = _DTYPES[sample_format]
        self._item = np.dtype(self._dtype).itemsize

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
        off = align(off, 8) + 8  # clock.offset_ns
        off = align(off, 4) + 4 + len(gm)
        off = align(off, 4) + 4 + len(src)
        status_at = align(off, 4)
        off = status_at + 4 + n_status
        data_len_at = align(off, 4)
        data_at = align(data_len_at + 4, self._item)
        buf = bytearray(4 + data_at + self._item * n)
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
        p = 4 + align(base + 33, 8)
        struct.pack_into("<qI", buf, p, clock.offset_ns, len(gm))
        p += 12
        buf[p : p + len(gm)] = gm
        p = 4 + align(p - 4 + len(gm), 4)
        struct.pack_into("<I", buf, p, len(src))
        buf[p + 4 : p + 4 + len(src)] = src
        struct.pack_into("<I", buf, 4 + status_at, n_status)
        if status is not None:
            buf[4 + status_at + 4 : 4 + status_at + 4 + n] = np.ascontiguousarray(
                status, dtype=np.uint8
            ).tobytes()
        struct.pack_into("<I", buf, 4 + data_len_at, n)
        np.frombuffer(buf, dtype=self._dtype, count=n, offset=4 + data_at)[:] = data.reshape(-1)
        return buf


def _read_header(r: Reader, sample_format: SampleFormat) -> BatchHeader:
    return _read_rest(r, sample_format, r.string(), r.string(), r.strings(), r.strings())


def _read_rest(
    r: Reader,
    sample_format: SampleFormat,
    node: str,
    stream: str,
    names: tuple[str, ...],
    units: tuple[str, ...],
) -> BatchHeader:
    """The header after its strings (node, stream, channel names and units)."""
    seq, t0, period, scans, channels = r.unpack("<QqdII", 32, 8)
    (state,) = r.unpack("<B", 1, 1)
    (offset,) = r.unpack("<q", 8, 8)
    gm = r.string()
    source = r.string()
    if len(names) != channels or len(units) != channels:
        raise WireError(f"{channels} channels but {len(names)} names and {len(units)} units")
    if scans == 0 or channels == 0:
        raise WireError(f"an empty batch ({scans} scans x {channels} channels)")
    if not (math.isfinite(period) and period > 0):
        raise WireError(f"sample_period_ns is {period!r}, not a positive number")
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
        sample_format=sample_format,
    )


def _check_format(sample_format: str) -> SampleFormat:
    if sample_format not in _DTYPES:
        raise ValueError(f"unknown sample format {sample_format!r}")
    return sample_format


def read_header(
    payload: bytes | bytearray | memoryview, sample_format: SampleFormat = "float64"
) -> BatchHeader:
    """Decode and check everything but the arrays, and check the arrays' lengths.

    `sample_format` says which message the payload must be: SampleBatch (``float64``) or
    SampleBatch32 (``float32``); the bytes alone cannot say (the hub knows it from the
    stream's config, a reader from the MCAP channel's schema).

    Raises WireError for anything that is not a well-formed batch of that type.
    """
    r = Reader(payload)
    header = _read_header(r, _check_format(sample_format))
    _array_views(r, header)
    return header


def _array_views(r: Reader, h: BatchHeader) -> tuple[memoryview, memoryview]:
    n = h.samples
    n_status = r.u32()
    if n_status not in (0, n):
        raise WireError(f"sample_status has {n_status} entries, expected 0 or {n}")
    status = r.take(n_status)
    n_data = r.u32()
    if n_data != n:
        raise WireError(f"data has {n_data} values, expected {n}")
    item = 8 if h.sample_format == "float64" else 4
    r.align(item)
    data = r.take(item * n)
    if r.pos != len(r.buf):
        raise WireError(f"{len(r.buf) - r.pos} trailing bytes")
    return status, data


def _batch(h: BatchHeader, status_mv: memoryview, data_mv: memoryview) -> SampleBatch:
    shape = (h.scan_count, h.channel_count)
    data = np.frombuffer(data_mv, dtype=_DTYPES[h.sample_format]).reshape(shape)
    status = np.frombuffer(status_mv, dtype=np.uint8).reshape(shape) if len(status_mv) else None
    return SampleBatch(h, data, status)


def decode_batch(
    payload: bytes | bytearray | memoryview, sample_format: SampleFormat = "float64"
) -> SampleBatch:
    """Decode a SampleBatch (or, with ``"float32"``, a SampleBatch32); arrays are read-only
    numpy views over `payload` (no copy), in the wire's dtype."""
    r = Reader(payload)
    h = _read_header(r, _check_format(sample_format))
    return _batch(h, *_array_views(r, h))


def batch_values(
    header: BatchHeader, payload: bytes | bytearray | memoryview
) -> npt.NDArray[np.float64]:
    """The (scans, channels) values of a batch already checked by `read_header` (the hub's
    accepted batches): the payload's tail, a read-only view for float64 and an exact float64
    copy for float32, so every consumer computes in float64 whatever the stream sends."""
    n = header.samples
    dtype = _DTYPES[header.sample_format]
    size = np.dtype(dtype).itemsize
    data = np.frombuffer(payload, dtype=dtype, count=n, offset=len(payload) - size * n)
    out = data.reshape(header.scan_count, header.channel_count)
    return out if header.sample_format == "float64" else out.astype(np.float64)


class BatchDecoder:
    """Decodes the batches of one stream as `decode_batch` does, but parses the part that
    never changes within a stream (node, stream, channel names and units) only when its bytes
    change: the mirror of `BatchEncoder`, for readers of long recordings. Every other field
    and every length is checked on every batch."""

    def __init__(self) -> None:
        self._prefix = b""
        self._strings: tuple[str, str, tuple[str, ...], tuple[str, ...]] = ("", "", (), ())

    def decode(
        self, payload: bytes | bytearray | memoryview, sample_format: SampleFormat = "float64"
    ) -> SampleBatch:
        """Like `decode_batch` (raises WireError for anything that is not a batch of
        `sample_format`)."""
        r = Reader(payload)
        h = self._header(r, sample_format)
        return _batch(h, *_array_views(r, h))

    def read_header(
        self, payload: bytes | bytearray | memoryview, sample_format: SampleFormat = "float64"
    ) -> BatchHeader:
        """Like `read_header` (every field and length checked), with the strings cached."""
        r = Reader(payload)
        h = self._header(r, sample_format)
        _array_views(r, h)
        return h

    def _header(self, r: Reader, sample_format: SampleFormat) -> BatchHeader:
        payload = r.buf
        n = len(self._prefix)
        if n and len(payload) > n and payload[:n] == self._prefix:
            r.pos = n
        else:
            self._strings = (r.string(), r.string(), r.strings(), r.strings())
            self._prefix = bytes(payload[: r.pos])
        return _read_rest(r, _check_format(sample_format), *self._strings)
