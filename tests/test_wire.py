"""The SampleBatch codec against two independent decoders (rosbags, mcap-ros2-support)."""

from __future__ import annotations

import contextlib
import io

import numpy as np
import pytest
from mcap.writer import Writer
from mcap_ros2.reader import read_ros2_messages
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from edge.errors import WireError
from edge.wire import (
    SAMPLE_BATCH_SCHEMA,
    SAMPLE_BATCH_TYPE,
    BatchEncoder,
    SampleStatus,
    decode_batch,
    read_header,
)
from ptp.quality import ClockQuality, ClockState

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


def test_random_bytes_and_lying_lengths_raise_only_wire_error():
    rng = np.random.default_rng(7)
    payload, _ = _batch(3, True, "gm")
    for _ in range(3000):
        kind = rng.integers(3)
        if kind == 0:
            bad = rng.bytes(int(rng.integers(0, 400)))
        elif kind == 1:  # flip a few bytes of a real payload (lengths, counts, strings)
            arr = bytearray(payload)
            for pos in rng.integers(0, len(arr), size=int(rng.integers(1, 4))):
                arr[pos] = int(rng.integers(256))
            bad = bytes(arr)
        else:  # claim a huge array
            arr = bytearray(payload)
            arr[-3 * 8 * 3 - 4 : -3 * 8 * 3] = (0xFFFFFFF0).to_bytes(4, "little")
            bad = bytes(arr)
        with contextlib.suppress(WireError):
            read_header(bad)


def test_trailing_bytes_are_refused():
    payload, _ = _batch(2, False)
    with pytest.raises(WireError, match="trailing"):
        read_header(payload + b"\x00" * 8)
