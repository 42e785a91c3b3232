"""SampleBatch32 (a stream's ``sample_format: float32``) against two independent decoders
(rosbags, mcap-ros2-support), and what it refuses: every truncation, a SampleBatch taken for a
SampleBatch32 and back, and (judged by rosbags plus the message's rules) bytes flipped anywhere."""

from __future__ import annotations

import io
import math
from typing import Any

import numpy as np
import pytest
from mcap.writer import Writer
from mcap_ros2.reader import read_ros2_messages
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from fleetdaq.contract.errors import WireError
from fleetdaq.contract.wire import (
    BATCH_TYPES,
    SAMPLE_BATCH32_SCHEMA,
    SAMPLE_BATCH32_TYPE,
    BatchDecoder,
    BatchEncoder,
    SampleStatus,
    batch_values,
    decode_batch,
    read_header,
    sample_format_of,
)
from fleetdaq.ptp.quality import ClockQuality, ClockState

NAMES = ("heave", "surge", "pitch")
UNITS = ("m", "m", "deg")
T0 = 1_795_000_000_123_456_789


def _typestore():  # type: ignore[no-untyped-def]
    store = get_typestore(Stores.EMPTY)
    store.register(get_types_from_msg(SAMPLE_BATCH32_SCHEMA, SAMPLE_BATCH32_TYPE))
    return store


def _batch(
    scans: int = 7, with_status: bool = True, gm: str = "", fmt: Any = "float32"
) -> tuple[bytes, np.ndarray]:
    rng = np.random.default_rng(1)
    data = rng.normal(scale=100.0, size=(scans, len(NAMES)))  # not float32 values
    status = None
    if with_status:
        status = np.zeros(data.shape, dtype=np.uint8)
        status[scans - 1, 1] = SampleStatus.OPEN_CIRCUIT
        data[scans - 1, 1] = np.nan
    enc = BatchEncoder("am-cell", "tc", NAMES, UNITS, fmt)
    clock = ClockQuality(ClockState.LOCKED, -1234, gm, "ptp4l")
    payload = enc.encode(41, T0, 250_000_000.5, data, clock, status)
    return bytes(payload), data


@pytest.mark.parametrize("gm", ["", "a", "abc", "001122.fffe.334455"])
@pytest.mark.parametrize("with_status", [True, False])
@pytest.mark.parametrize("scans", [1, 2, 7])
def test_rosbags_decodes_our_float32_bytes_to_the_rounded_values(
    scans: int, with_status: bool, gm: str
):
    payload, data = _batch(scans, with_status, gm)
    msg = _typestore().deserialize_cdr(payload, SAMPLE_BATCH32_TYPE)
    assert (msg.node, msg.stream) == ("am-cell", "tc")
    assert list(msg.channel_names) == list(NAMES)
    assert msg.sequence == 41
    assert msg.first_sample_time_ns == T0
    assert msg.sample_period_ns == 250_000_000.5
    assert (msg.scan_count, msg.channel_count) == (scans, 3)
    assert msg.clock.offset_ns == -1234
    assert msg.clock.grandmaster_id == gm
    assert msg.data.dtype == np.float32
    np.testing.assert_array_equal(msg.data.reshape(scans, 3), data.astype(np.float32))
    assert len(msg.sample_status) == (scans * 3 if with_status else 0)


@pytest.mark.parametrize("with_status", [True, False])
def test_our_float32_bytes_equal_rosbags_own_serialisation(with_status: bool):
    for gm in ("", "g", "gm", "gm-1"):  # every padding before the data array
        payload, _ = _batch(5, with_status, gm)
        store = _typestore()
        msg = store.deserialize_cdr(payload, SAMPLE_BATCH32_TYPE)
        assert store.serialize_cdr(msg, SAMPLE_BATCH32_TYPE).tobytes() == payload


def test_float32_is_about_half_the_bytes():
    big32, _ = _batch(1000, False)
    big64, _ = _batch(1000, False, fmt="float64")
    assert len(big32) < 0.51 * len(big64)


def test_mcap_ros2_support_decodes_our_float32_bytes_to_the_rounded_values():
    payload, data = _batch(4, True, "gm-1")
    buf = io.BytesIO()
    w = Writer(buf)
    w.start(profile="ros2")
    sid = w.register_schema(SAMPLE_BATCH32_TYPE, "ros2msg", SAMPLE_BATCH32_SCHEMA.encode())
    cid = w.register_channel("/am-cell/tc", "cdr", sid)
    w.add_message(cid, log_time=2, data=payload, publish_time=1)
    w.finish()
    buf.seek(0)
    (m,) = list(read_ros2_messages(buf))
    msg = m.ros_msg
    assert msg.sequence == 41
    assert msg.clock.grandmaster_id == "gm-1"
    got = np.array(msg.data, dtype=np.float32).reshape(4, 3)
    np.testing.assert_array_equal(got, data.astype(np.float32))
    assert list(msg.sample_status).count(SampleStatus.OPEN_CIRCUIT) == 1


def test_decode_gives_float32_views_and_batch_values_exact_float64():
    payload, data = _batch(7, True)
    batch = decode_batch(payload, "float32")
    assert batch.header.sample_format == "float32"
    assert batch.header.msgtype == SAMPLE_BATCH32_TYPE
    assert batch.data.dtype == np.float32
    np.testing.assert_array_equal(batch.data, data.astype(np.float32))
    assert np.isnan(batch.data[6, 1])
    assert batch.status is not None
    assert batch.status[6, 1] == SampleStatus.OPEN_CIRCUIT
    wide = batch_values(read_header(payload, "float32"), payload)
    assert wide.dtype == np.float64
    assert wide.shape == (7, 3)
    np.testing.assert_array_equal(wide, data.astype(np.float32).astype(np.float64))
    dec = BatchDecoder()
    for _ in range(2):  # the second one through the cached prefix
        np.testing.assert_array_equal(dec.decode(payload, "float32").data, batch.data)


def test_each_format_is_refused_as_the_other():
    for scans in (1, 2, 3, 8):
        for gm in ("", "g", "gm", "gmx"):
            p32, _ = _batch(scans, False, gm)
            p64, _ = _batch(scans, False, gm, fmt="float64")
            with pytest.raises(WireError):
                read_header(p32)  # float64 expected by default
            with pytest.raises(WireError):
                read_header(p64, "float32")
            with pytest.raises(WireError):
                BatchDecoder().decode(p32, "float64")


def test_every_truncation_of_a_float32_batch_is_refused():
    payload, _ = _batch(3, True, "gm")
    for cut in range(len(payload)):
        with pytest.raises(WireError):
            read_header(payload[:cut], "float32")
    with pytest.raises(WireError, match="trailing"):
        read_header(payload + b"\x00" * 4, "float32")


def test_message_types_and_formats_map_both_ways():
    for fmt, msgtype in BATCH_TYPES.items():
        assert sample_format_of(msgtype) == fmt
    assert sample_format_of("fleetdaq_msgs/msg/Event") is None
    with pytest.raises(ValueError, match="sample format"):
        BatchEncoder("a", "b", ("c",), ("",), "float16")  # type: ignore[arg-type]


def _contract_broken(store: Any, m: Any, raw: bytes) -> list[str]:
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
    if len(store.serialize_cdr(m, SAMPLE_BATCH32_TYPE)) != len(raw):
        broken.append("nothing after the message")
    return broken


def test_mangled_float32_payloads_are_refused_exactly_when_an_independent_decoder_says_so():
    store = _typestore()
    payload, _ = _batch(3, True, "gm")
    rng = np.random.default_rng(9)
    outcomes = {"refused": 0, "accepted": 0}
    for _ in range(2000):
        arr = bytearray(payload)
        for pos in rng.integers(0, len(arr), size=int(rng.integers(1, 4))):
            arr[pos] = int(rng.integers(256))
        bad = bytes(arr)
        try:
            theirs = store.deserialize_cdr(bad, SAMPLE_BATCH32_TYPE)
            broken = _contract_broken(store, theirs, bad)
        except Exception as err:  # rosbags raises whatever its parsing hits
            theirs, broken = None, [f"rosbags: {err!r}"]
        try:
            ours = decode_batch(bad, "float32")
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
        assert ours.header.sequence == theirs.sequence
        np.testing.assert_array_equal(ours.data.reshape(-1), theirs.data)
    assert min(outcomes.values()) > 100, outcomes
