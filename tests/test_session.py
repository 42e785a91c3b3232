"""Recording sessions: split files, `.active` names, selection, metadata, rosbag2 layout."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml
from mcap.reader import make_reader
from rosbags.highlevel import AnyReader

from fleetdaq.contract.wire import BatchEncoder, decode_batch
from fleetdaq.hub.config.hub import RecorderConfig
from fleetdaq.hub.recording.session import ACTIVE_SUFFIX, RecordingSession, StreamSelector
from fleetdaq.hub.recording.stream_stats import StreamStats
from fleetdaq.ptp.quality import UNSYNCED

T0 = 1_795_000_000_000_000_000
SEC = 1_000_000_000


def _payloads(n: int, scans: int = 100, seed: int = 0) -> list[bytes]:
    rng = np.random.default_rng(seed)
    enc = BatchEncoder("wec", "t8", ("a", "b"), ("V", "V"))
    return [
        bytes(enc.encode(i, T0 + i * SEC // 10, 1e6, rng.normal(size=(scans, 2)), UNSYNCED))
        for i in range(n)
    ]


def _session(tmp_path: Path, **kw: object) -> RecordingSession:
    cfg = RecorderConfig.model_validate(kw)
    return RecordingSession(tmp_path, "demo", ["wec"], cfg, "site: demo\n", T0)


def test_files_split_every_file_duration_and_are_active_until_closed(tmp_path: Path):
    s = _session(tmp_path, file_duration_s=1.0)
    for i, p in enumerate(_payloads(35)):  # 3.5 s of batches at 10 Hz
        s.write("/wec/t8", p, T0 + i * SEC // 10, T0 + i * SEC // 10)
        active = list(s.dir.glob("*.mcap" + ACTIVE_SUFFIX))
        assert len(active) == 1, "exactly one file is being written"
        assert active[0] == s.current_file
    assert [p.name for p in sorted(s.dir.glob("*.mcap"))] == [
        f"{s.name}_{i:04d}.mcap" for i in range(3)
    ]
    s.close()
    s.close()  # idempotent
    assert not list(s.dir.glob("*" + ACTIVE_SUFFIX))
    files = sorted(s.dir.glob("*.mcap"))
    assert len(files) == 4
    counts = []
    for f in files:
        with f.open("rb") as fh:
            counts.append(sum(1 for _ in make_reader(fh).iter_messages()))
    assert counts == [10, 10, 10, 5]


def test_files_split_at_max_file_bytes(tmp_path: Path):
    s = _session(tmp_path, file_duration_s=None, max_file_bytes=1_000_000, chunk_size=65536)
    payloads = _payloads(60, scans=4000)  # 64 KB of noise each: ~3.8 MB in all
    for i, p in enumerate(payloads):
        s.write("/wec/t8", p, T0 + i, T0 + i)
    s.close()
    files = sorted(s.dir.glob("*.mcap"))
    assert len(files) >= 4
    assert all(f.stat().st_size <= 1_000_000 for f in files), [f.stat().st_size for f in files]


def test_each_file_holds_session_metadata_config_and_schema(tmp_path: Path):
    s = _session(tmp_path, file_duration_s=1.0)
    for i, p in enumerate(_payloads(15)):
        s.write("/wec/t8", p, T0 + i * SEC // 10, T0 + i * SEC // 10 + 5)
    s.close()
    for f in sorted(s.dir.glob("*.mcap")):
        with f.open("rb") as fh:
            r = make_reader(fh)
            meta = {m.name: m.metadata for m in r.iter_metadata()}
            assert meta["fleetdaq.session"]["site"] == "demo"
            assert meta["fleetdaq.session"]["session"] == s.name
            assert meta["fleetdaq.session"]["software"].startswith("fleetdaq ")
            (att,) = list(r.iter_attachments())
            assert att.name == "config.yaml"
            assert yaml.safe_load(att.data) == {"site": "demo"}
            summary = r.get_summary()
            assert summary is not None
            (schema,) = summary.schemas.values()
            assert schema.encoding == "ros2msg"
            for _, _, msg in r.iter_messages():
                assert msg.log_time - msg.publish_time == 5


def test_session_folder_opens_as_one_rosbag2_bag(tmp_path: Path):
    s = _session(tmp_path, file_duration_s=1.0)
    payloads = _payloads(25)
    for i, p in enumerate(payloads):
        s.write("/wec/t8", p, T0 + i * SEC // 10, T0 + i * SEC // 10)
    s.close()
    with AnyReader([s.dir]) as reader:
        seqs = [reader.deserialize(raw, c.msgtype).sequence for c, _, raw in reader.messages()]
    assert seqs == list(range(25))


def test_selection_counts_every_include_and_exclude_pattern():
    sel = StreamSelector(["wec/*", "shore/env"], ["wec/raw*", "*/debug"])
    assert sel("wec", "t8")
    assert sel("shore", "env")
    assert not sel("shore", "wind")
    assert not sel("wec", "raw_adc")
    assert not sel("wec", "debug")
    assert StreamSelector(["*"], [])("am-cell", "tc")


def test_accounting_counts_holes_duplicates_and_late_batches():
    st = StreamStats("wec", "t8", True)
    for seq in [5, 6, 7, 10, 10, 8, 11]:
        is_new, lost = st.offer(seq, floor=None)
        assert lost == 0
        if is_new:
            st.count(seq, scans=100, samples=800, recv_ns=seq, t0=seq, period_ns=1.0)
    assert st.first_sequence == 5
    assert st.missing == 1  # 9 is still expected (the edge may replay it)
    assert st.contiguous == 8
    assert st.duplicates == 1  # the second 10
    assert st.late == 1  # 8 came after 10
    assert st.batches == 6
    assert st.samples == 4800


def test_a_floor_past_a_hole_makes_it_lost_for_good():
    st = StreamStats("wec", "t8", True)
    assert st.offer(0, floor=0) == (True, 0)
    assert st.offer(3, floor=0) == (True, 0)  # 1, 2 missing: may still come
    assert st.missing == 2
    assert st.offer(4, floor=2) == (True, 1)  # the edge dropped 1 (spool full): lost
    assert (st.lost, st.missing, st.gaps) == (1, 1, 2)
    assert st.offer(2, floor=2) == (True, 0)
    assert (st.contiguous, st.missing, st.gaps) == (4, 0, 1)


def test_a_hub_that_starts_late_takes_the_edges_floor_as_its_base():
    st = StreamStats("wec", "t8", True)
    assert st.offer(120, floor=100) == (True, 0)  # the live batch; 100..119 will be replayed
    assert (st.first_sequence, st.contiguous, st.missing) == (100, 99, 20)
    for seq in range(100, 120):
        st.offer(seq, floor=100)
    assert (st.contiguous, st.missing, st.lost) == (120, 0, 0)


def test_decoded_payload_from_file_equals_what_was_written(tmp_path: Path):
    s = _session(tmp_path, file_duration_s=10.0)
    payloads = _payloads(3)
    for i, p in enumerate(payloads):
        s.write("/wec/t8", p, T0 + i, T0 + i)
    s.close()
    (f,) = sorted(s.dir.glob("*.mcap"))
    with f.open("rb") as fh:
        got = [m.data for _, _, m in make_reader(fh).iter_messages()]
    assert got == payloads
    assert decode_batch(got[2]).header.sequence == 2


def test_a_restarted_spool_numbering_is_counted_afresh_and_its_open_holes_lost():
    st = StreamStats("wec", "t8", True, epoch=7)
    for seq in [0, 1, 2, 4, 5]:
        assert st.offer(seq, floor=0)[0]
    assert st.missing == 1  # 3
    assert st.restart(8) == 1, "the old spool's hole can never be filled now"
    assert st.lost == 1
    assert st.epoch == 8
    assert st.spool_restarts == 1
    for seq in [0, 1, 2]:  # the new spool's batches are new, not replays of the old ones
        is_new, lost = st.offer(seq, floor=0)
        assert is_new
        assert lost == 0
    assert st.contiguous == 2
    assert st.duplicates == 0


def test_a_file_whose_head_cannot_be_written_leaves_no_active_file(tmp_path: Path):
    cfg = RecorderConfig(file_duration_s=60)
    # Metadata holding text no encoder writes (a lone surrogate), past every check upstream.
    extra = {"fleetdaq.snapshot": {"note": "layer \ud800"}}
    s = RecordingSession(tmp_path, "demo", ["wec"], cfg, "site: demo\n", T0, extra_metadata=extra)
    with pytest.raises(UnicodeEncodeError):
        s.write("/wec/t8", _payloads(1)[0], T0, T0)
    assert [p.name for p in s.dir.iterdir()] == ["metadata.yaml"]  # the empty bag, from the start
    assert s.current_file is None
