"""The recorder's payloads under load: every batch two edges publish as fast as Zenoh takes them
(a backlog builds in the recorder's queue, the snapshot buffer and the batch feed hold the same
payloads by reference) is on disk byte for byte, read back by rosbags' own MCAP reader. A
payload reused, overwritten or handed to the wrong stream before its write would show here as
a batch whose bytes differ from the ones sent under its sequence."""

from __future__ import annotations

import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import zenoh
from rosbags.rosbag2 import Reader

from fleetdaq.contract.keys import SiteKeys
from fleetdaq.contract.wire import BatchEncoder, encode_u64, read_header
from fleetdaq.hub.config.load import parse_config
from fleetdaq.hub.recording.session import topic_of
from fleetdaq.hub.runtime import HubRuntime
from fleetdaq.ptp.quality import UNSYNCED
from fleetdaq.runtime.zenoh_session import client_config
from tests.procs import free_port, wait_until

NODES = ("wec_a", "wec_b")
BATCHES = 150
SCANS = 2000
CHANNELS = 4

SITE = """\
site: payloads
hub:
  listen: [tcp/127.0.0.1:{port}]
  dashboard: {{enabled: false}}
  recorder: {{flush_interval_s: 0.2, chunk_size: 262144}}
nodes:
""" + "".join(
    f"""\
  {node}:
    streams:
      t8:
        driver: wave_sim
        rate_hz: 1000
        scans_per_batch: {SCANS}
        channels: [{{{{name: a}}}}, {{{{name: b}}}}, {{{{name: c}}}}, {{{{name: d}}}}]
"""
    for node in NODES
)


@pytest.fixture
def hub(tmp_path: Path) -> Iterator[tuple[HubRuntime, int]]:
    port = free_port()
    runtime = HubRuntime(parse_config(SITE.format(port=port), "<test>"), tmp_path / "data")
    yield runtime, port
    runtime.close()


def _payloads(node: str, seed: int) -> list[bytes]:
    """Distinct noisy batches (64 KB each): no two share their bytes."""
    enc = BatchEncoder(node, "t8", tuple("abcd"), ("V",) * CHANNELS)
    rng = np.random.default_rng(seed)
    t0 = time.time_ns()
    return [
        bytes(
            enc.encode(
                seq, t0 + seq * SCANS * 1_000_000, 1e6, rng.normal(size=(SCANS, 4)), UNSYNCED
            )
        )
        for seq in range(BATCHES)
    ]


def test_every_batch_published_under_load_is_recorded_byte_for_byte(
    hub: tuple[HubRuntime, int],
):
    runtime, port = hub
    sent = {node: _payloads(node, seed) for seed, node in enumerate(NODES)}
    runtime.start()
    keys = SiteKeys("payloads")
    session = zenoh.open(client_config([f"tcp/127.0.0.1:{port}"]))
    pubs = {
        node: session.declare_publisher(
            keys.data(node, "t8"),
            congestion_control=zenoh.CongestionControl.BLOCK,
            reliability=zenoh.Reliability.RELIABLE,
        )
        for node in NODES
    }
    try:
        for pub in pubs.values():
            wait_until(lambda p=pub: p.matching_status.matching, 10.0, "the hub's subscriber")
        for seq in range(BATCHES):  # interleaved, as fast as Zenoh takes them
            for node, pub in pubs.items():
                pub.put(sent[node][seq], attachment=encode_u64(0))
        streams = runtime.recorder.streams
        wait_until(
            lambda: all(streams[(n, "t8")].batches == BATCHES for n in NODES),
            60.0,
            f"the recorder counting {BATCHES} batches of each node",
        )
    finally:
        for pub in pubs.values():
            pub.undeclare()
        session.close()
    runtime.close()
    folder = runtime.recorder.summary()["session"]

    recorded: dict[str, dict[int, bytes]] = {node: {} for node in NODES}
    topics = {topic_of(node, "t8"): node for node in NODES}
    with Reader(Path(folder)) as reader:
        for connection, _, raw in reader.messages():
            node = topics.get(connection.topic)
            if node is None:
                continue  # events, health
            seq = read_header(raw).sequence
            assert seq not in recorded[node], f"{node} batch {seq} recorded twice"
            recorded[node][seq] = bytes(raw)
    for node in NODES:
        assert sorted(recorded[node]) == list(range(BATCHES)), f"{node}: every batch, once"
        for seq, raw in recorded[node].items():
            assert raw == sent[node][seq], f"{node} batch {seq}: the bytes sent"
