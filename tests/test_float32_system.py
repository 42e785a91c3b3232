"""A float32 stream end to end: hub and a sim edge as separate OS processes over real Zenoh on
loopback. The edge sends SampleBatch32, the hub records it untouched under that schema next to
a float64 stream, and the recording reads back the same with rosbags, mcap-ros2-support and
fleetdaq.read; a SampleBatch on the float32 stream's key is refused as malformed."""

from __future__ import annotations

import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap_ros2.reader import read_ros2_messages
from rosbags.highlevel import AnyReader

import fleetdaq.read as fr
from fleetdaq.contract.keys import SiteKeys
from fleetdaq.contract.wire import SAMPLE_BATCH32_TYPE, SAMPLE_BATCH_TYPE, BatchEncoder
from fleetdaq.ptp.quality import ClockQuality, ClockState
from tests.procs import HubClient, Proc, free_port, sessions, stream_view, wait_for_port

BATCHES = 30
SITE = """\
site: f32sys
hub:
  listen: [tcp/127.0.0.1:{port}]
nodes:
  wec:
    streams:
      t8:
        driver: wave_sim
        rate_hz: 2000
        scans_per_batch: 100
        sample_format: float32
        channels:
          - {{name: heave, unit: m, scale: 0.5}}
          - {{name: force, unit: kN, scale: 12.5, offset: -1}}
      ref:
        driver: wave_sim
        rate_hz: 1000
        scans_per_batch: 100
        channels: [{{name: surge, unit: m}}]
"""
UNSYNCED = ClockQuality(ClockState.UNSYNCED, 0, "", "none")
TOPICS = {"/wec/t8": SAMPLE_BATCH32_TYPE, "/wec/ref": SAMPLE_BATCH_TYPE}


@pytest.fixture(scope="module")
def session(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Path]:
    tmp = tmp_path_factory.mktemp("f32")
    port = free_port()
    cfg = tmp / "site.yaml"
    cfg.write_text(SITE.format(port=port))
    data = tmp / "data"
    hub = Proc(["hub", "--config", str(cfg), "--data", str(data)], tmp / "hub.log")
    procs = [hub]
    try:
        wait_for_port(port)
        edge = Proc(
            ["edge", "--config", str(cfg), "--node", "wec", "--spool", str(tmp / "spool")],
            tmp / "wec.log",
        )
        procs.append(edge)
        with HubClient(port, "f32sys") as client:

            def enough(status: dict[str, object]) -> bool:
                views = [stream_view(status, "wec", s) for s in ("t8", "ref")]  # type: ignore[arg-type]
                return all(v is not None and v["batches"] >= BATCHES for v in views)

            client.wait(enough, 60, f"{BATCHES} batches of each stream recorded")
            # A float64 SampleBatch on the float32 stream's key is not a batch of that stream.
            enc = BatchEncoder("wec", "t8", ("heave", "force"), ("m", "kN"))
            wrong = enc.encode(10**6, time.time_ns(), 5e5, np.zeros((100, 2)), UNSYNCED)
            client.session.put(SiteKeys("f32sys").data("wec", "t8"), bytes(wrong))

            def refused(status: dict[str, object]) -> dict[str, object] | None:
                t8 = stream_view(status, "wec", "t8")  # type: ignore[arg-type]
                return t8 if t8 is not None and t8["malformed"] == 1 else None

            t8 = client.wait(refused, 20, "the float64 batch refused as malformed")
            assert t8["gaps"] == 0
        codes = {"wec": edge.terminate(), "hub": hub.terminate()}
        assert codes == {"wec": 0, "hub": 0}, {p.log_path.stem: p.output()[-2000:] for p in procs}
        (found,) = sessions(data)
        yield found
    finally:
        for p in procs:
            p.kill()


def _files(session: Path) -> list[Path]:
    files = sorted(session.glob("*.mcap"))
    assert files
    return files


def test_each_stream_is_recorded_under_its_own_message_type(session: Path):
    for f in _files(session):
        with f.open("rb") as fh:
            summary = make_reader(fh).get_summary()
        assert summary is not None
        types = {
            ch.topic: summary.schemas[ch.schema_id].name
            for ch in summary.channels.values()
            if ch.topic in TOPICS
        }
        assert types == TOPICS


def _rosbags(session: Path) -> dict[str, list[object]]:
    out: dict[str, list[object]] = {}
    with AnyReader(_files(session)) as reader:
        for conn, _, raw in reader.messages():
            if conn.topic in TOPICS:
                out.setdefault(conn.topic, []).append(reader.deserialize(raw, conn.msgtype))
    return out


def test_rosbags_mcap_ros2_support_and_fleetdaq_read_agree_on_the_float32_stream(session: Path):
    by_rosbags = _rosbags(session)
    msgs: list[object] = by_rosbags["/wec/t8"]
    seqs = [m.sequence for m in msgs]  # type: ignore[attr-defined]
    assert seqs == list(range(len(seqs)))
    assert len(seqs) >= BATCHES
    theirs = np.concatenate([m.data for m in msgs])  # type: ignore[attr-defined]
    assert theirs.dtype == np.float32
    assert np.isfinite(theirs).all()

    other: list[float] = []
    for f in _files(session):
        with f.open("rb") as fh:
            for m in read_ros2_messages(fh, topics=["/wec/t8"]):
                other.extend(m.ros_msg.data)
    np.testing.assert_array_equal(np.array(other, dtype=np.float32), theirs)

    s = fr.read_stream(session, "wec/t8")
    assert s.data.dtype == np.float64  # widened exactly
    assert s.data.shape == (theirs.size // 2, 2)
    np.testing.assert_array_equal(s.data, theirs.reshape(-1, 2).astype(np.float64))
    # float32 values indeed: rounding them to float32 again changes nothing, and they are real
    # wave data (not zeros): float32(truth) as the edge computed it.
    np.testing.assert_array_equal(s.data.astype(np.float32).astype(np.float64), s.data)
    assert np.ptp(s["force"]) > 1.0


def test_the_float64_stream_next_to_it_stays_float64(session: Path):
    msgs = _rosbags(session)["/wec/ref"]
    data = np.concatenate([m.data for m in msgs])  # type: ignore[attr-defined]
    assert data.dtype == np.float64
    s = fr.read_stream(session, "wec/ref")
    np.testing.assert_array_equal(s.data.reshape(-1), data)
    assert not np.array_equal(data.astype(np.float32).astype(np.float64), data)


def test_a_float32_batch_is_about_half_the_bytes_of_a_float64_one(session: Path):
    """Per sample in the messages as sent (2 and 1 channels per scan, 100 scans a batch)."""
    sizes: dict[str, list[int]] = {}
    for f in _files(session):
        with f.open("rb") as fh:
            for _, ch, msg in make_reader(fh).iter_messages(topics=list(TOPICS)):
                sizes.setdefault(ch.topic, []).append(len(msg.data))
    per32 = np.median(sizes["/wec/t8"]) / 200
    per64 = np.median(sizes["/wec/ref"]) / 100
    assert per32 < 0.6 * per64, (per32, per64)
