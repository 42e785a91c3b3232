"""The SampleBatch codec against two independent decoders (rosbags, mcap-ros2-support), and
what it refuses: every kind of malformed payload, random bytes, and (judged by rosbags plus the
message's rules) bytes flipped anywhere; flips in fields that take any value still decode."""

from __future__ import annotations

import io
import math
import struct
from typing import Any

import numpy as np
import pytest
from mcap.writer import Writer
from mcap_ros2.reader import read_ros2_messages
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from fleetdaq.contract.cdr import MAX_ITEMS, MAX_STRING_BYTES
from fleetdaq.contract.errors import WireError
from fleetdaq.contract.wire import (
    SAMPLE_BATCH_SCHEMA,
    SAMPLE_BATCH_TYPE,
    BatchEncoder,
    SampleStatus,
    decode_batch,
    read_header,
)
from fleetdaq.ptp.quality import ClockQuality, ClockState

NAMES = ("heave", "surge", "pitch")
UNITS = ("m", "m", "deg")


def _typestore():  # type: ignore[no-untyped-def]
    store = get_typestore(Stores.EMPTY)
    store.register(get_types_from_msg(SAMPLE_BATCH_SCHEMA, SAMPLE_BATCH_TYPE))
    return store


def _batch(scans: int = 7, with_status: bool = True, gm: str = "") -> tuple[bytes, np.ndarray]:
    rng = np.random.default_rng(1)
    data = rng.normal(size=(scans, len(NAMES)))
    status = None
    if with_status:
        status = np.zeros(data.shape, dtype=np.uint8)
        status[scans - 1, 1] = SampleStatus.OPEN_CIRCUIT
        data[scans - 1, 1] = np.nan
    enc = BatchEncoder("am-cell", "tc", NAMES, UNITS)
    clock = ClockQuality(ClockState.LOCKED, -1234, gm, "ptp4l")
    payload = enc.encode(41, 1_795_000_000_123_456_789, 250_000_000.5, data, clock, status)
    return bytes(payload), data


@pytest.mark.parametrize("gm", ["", "a", "001122.fffe.334455"])
@pytest.mark.parametrize("with_status", [True, False])
@pytest.mark.parametrize("scans", [1, 2, 7])
def test_rosbags_decodes_our_bytes_to_the_same_values(scans: int, with_status: bool, gm: str):
    payload, data = _batch(scans, with_status, gm)
    msg = _typestore().deserialize_cdr(payload, SAMPLE_BATCH_TYPE)
    assert (msg.node, msg.stream) == ("am-cell", "tc")
    assert list(msg.channel_names) == list(NAMES)
    assert list(msg.channel_units) == list(UNITS)
    assert msg.sequence == 41
    assert msg.first_sample_time_ns == 1_795_000_000_123_456_789
    assert msg.sample_period_ns == 250_000_000.5
    assert (msg.scan_count, msg.channel_count) == (scans, 3)
    assert msg.clock.state == ClockState.LOCKED
    assert msg.clock.offset_ns == -1234
    assert msg.clock.grandmaster_id == gm
    assert msg.clock.source == "ptp4l"
    assert isinstance(msg.data, np.ndarray)
    np.testing.assert_array_equal(msg.data.reshape(scans, 3), data)
    assert len(msg.sample_status) == (scans * 3 if with_status else 0)


@pytest.mark.parametrize("with_status", [True, False])
def test_our_bytes_equal_rosbags_own_serialisation(with_status: bool):
    payload, _ = _batch(5, with_status, "gm")
    store = _typestore()
    msg = store.deserialize_cdr(payload, SAMPLE_BATCH_TYPE)
    assert store.serialize_cdr(msg, SAMPLE_BATCH_TYPE).tobytes() == payload


def test_mcap_ros2_support_decodes_our_bytes_to_the_same_values():
    payload, data = _batch(4, True, "gm-1")
    buf = io.BytesIO()
    w = Writer(buf)
    w.start(profile="ros2")
    sid = w.register_schema(SAMPLE_BATCH_TYPE, "ros2msg", SAMPLE_BATCH_SCHEMA.encode())
    cid = w.register_channel("/am-cell/tc", "cdr", sid)
    w.add_message(cid, log_time=2, data=payload, publish_time=1)
    w.finish()
    buf.seek(0)
    (m,) = list(read_ros2_messages(buf))
    msg = m.ros_msg
    assert msg.sequence == 41
    assert msg.clock.grandmaster_id == "gm-1"
    assert list(msg.channel_names) == list(NAMES)
    got = np.array(msg.data, dtype=float).reshape(4, 3)
    np.testing.assert_array_equal(got, data)
    assert list(msg.sample_status).count(SampleStatus.OPEN_CIRCUIT) == 1


def test_decode_returns_numpy_views_with_invalid_samples_flagged():
    payload, data = _batch(7, True)
    batch = decode_batch(payload)
    assert batch.data.shape == (7, 3)
    assert batch.data.dtype == np.float64
    np.testing.assert_array_equal(batch.data, data)
    assert batch.status is not None
    assert np.isnan(batch.data[6, 1])
    assert batch.status[6, 1] == SampleStatus.OPEN_CIRCUIT
    assert int((batch.status != 0).sum()) == 1
    assert batch.header.samples == 21


def test_every_truncation_of_a_batch_is_refused_with_wire_error():
    payload, _ = _batch(3, True, "gm")
    for cut in range(len(payload)):
        with pytest.raises(WireError):
            read_header(payload[:cut])


def test_trailing_bytes_are_refused():
    payload, _ = _batch(2, False)
    with pytest.raises(WireError, match="trailing"):
        read_header(payload + b"\x00" * 8)


# --- malformed payloads are refused; well-formed ones are not ---------------------------------


class Layout:
    """Where the fields of a `_batch(3, True, "gm")` payload are, found by their encoded values
    (not by re-running the encoder's arithmetic)."""

    def __init__(self, payload: bytes) -> None:
        self.payload = payload
        at = 4
        self.strings: dict[str, int] = {}  # string -> offset of its length field

        def find(raw: bytes) -> int:
            nonlocal at
            pos = payload.index(raw, at)
            at = pos + len(raw)
            return pos

        for s in ("am-cell", "tc", *NAMES, *UNITS):
            self.strings.setdefault(s, find(struct.pack("<I", len(s) + 1) + s.encode() + b"\0"))
        self.names_count = self.strings["heave"] - 4
        self.sequence = find(struct.pack("<Q", 41))
        self.first_time = find(struct.pack("<q", 1_795_000_000_123_456_789))
        self.period = find(struct.pack("<d", 250_000_000.5))
        self.scans = find(struct.pack("<II", 3, 3))
        self.channels = self.scans + 4
        self.state = self.channels + 4
        self.offset_ns = find(struct.pack("<q", -1234))
        for s in ("gm", "ptp4l"):
            self.strings[s] = find(struct.pack("<I", len(s) + 1) + s.encode() + b"\0")
        self.status_count = find(struct.pack("<I", 9))
        self.data = len(payload) - 8 * 9
        self.data_count = payload.rindex(struct.pack("<I", 9), 0, self.data)

    def put(self, offset: int, fmt: str, value: object) -> bytes:
        arr = bytearray(self.payload)
        struct.pack_into(fmt, arr, offset, value)
        return bytes(arr)


def _malformed() -> dict[str, bytes]:
    """One payload per way of being malformed, each not a valid SampleBatch by construction."""
    payload, _ = _batch(3, True, "gm")
    at = Layout(payload)
    node = at.strings["am-cell"]
    out = {
        "big-endian CDR": payload[:1] + b"\x00" + payload[2:],
        "an empty string (no terminator)": at.put(node, "<I", 0),
        "a string without its NUL": at.put(node + 4 + 7, "<B", ord("x")),
        "a string that is not UTF-8": at.put(at.strings["tc"] + 4, "<B", 0xFF),
        "a string longer than the payload": at.put(node, "<I", 0x7FFF_FFFF),
        "a string over the size limit": at.put(node, "<I", MAX_STRING_BYTES + 1),
        "more names than the limit": at.put(at.names_count, "<I", MAX_ITEMS + 1),
        "fewer channels than names": at.put(at.channels, "<I", 2),
        "no channels": at.put(at.channels, "<I", 0),
        "no scans": at.put(at.scans, "<I", 0),
        "more scans than data": at.put(at.scans, "<I", 4),
        "a NaN sample period": at.put(at.period, "<d", math.nan),
        "an infinite sample period": at.put(at.period, "<d", math.inf),
        "a zero sample period": at.put(at.period, "<d", 0.0),
        "a negative sample period": at.put(at.period, "<d", -1.0),
        "clock state 3": at.put(at.state, "<B", 3),
        "clock state 255": at.put(at.state, "<B", 255),
        "a status per scan, not per sample": at.put(at.status_count, "<I", 3),
        "more data than samples": at.put(at.data_count, "<I", 10),
        "less data than samples": at.put(at.data_count, "<I", 8),
        "a huge data array": at.put(at.data_count, "<I", 0xFFFF_FFF0),
    }
    for n in (1, 7, 8, 64):
        out[f"{n} trailing bytes"] = payload + b"\x00" * n
    return out


@pytest.mark.parametrize(("why", "bad"), list(_malformed().items()), ids=list(_malformed()))
def test_each_kind_of_malformed_payload_is_refused_with_wire_error(why: str, bad: bytes):
    with pytest.raises(WireError):
        read_header(bad)
    with pytest.raises(WireError):
        decode_batch(bad)


def test_random_bytes_are_refused_with_wire_error():
    rng = np.random.default_rng(7)
    for i in range(3000):
        bad = rng.bytes(int(rng.integers(0, 400)))
        if i % 2:  # past the encapsulation check, into the fields
            bad = b"\x00\x01\x00\x00" + bad
        with pytest.raises(WireError):
            read_header(bad)


def test_any_value_in_the_fields_that_take_any_value_still_decodes():
    """A decoder that refused everything would pass the tests above: flips in the data, the
    sequence, the time and the clock offset make another valid batch, read back as flipped."""
    payload, _ = _batch(3, True, "gm")
    at = Layout(payload)
    free = [
        *range(at.data, len(payload)),
        *range(at.sequence, at.sequence + 8),
        *range(at.first_time, at.first_time + 8),
        *range(at.offset_ns, at.offset_ns + 8),
    ]
    rng = np.random.default_rng(8)
    for _ in range(500):
        arr = bytearray(payload)
        for pos in rng.choice(free, size=int(rng.integers(1, 5)), replace=False):
            arr[pos] = int(rng.integers(256))
        batch = decode_batch(bytes(arr))
        h = batch.header
        assert h.sequence == struct.unpack_from("<Q", arr, at.sequence)[0]
        assert h.first_sample_time_ns == struct.unpack_from("<q", arr, at.first_time)[0]
        assert h.clock.offset_ns == struct.unpack_from("<q", arr, at.offset_ns)[0]
        assert batch.data.tobytes() == bytes(arr[at.data :])


def _contract_broken(store: Any, msg: object, raw: bytes) -> list[str]:
    """What a message rosbags could decode breaks of the SampleBatch contract."""
    m: Any = msg
    n = m.scan_count * m.channel_count
    broken = []
    if not len(m.channel_names) == len(m.channel_units) == m.channel_count:
        broken.append("one name and unit per channel")
    if m.scan_count == 0 or m.channel_count == 0:
        broken.append("not empty")
    if not (math.isfinite(m.sample_period_ns) and m.sample_period_ns > 0):
        broken.append("a positive sample period")
    if m.clock.state not in (0, 1, 2):
        broken.append("a known clock state")
    if len(m.sample_status) not in (0, n):
        broken.append("no status or one per sample")
    if len(m.data) != n:
        broken.append("one value per sample")
    if len(store.serialize_cdr(m, SAMPLE_BATCH_TYPE)) != len(raw):
        broken.append("nothing after the message")
    return broken


def test_mangled_payloads_are_refused_exactly_when_an_independent_decoder_says_so():
    """Bytes flipped anywhere, judged by rosbags' CDR decoder plus the message's rules: what
    rosbags cannot decode, or what breaks a rule, is refused; what we accept, rosbags reads the
    same. (rosbags does not check a string's NUL terminator; we do.)"""
    store = _typestore()
    payload, _ = _batch(3, True, "gm")
    rng = np.random.default_rng(9)
    outcomes = {"refused": 0, "accepted": 0}
    for _ in range(3000):
        arr = bytearray(payload)
        for pos in rng.integers(0, len(arr), size=int(rng.integers(1, 4))):
            arr[pos] = int(rng.integers(256))
        bad = bytes(arr)
        try:
            theirs = store.deserialize_cdr(bad, SAMPLE_BATCH_TYPE)
            broken = _contract_broken(store, theirs, bad)
        except Exception as err:  # rosbags raises whatever its parsing hits
            theirs, broken = None, [f"rosbags: {err!r}"]
        try:
            ours = decode_batch(bad)
        except WireError as err:
            refusal = str(err)
        else:
            refusal = ""
        if refusal:
            outcomes["refused"] += 1
            assert broken or "NUL" in refusal, f"refused a valid batch: {refusal}"
            continue
        outcomes["accepted"] += 1
        assert not broken, f"accepted a malformed batch: {broken}"
        h = ours.header
        assert (h.node, h.stream, h.sequence) == (theirs.node, theirs.stream, theirs.sequence)
        assert (h.channel_names, h.channel_units) == (
            tuple(theirs.channel_names),
            tuple(theirs.channel_units),
        )
        assert (h.first_sample_time_ns, h.scan_count) == (
            theirs.first_sample_time_ns,
            theirs.scan_count,
        )
        assert h.clock == ClockQuality(
            ClockState(theirs.clock.state),
            theirs.clock.offset_ns,
            theirs.clock.grandmaster_id,
            theirs.clock.source,
        )
        assert ours.data.tobytes() == theirs.data.tobytes()
        status = b"" if ours.status is None else ours.status.tobytes()
        assert status == bytes(theirs.sample_status)
    assert min(outcomes.values()) > 300, outcomes  # both outcomes were exercised


def test_acks_and_floors_carry_the_spool_epoch_and_old_peers_still_read():
    from fleetdaq.contract.wire import decode_mark, encode_mark, encode_u64

    assert decode_mark(encode_mark(41, 2**63 + 5)) == (41, 2**63 + 5)
    assert decode_mark(encode_u64(41)) == (41, None), "an edge or hub from before epochs"
    for bad in (None, b"", b"\x00" * 7, b"\x00" * 12, b"\x00" * 17):
        assert decode_mark(bad) is None
