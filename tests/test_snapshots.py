"""The snapshot buffer: bounded by time and by memory (and says so), and written when an alarm of
a configured severity is raised — with the batches before it, read back by `fleetdaq.read`."""

from __future__ import annotations

import re
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import zenoh

from fleetdaq.contract.keys import SiteKeys
from fleetdaq.contract.wire import BatchEncoder, encode_u64
from fleetdaq.hub.bus import EventBus
from fleetdaq.hub.config.load import parse_config
from fleetdaq.hub.read_model import ReadModel
from fleetdaq.hub.recording.batch_feed import BatchFeed
from fleetdaq.hub.recording.snapshots import OVERHEAD_BYTES, SnapshotBuffer
from fleetdaq.hub.runtime import HubRuntime
from fleetdaq.ptp.quality import UNSYNCED
from fleetdaq.read import read_events, read_stream
from fleetdaq.runtime.zenoh_session import client_config
from tests.procs import free_port, wait_until

SITE = """\
site: snap
hub:
  listen: [tcp/127.0.0.1:{port}]
  recorder: {{flush_interval_s: 0.2}}
  snapshot: {{seconds: {seconds}, max_bytes: {max_bytes}, on_alarm: [major],
              min_interval_s: 3600}}
  dashboard: {{enabled: false}}
nodes:
  wec:
    streams:
      t8: {{driver: wave_sim, rate_hz: 1000, channels: [{{name: heave, unit: m}}]}}
alarms:
  heave_high: {{channel: wec/t8/heave, above: 5, severity: major}}
  heave_very_high: {{channel: wec/t8/heave, above: 8, severity: major}}
"""


def buffer(tmp_path: Path, seconds: float, max_bytes: int) -> SnapshotBuffer:
    site = parse_config(SITE.format(port=1, seconds=seconds, max_bytes=max_bytes), "<test>")
    return SnapshotBuffer(site, tmp_path, EventBus(), ReadModel("snap"), BatchFeed())


def test_the_buffer_holds_the_last_seconds_only(tmp_path: Path):
    snap = buffer(tmp_path, seconds=5, max_bytes=1 << 30)
    t0 = 1_800_000_000_000_000_000
    for i in range(100):  # 10 s at 10 messages/s
        snap.offer("/wec/t8", b"x" * 100, t0 + i * 100_000_000, t0 + i * 100_000_000, "t")
    c = snap.counters()
    assert c["covers_s"] == pytest.approx(5.0, abs=0.11)
    assert c["held_messages"] in (50, 51)
    assert c["held_bytes"] == c["held_messages"] * (100 + OVERHEAD_BYTES)
    assert c["evicted_for_memory"] == 0, "time, not memory, was the bound"


def test_memory_binds_before_time_and_the_view_says_how_much_is_covered(tmp_path: Path):
    snap = buffer(tmp_path, seconds=60, max_bytes=1 << 20)
    t0 = 1_800_000_000_000_000_000
    payload = b"x" * 100_000
    for i in range(50):  # 5 MB in 5 s
        snap.offer("/wec/t8", payload, t0 + i * 100_000_000, t0 + i * 100_000_000, "t")
    c = snap.counters()
    assert c["held_bytes"] <= 1 << 20
    assert c["held_messages"] == (1 << 20) // (100_000 + OVERHEAD_BYTES)
    assert c["evicted_for_memory"] == 50 - c["held_messages"]
    assert c["covers_s"] < 1.0, "the view says it covers far less than the 60 s asked for"


@pytest.fixture
def hub(tmp_path: Path) -> Iterator[tuple[HubRuntime, int]]:
    port = free_port()
    site = parse_config(SITE.format(port=port, seconds=3, max_bytes=64 << 20), "<test>")
    runtime = HubRuntime(site, tmp_path / "data")
    yield runtime, port
    runtime.close()


def test_an_alarm_writes_the_seconds_before_it_and_a_second_alarm_shares_it(
    hub: tuple[HubRuntime, int],
):
    runtime, port = hub
    runtime.start()
    runtime.recorder.stop_recording("test")  # nobody records: the snapshot still has it
    keys = SiteKeys("snap")
    session = zenoh.open(client_config([f"tcp/127.0.0.1:{port}"]))
    pub = session.declare_publisher(keys.data("wec", "t8"))
    enc = BatchEncoder("wec", "t8", ("heave",), ("m",))
    try:
        wait_until(lambda: pub.matching_status.matching, 10, "the hub's subscription")
        t0 = time.time_ns()
        seq = 0

        def send(value: float, n: int) -> None:
            nonlocal seq
            for _ in range(n):
                data = np.full((100, 1), value)
                pub.put(bytes(enc.encode(seq, t0 + seq * 100_000_000, 1e6, data, UNSYNCED)),
                        attachment=encode_u64(0))  # fmt: skip
                seq += 1

        send(1.0, 40)  # 4 s of normal data: more than the 3 s the buffer keeps
        wait_until(lambda: runtime.snapshot_buffer.counters()["held_messages"] >= 30, 20, "held")  # type: ignore[union-attr]
        send(9.0, 2)  # both alarms raise
        wait_until(lambda: runtime.snapshot().snapshots["written"] == 1, 30, "the alarm's snapshot")
        view = runtime.snapshot()
        assert view.snapshots["merged_alarms"] == 1, "the second alarm shares the first's file"
        folder = Path(view.snapshots["last"])
        assert folder.parent == runtime.data_dir / "snapshots"
        s = read_stream(folder, "wec/t8")
        assert s.data.max() == 9.0, "the batch that raised the alarm is in it"
        assert 2.0 <= (s.time_ns[-1] - s.time_ns[0]) / 1e9 <= 4.3
        assert np.count_nonzero(s.data == 1.0) >= 2000, "and the seconds before it"
        tags = [e.tag for e in read_events(folder)]
        assert "alarm_raised" in tags
        assert "recording_stopped" in tags
        # The event goes through the bus, after the counter: wait for it.
        wait_until(
            lambda: any(e.tag == "snapshot" for e in runtime.snapshot().recent_events),
            10,
            "the snapshot event",
        )
        taken = [e for e in runtime.snapshot().recent_events if e.tag == "snapshot"]
        assert (taken[-1].get("why") or "").startswith("alarm heave_")
        assert not list((runtime.data_dir / "snapshots").glob("*/*.active"))

        # Recording again: an alarm's seconds are in the recording, so no snapshot is taken.
        runtime.recorder.start_recording("test")
        send(1.0, 2)  # the alarms clear...
        send(9.0, 1)  # ...and raise again
        wait_until(lambda: runtime.snapshot().snapshots["skipped_recording"] >= 1, 20, "the skip")
        assert runtime.snapshot().snapshots["written"] == 1
    finally:
        pub.undeclare()
        session.close()


# --- a partitioned site: the main hub's triggers, to each partition hub's own buffer ------------


def test_the_buffer_tells_of_every_request_and_alarm_and_takes_remote_ones_as_its_own(
    tmp_path: Path,
):
    from fleetdaq.contract.messages import make_event

    site = parse_config(SITE.format(port=1, seconds=60, max_bytes=1 << 30), "<test>")
    recording = [True]
    told: list[dict[str, str]] = []
    snap = SnapshotBuffer(
        site,
        tmp_path,
        EventBus(),
        ReadModel("snap"),
        BatchFeed(),
        lambda: recording[0],
        on_trigger=told.append,
    )
    snap.start()
    try:
        assert snap.snapshot("ann@desk", "before the storm")[0] is False  # nothing held yet
        raised = make_event(time.time_ns(), "hub", 40, "alarms", "alarm_raised", "x",
                            alarm="heave_high", severity="major")  # fmt: skip
        snap._on_event(raised)
        assert told == [
            {"kind": "request", "who": "ann@desk", "note": "before the storm"},
            {"kind": "alarm", "alarm": "heave_high"},
        ]
        assert snap.skipped_recording == 1, "recording: this hub's own alarm takes none"
        snap.remote({"kind": "alarm", "alarm": "heave_high"})
        assert snap.skipped_recording == 2, "nor a passed-on one while its recorder writes"
        recording[0] = False
        snap.remote({"kind": "alarm", "alarm": "heave_high"})
        snap.remote({"kind": "alarm", "alarm": "heave_very_high"})
        assert snap.merged == 1, "alarms within min_interval_s share one snapshot"
    finally:
        snap.stop()


@pytest.mark.parametrize(
    ("raw", "why"),
    [
        (b"", "not JSON"),
        (b"[]", "not a JSON object"),
        (b'{"kind": "shutdown"}', "is not alarm or request"),
        (b'{"kind": "alarm"}', "missing ['alarm']"),
        (b'{"kind": "request", "note": "x"}', "missing ['who']"),
        (b'{"kind": "alarm", "alarm": "a", "path": "/etc"}', "unknown keys ['path']"),
        (b'{"kind": "alarm", "alarm": 7}', "alarm is not a string"),
        (b'{"kind": "request", "who": "' + b"w" * 5000 + b'"}', "bytes (at most 4096)"),
        (b'{"kind": "request", "who": "a@b", "note": "\\ud800"}', "note holds a lone UTF-16"),
        (b'{"kind": "alarm", "alarm": "a\\u001b[2J"}', "alarm holds a control character"),
    ],
)
def test_a_trigger_that_is_not_one_is_refused_saying_why(raw: bytes, why: str):
    from fleetdaq.hub.partitions.snapshots import parse_trigger

    with pytest.raises(ValueError, match=re.escape(why)):
        parse_trigger(raw)
    assert parse_trigger(b'{"kind": "request", "who": "ann@desk"}') == {
        "kind": "request", "who": "ann@desk"
    }  # fmt: skip
