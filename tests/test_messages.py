"""Events, node health and the hub heartbeat: our CDR against rosbags (an independent codec) and
mcap-ros2-support, and every malformed payload refused with a WireError (nothing else)."""

from __future__ import annotations

import dataclasses
import math
import random
from typing import Any

import pytest
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from fleetdaq.contract.cdr import decode, encode
from fleetdaq.contract.errors import WireError
from fleetdaq.contract.messages import (
    EVENT_TYPE,
    HUB_HEARTBEAT_TYPE,
    NODE_HEALTH_TYPE,
    SCHEMAS,
    DiskUsage,
    Event,
    HostMetrics,
    HubHeartbeat,
    KeyValue,
    NodeHealth,
    StreamHealth,
    TimeSyncStatus,
    make_event,
)
from fleetdaq.ptp.time_status import Check, Level, SyncState, TimeStatus


def _store(name: str):  # type: ignore[no-untyped-def]
    store = get_typestore(Stores.EMPTY)
    store.register(get_types_from_msg(SCHEMAS[name], name))
    return store


def _health() -> NodeHealth:
    status = TimeStatus(
        source="ptp4l",
        state=SyncState.LOCKED,
        checks=(Check("offset", Level.OK, "offset 120 ns"),),
        time_ns=1_795_000_000_000_000_000,
        offset_ns=-120,
        grandmaster_id="001122.fffe.334455",
        port_state="SLAVE",
        interface_hardware=None,
        kernel_synchronised=False,
        ignored=frozenset({"kernel_sync"}),
    )
    return NodeHealth(
        time_ns=1_795_000_000_123_456_789,
        node="wec",
        version="0.1.0",
        uptime_s=12.5,
        host=HostMetrics(
            cpu_percent=12.5,
            load_1m=0.5,
            load_5m=0.25,
            load_15m=0.125,
            memory_total_bytes=8 << 30,
            memory_available_bytes=5 << 30,
            disks=(DiskUsage("spool", "/var/lib/fleetdaq/spool", 1 << 34, 1 << 36),),
            cpu_temperature_c=math.nan,
            process_rss_bytes=123 << 20,
            host_uptime_s=86400.0,
        ),
        streams=(
            StreamHealth(
                "t8",
                100,
                100_000,
                3,
                0,
                100,
                2,
                100_000.004,
                2 << 20,
                97,
                98,
                0,
                0.3,
                0,
                (KeyValue("ljm_scan_backlog", "12"),),
            ),
        ),
        clock=TimeSyncStatus.of(status),
        certificate_not_after_ns=1_850_000_000 * 10**9,
    )


def test_node_health_round_trips_and_rosbags_reads_the_same_bytes():
    h = _health()
    payload = encode(h)
    back = decode(payload, NodeHealth)
    assert back.node == "wec"
    assert back.streams == h.streams
    assert math.isnan(back.host.cpu_temperature_c)
    assert back.time_status() == h.time_status()
    store = _store(NODE_HEALTH_TYPE)
    msg = store.deserialize_cdr(payload, NODE_HEALTH_TYPE)
    assert msg.streams[0].device[0].key == "ljm_scan_backlog"
    assert msg.clock.grandmaster_id == "001122.fffe.334455"
    assert store.serialize_cdr(msg, NODE_HEALTH_TYPE).tobytes() == payload


def test_the_clock_status_survives_the_wire_exactly():
    status = _health().time_status()
    assert status is not None
    assert status.offset_ns == -120
    assert status.interface_hardware is None
    assert status.kernel_synchronised is False
    assert status.ignored == frozenset({"kernel_sync"})
    assert TimeSyncStatus.unknown().status() is None


def test_events_carry_structured_fields_and_match_rosbags():
    e = make_event(
        1_795_000_000_000_000_001, "am-cell", 30, "clock", "grandmaster_changed", "— °C",
        old="aa", new="bb",
    )  # fmt: skip
    payload = encode(e)
    assert decode(payload, Event) == e
    assert e.get("new") == "bb"
    assert e.get("missing") is None
    store = _store(EVENT_TYPE)
    msg = store.deserialize_cdr(payload, EVENT_TYPE)
    assert [(kv.key, kv.value) for kv in msg.fields] == [("old", "aa"), ("new", "bb")]
    assert store.serialize_cdr(msg, EVENT_TYPE).tobytes() == payload


def test_the_heartbeat_matches_rosbags():
    hb = HubHeartbeat(1_795_000_000_000_000_000, "0.1.0", "2026-11-23T01-00-00Z", 7)
    payload = encode(hb)
    assert decode(payload, HubHeartbeat) == hb
    store = _store(HUB_HEARTBEAT_TYPE)
    assert (
        store.serialize_cdr(
            store.deserialize_cdr(payload, HUB_HEARTBEAT_TYPE), HUB_HEARTBEAT_TYPE
        ).tobytes()
        == payload
    )


@pytest.mark.parametrize("cls", [NodeHealth, Event])
def test_every_truncation_is_refused_but_an_older_form(cls: type):
    """A payload cut anywhere is refused, except exactly where an older fleetdaq's message
    ended (before the fields appended since, which then take their defaults): a hub reads the
    health and events of an edge not yet upgraded, and recordings made before."""
    msg: Any = _health() if cls is NodeHealth else make_event(1, "n", 20, "s", "t", "m", a=1)
    older: list[Any] = (
        [
            dataclasses.replace(msg, outputs=(), certificate_not_after_ns=0),  # before control
            dataclasses.replace(msg, certificate_not_after_ns=0),  # before certificate dates
        ]
        if cls is NodeHealth
        else [dataclasses.replace(msg, fields=())]
    )
    payload = encode(msg)
    read = []
    for cut in range(len(payload)):
        try:
            read.append(decode(payload[:cut], cls))
        except WireError:
            continue
    assert [encode(m) for m in read] == [encode(m) for m in older]  # (NaN is not NaN)
    assert encode(decode(payload, cls)) == payload
    with pytest.raises(WireError, match=r"trailing bytes .* newer fleetdaq"):
        decode(payload + b"\x00" * 4, cls)  # a newer form: refused, and said what it may be


def test_bit_flips_are_refused_or_decode_into_a_valid_message_never_anything_else():
    payload = bytearray(encode(_health()))
    rng = random.Random(7)
    refused = 0
    for _ in range(3000):
        mutated = bytearray(payload)
        for _ in range(rng.randint(1, 4)):
            i = rng.randrange(len(mutated))
            mutated[i] ^= 1 << rng.randrange(8)
        try:
            h = decode(bytes(mutated), NodeHealth)
        except WireError:
            refused += 1
            continue
        assert isinstance(h, NodeHealth)
    assert refused > 0


def test_lying_lengths_are_refused_before_anything_is_allocated():
    e = encode(make_event(1, "n", 20, "s", "t", "m"))
    # The node string's length field sits right after time_ns (offset 4 + 8).
    lying = e[:12] + (0x7FFFFFFF).to_bytes(4, "little") + e[16:]
    with pytest.raises(WireError, match=r"limit|truncated"):
        decode(lying, Event)


def test_an_event_level_that_is_not_a_logging_level_is_refused():
    bad = bytearray(encode(make_event(1, "n", 20, "s", "t", "m")))
    # level (uint8) follows the node string: 4 + 8 + 4 + len("n\0") = 18
    assert bad[18] == 20
    bad[18] = 77
    with pytest.raises(WireError, match="level"):
        decode(bytes(bad), Event)
