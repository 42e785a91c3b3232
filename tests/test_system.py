"""Hub and two edges as separate OS processes over real Zenoh on loopback; files read back
with rosbags."""

from __future__ import annotations

import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from rosbags.highlevel import AnyReader

from fleetdaq.hub.recording.session import ACTIVE_SUFFIX
from tests.procs import Proc, free_port, sessions, wait_for_port

RUN_S = 10.0
SITE = """\
site: systest
hub:
  listen: [tcp/127.0.0.1:{port}]
  recorder: {{file_duration_s: 3}}
nodes:
  wec:
    streams:
      t8:
        driver: wave_sim
        rate_hz: 10000
        scans_per_batch: 100
        drift_ppm: 40
        channels:
          - {{name: heave, unit: m, scale: 0.5}}
          - {{name: surge, unit: m}}
          - {{name: pitch, unit: deg}}
          - {{name: force, unit: kN, scale: 12.5, offset: -1}}
  am-cell:
    streams:
      tc:
        driver: thermocouple_sim
        rate_hz: 4
        channels: [{{name: substrate, unit: degC}}, {{name: cold_junction, unit: degC}}]
"""
RATES = {"/wec/t8": 10000.0, "/am_cell/tc": 4.0}  # node am-cell: topics /am_cell/...


@pytest.fixture(scope="module")
def recording(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[Path, list[Proc]]]:
    tmp = tmp_path_factory.mktemp("system")
    port = free_port()
    cfg = tmp / "site.yaml"
    cfg.write_text(SITE.format(port=port))
    data = tmp / "data"
    procs: list[Proc] = []
    try:
        hub = Proc(["hub", "--config", str(cfg), "--data", str(data)], tmp / "hub.log")
        procs.append(hub)
        wait_for_port(port)
        for node in ("wec", "am-cell"):
            procs.append(
                Proc(
                    ["edge", "--config", str(cfg), "--node", node, "--spool", str(tmp / "spool")],
                    tmp / f"{node}.log",
                )
            )
        time.sleep(RUN_S)  # the acquisition itself: a fixed stretch of real time
        codes = {p.log_path.stem: p.terminate() for p in procs[1:]}
        codes["hub"] = hub.terminate()
        assert codes == {"wec": 0, "am-cell": 0, "hub": 0}, {
            p.log_path.stem: p.output()[-2000:] for p in procs
        }
        (session,) = sessions(data)
        yield session, procs
    finally:
        for p in procs:
            p.kill()


def _messages(session: Path) -> dict[str, list[tuple[int, object]]]:
    out: dict[str, list[tuple[int, object]]] = {}
    files = sorted(session.glob("*.mcap"))
    with AnyReader(files) as reader:
        for conn, log_time, raw in reader.messages():
            out.setdefault(conn.topic, []).append((log_time, reader.deserialize(raw, conn.msgtype)))
    return out


def test_every_file_is_closed_and_decodes(recording: tuple[Path, list[Proc]]):
    session, _ = recording
    assert not list(session.glob("*" + ACTIVE_SUFFIX))
    files = sorted(session.glob("*.mcap"))
    assert len(files) >= 3, "10 s at file_duration_s 3 makes at least 3 files"
    for f in files:
        with AnyReader([f]) as reader:
            n = sum(1 for c, _, raw in reader.messages() if reader.deserialize(raw, c.msgtype))
        assert n > 0


def test_sequences_are_contiguous_across_files(recording: tuple[Path, list[Proc]]):
    msgs = _messages(recording[0])
    health = {"/wec/health", "/am_cell/health", "/hub/health"}
    assert set(msgs) == {*RATES, "/events", *health}
    for topic in RATES:
        items = msgs[topic]
        seqs = [m.sequence for _, m in items]  # type: ignore[attr-defined]
        assert seqs == list(range(len(seqs))), f"{topic}: not contiguous from 0"


def test_sample_counts_match_rate_times_time(recording: tuple[Path, list[Proc]]):
    msgs = _messages(recording[0])
    for topic, rate in RATES.items():
        items = msgs[topic]
        first, last = items[0][1], items[-1][1]
        scans = sum(m.scan_count for _, m in items)  # type: ignore[attr-defined]
        span_s = (
            last.first_sample_time_ns
            + last.scan_count * last.sample_period_ns  # type: ignore[attr-defined]
            - first.first_sample_time_ns
        ) / 1e9  # type: ignore[attr-defined]
        expected = rate * span_s
        assert abs(scans - expected) <= 0.02 * expected + 1, (topic, scans, expected)
        assert span_s > 0.7 * RUN_S, (topic, span_s)
        values = np.concatenate([m.data for _, m in items])  # type: ignore[attr-defined]
        assert values.size == scans * first.channel_count  # type: ignore[attr-defined]
        assert np.isfinite(values).all()


def test_first_sample_times_increase_and_sit_near_log_time(recording: tuple[Path, list[Proc]]):
    msgs = _messages(recording[0])
    for topic in RATES:
        items = msgs[topic]
        times = np.array([m.first_sample_time_ns for _, m in items])  # type: ignore[attr-defined]
        assert (np.diff(times) > 0).all(), topic
        lag_ms = np.array([log - m.first_sample_time_ns for log, m in items]) / 1e6  # type: ignore[attr-defined]
        # Every batch of this site is at most 10 ms long (100 scans at 10 kHz, 1 scan at 4 Hz).
        assert lag_ms.min() >= 0, (topic, lag_ms.min())
        assert lag_ms.max() <= 50, (topic, np.percentile(lag_ms, [50, 99, 100]))


def test_every_edges_start_and_stop_are_events_in_the_recording(
    recording: tuple[Path, list[Proc]],
):
    msgs = _messages(recording[0])
    events = [(m.node, m.tag) for _, m in msgs.get("/events", [])]  # type: ignore[attr-defined]
    for node in ("wec", "am-cell"):
        assert (node, "started") in events, events
        assert (node, "stopped") in events, events
    assert ("hub", "started") in events
    assert (recording[0].parent / "events.log").read_text().count("started") >= 3


def test_every_nodes_typed_health_is_in_the_recording_about_once_a_second(
    recording: tuple[Path, list[Proc]],
):
    msgs = _messages(recording[0])
    for node in ("wec", "am-cell", "hub"):
        items = msgs[f"/{node.replace('-', '_')}/health"]  # recorded under its ROS 2 name
        assert len(items) >= 0.5 * RUN_S, (node, len(items))
        last = items[-1][1]
        assert last.node == node  # type: ignore[attr-defined]
        assert last.host.memory_total_bytes > 0  # type: ignore[attr-defined]
        roles = {d.role for d in last.host.disks}  # type: ignore[attr-defined]
        assert roles == ({"data"} if node == "hub" else {"spool"}), roles
    wec = msgs["/wec/health"][-1][1]
    (t8,) = wec.streams  # type: ignore[attr-defined]
    assert t8.name == "t8"
    assert t8.batches > 0
    assert t8.spool_acked >= 0, "the hub's acks reached the edge"
