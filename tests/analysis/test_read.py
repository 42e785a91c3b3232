"""`fleetdaq.read`: a recording into numpy with times, names and units; windows that read only
the files they need; replays deduplicated; invalid samples NaN; gaps listed; clear errors."""

from __future__ import annotations

import tracemalloc
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap.writer import Writer
from rosbags.highlevel import AnyReader

import fleetdaq.read as fr
from fleetdaq.contract.wire import (
    SAMPLE_BATCH_SCHEMA,
    SAMPLE_BATCH_TYPE,
    BatchEncoder,
    SampleStatus,
)
from fleetdaq.hub.config.hub import RecorderConfig
from fleetdaq.hub.recording.session import ACTIVE_SUFFIX, RecordingSession
from fleetdaq.hub.recording.verify import recover_file
from tests.analysis.recordings import (
    CHANNELS,
    SEC,
    T0,
    UNITS,
    Batch,
    alarm_message,
    event_message,
    health_message,
    make_batches,
    write_session,
)


def _expected(batches: list[Batch]) -> tuple[np.ndarray, np.ndarray]:
    return (
        np.concatenate([b.times() for b in batches]),
        np.concatenate([b.data for b in batches]),
    )


def test_a_session_reads_into_numpy_with_times_names_and_units(tmp_path: Path):
    batches = make_batches(30, scans=100, rate_hz=1000.0)  # 3 s, 3 files of 1 s
    s = write_session(tmp_path, batches)
    got = fr.read_stream(s.dir, "wec/t8")
    t, data = _expected(batches)
    assert got.channels == CHANNELS
    assert got.units == UNITS
    assert np.array_equal(got.time_ns, t)
    assert np.array_equal(got.data, data)
    assert got.time.dtype == np.dtype("datetime64[ns]")
    assert got.time[0] == np.datetime64(T0, "ns")
    assert np.array_equal(got["surge"], data[:, 1])
    assert got.unit("pitch") == "deg"
    assert got.gaps == ()
    assert got.duplicates == 0
    assert list(got.batches.sequence) == list(range(30))
    assert got.sample_rate_hz == pytest.approx(1000.0)
    assert set(got.files) == set(s.files())
    assert len(s.files()) == 3


def test_values_agree_with_an_independent_reader(tmp_path: Path):
    s = write_session(tmp_path, make_batches(12, scans=250, seed=3))
    with AnyReader([s.dir]) as reader:
        conns = [c for c in reader.connections if c.topic == "/wec/t8"]
        msgs = [reader.deserialize(raw, c.msgtype) for c, _, raw in reader.messages(conns)]
    theirs = np.concatenate([m.data.reshape(m.scan_count, m.channel_count) for m in msgs])
    t = np.concatenate(
        [
            m.first_sample_time_ns
            + np.rint(np.arange(m.scan_count) * m.sample_period_ns).astype(np.int64)
            for m in msgs
        ]
    )
    ours = fr.read_stream(s.dir, "/wec/t8")
    assert np.array_equal(ours.data, theirs)
    assert np.array_equal(ours.time_ns, t)
    assert tuple(msgs[0].channel_names) == ours.channels


def test_a_window_is_half_open_to_the_scan(tmp_path: Path):
    batches = make_batches(10, scans=100, rate_hz=1000.0)
    s = write_session(tmp_path, batches)
    t, data = _expected(batches)
    start, end = int(t[150]), int(t[420])
    got = fr.read_stream(s.dir, "t8", start=start, end=end)
    assert np.array_equal(got.time_ns, t[150:420])
    assert np.array_equal(got.data, data[150:420])
    # The same window as text (ISO 8601 with ns, an offset) and as an offset from the start.
    iso = fr.read_stream(s.dir, "t8", start="2026-11-18T12:06:40.150+01:00", end=end)
    assert np.array_equal(iso.time_ns, got.time_ns)
    rel = fr.read_stream(s.dir, "t8", start="+150ms", end="+420ms")
    assert np.array_equal(rel.time_ns, got.time_ns)
    assert iso.files == (s.files()[0],)


def test_a_window_opens_only_the_files_it_needs(tmp_path: Path):
    batches = make_batches(60, scans=100, rate_hz=1000.0)  # 6 s in six 1-s files
    s = write_session(tmp_path, batches)
    files = s.files()
    assert len(files) == 6
    # Wreck every chunk of the files outside the window (their summaries stay readable): a
    # reader that touched their data would fail.
    for f in files[:2] + files[4:]:
        _scramble_chunks(f)
    got = fr.read_stream(
        s.dir, "wec/t8", start=T0 + 2 * SEC + SEC // 4, end=T0 + 3 * SEC + SEC // 2
    )
    t, data = _expected(batches)
    keep = (t >= T0 + 2 * SEC + SEC // 4) & (t < T0 + 3 * SEC + SEC // 2)
    assert np.array_equal(got.data, data[keep])
    assert got.files == (files[2], files[3])
    with pytest.raises(fr.DamagedRecording, match=files[0].name):
        fr.read_stream(s.dir, "wec/t8")


def _scramble_chunks(path: Path) -> None:
    with path.open("rb") as fh:
        summary = make_reader(fh).get_summary()
    assert summary is not None
    raw = bytearray(path.read_bytes())
    for ci in summary.chunk_indexes:
        a = ci.chunk_start_offset + 60
        raw[a : ci.chunk_start_offset + ci.chunk_length] = b"\xa5" * (ci.chunk_length - 60)
    path.write_bytes(bytes(raw))


def test_memory_follows_the_window_not_the_recording(tmp_path: Path):
    batches = make_batches(400, scans=2000, rate_hz=10_000.0, channels=3)  # 80 s, 19.2 MB
    s = write_session(tmp_path, batches, file_duration_s=2.0)  # 40 files
    session_bytes = sum(b.data.nbytes for b in batches)
    tracemalloc.start()
    try:
        got = fr.read_stream(s.dir, "wec/t8", start="+16s", end="+18s")
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert got.data.nbytes == session_bytes // 40
    assert len(got.files) == 1
    # The window's data, its times and a few chunks in flight: nothing near the session's size.
    assert peak < session_bytes // 5, (peak, session_bytes)


def test_a_replay_in_the_next_session_appears_once(tmp_path: Path):
    first = make_batches(30, seed=1)  # sequences 0..29
    later = make_batches(40, first_sequence=25, t0_ns=first[25].t0_ns, seed=2)
    later = first[25:30] + later[5:]  # the hub crashed: 25..29 re-sent, then live again
    a = write_session(tmp_path / "a", first)
    b = write_session(tmp_path / "b", later)
    got = fr.read_stream([a.dir, b.dir], "wec/t8")
    assert list(got.batches.sequence) == list(range(65))
    assert got.duplicates == 5
    t, data = _expected(first + later[5:])
    assert np.array_equal(got.time_ns, t)
    assert np.array_equal(got.data, data)


def test_a_data_root_reads_every_session_in_it(tmp_path: Path):
    first = make_batches(10, seed=1)
    second = make_batches(10, first_sequence=10, t0_ns=first[-1].t0_ns + SEC, seed=2)
    write_session(tmp_path / "data", first)
    write_session(tmp_path / "data", second, start_ns=second[0].t0_ns)
    got = fr.read_stream(tmp_path / "data", "wec/t8")
    assert list(got.batches.sequence) == list(range(20))
    assert [g.kind for g in got.gaps] == ["acquisition"]
    assert len(fr.open_recording(tmp_path / "data").sessions()) == 2


def test_batches_replayed_late_are_put_back_in_time_order(tmp_path: Path):
    batches = make_batches(20, scans=50)
    late = [10, 11, 12]  # held in the edge's spool during an outage, replayed after 19
    order = [b for b in batches if b.sequence not in late] + [batches[i] for i in late]
    log = [T0 + 10 * SEC + i * 1_000_000 for i in range(len(order))]
    s = write_session(tmp_path, order, log_ns=log)
    got = fr.read_stream(s.dir, "wec/t8")
    t, data = _expected(batches)
    assert np.array_equal(got.time_ns, t)
    assert np.array_equal(got.data, data)
    assert got.gaps == ()


def test_missing_batches_and_acquisition_gaps_are_listed(tmp_path: Path):
    batches = make_batches(20, scans=100, rate_hz=1000.0)
    kept = [b for b in batches if b.sequence not in (5, 6)]
    restarted = make_batches(5, first_sequence=20, t0_ns=batches[-1].t0_ns + 5 * SEC, seed=9)
    s = write_session(tmp_path, kept + restarted, file_duration_s=10.0)
    got = fr.read_stream(s.dir, "wec/t8")
    missing, acquisition = got.gaps
    assert missing.kind == "missing"
    assert (missing.missing_batches, missing.first_missing_sequence) == (2, 5)
    assert missing.start_ns == batches[5].t0_ns
    assert missing.end_ns == batches[7].t0_ns
    assert acquisition.kind == "acquisition"
    assert acquisition.start_ns == batches[-1].t0_ns + 100 * 1_000_000
    assert acquisition.end_ns == restarted[0].t0_ns


def test_invalid_samples_are_nan_and_keep_their_codes(tmp_path: Path):
    batches = make_batches(4, scans=10)
    status = np.zeros((10, 3), dtype=np.uint8)
    status[3, 0] = SampleStatus.OPEN_CIRCUIT
    status[7, 2] = SampleStatus.COMM_ERROR
    flagged = Batch(1, batches[1].t0_ns, batches[1].period_ns, batches[1].data.copy(), status)
    # The value under a flag is a number here: the reader must not trust it.
    s = write_session(tmp_path, [batches[0], flagged, batches[2], batches[3]])
    got = fr.read_stream(s.dir, "wec/t8")
    assert got.status is not None
    assert got.status[13, 0] == SampleStatus.OPEN_CIRCUIT
    assert got.status[17, 2] == SampleStatus.COMM_ERROR
    assert np.isnan(got.data[13, 0])
    assert np.isnan(got.data[17, 2])
    assert np.count_nonzero(np.isnan(got.data)) == 2
    assert np.count_nonzero(got.status) == 2


def test_channels_are_chosen_by_name_in_the_order_asked(tmp_path: Path):
    batches = make_batches(5)
    s = write_session(tmp_path, batches)
    got = fr.read_stream(s.dir, "wec/t8", channels=["pitch", "heave"])
    _, data = _expected(batches)
    assert got.channels == ("pitch", "heave")
    assert got.units == ("deg", "m")
    assert np.array_equal(got.data, data[:, [2, 0]])
    one = fr.read_stream(s.dir, "wec/t8", channels="surge")
    assert one.data.shape == (500, 1)


def test_an_empty_window_still_names_its_channels(tmp_path: Path):
    s = write_session(tmp_path, make_batches(5))
    got = fr.read_stream(s.dir, "wec/t8", start=T0 + 100 * SEC, end=T0 + 101 * SEC)
    assert len(got) == 0
    assert got.data.shape == (0, 3)
    assert got.channels == CHANNELS
    assert got.to_pandas().empty


@pytest.mark.parametrize(
    ("kwargs", "error", "text"),
    [
        ({"stream": "wec/nope"}, fr.UnknownStream, "streams: wec/t8"),
        ({"stream": "wec/t8", "channels": ["heave", "yaw"]}, fr.UnknownChannel, "'yaw'"),
        ({"stream": "wec/t8", "start": "+2s", "end": "+1s"}, fr.BadWindow, "empty window"),
        ({"stream": "wec/t8", "start": "yesterday"}, fr.BadWindow, "not a time"),
        ({"stream": "wec/t8", "start": 1.5}, fr.BadWindow, "ambiguous"),
    ],
)
def test_bad_requests_fail_with_one_line(tmp_path: Path, kwargs, error, text):  # type: ignore[no-untyped-def]
    s = write_session(tmp_path, make_batches(3))
    with pytest.raises(error, match=text) as info:
        fr.read_stream(s.dir, **kwargs)
    assert "\n" not in str(info.value)


def test_a_missing_folder_and_unfinished_files_are_explained(tmp_path: Path):
    with pytest.raises(fr.NoRecording, match="no such file or folder"):
        fr.read_stream(tmp_path / "nope", "wec/t8")
    (tmp_path / "empty").mkdir()
    with pytest.raises(fr.NoRecording, match="no MCAP files"):
        fr.read_stream(tmp_path / "empty", "wec/t8")
    s = write_session(tmp_path / "rec", make_batches(20))
    last = s.files()[-1]
    last.rename(last.with_name(last.name + ACTIVE_SUFFIX))
    got = fr.read_stream(s.dir, "wec/t8")
    assert got.skipped == (last.with_name(last.name + ACTIVE_SUFFIX),)
    assert len(got.batches) == 10
    for f in s.files()[:-1]:
        f.unlink()
    with pytest.raises(fr.NoRecording, match="fleetdaq verify --recover"):
        fr.read_stream(s.dir, "wec/t8")


def test_a_file_cut_by_a_crash_and_recovered_is_still_found_by_a_window(tmp_path: Path):
    batches = make_batches(30, scans=100)
    s = write_session(tmp_path, batches[:20])  # two closed files, 0 s..2 s
    # The third file as a kill -9 leaves it: flushed, never closed (no summary, no index).
    cfg = RecorderConfig(file_duration_s=60, chunk_size=64 * 1024)
    crash = RecordingSession(tmp_path / "x", "demo", ["wec"], cfg, "site: demo\n", T0)
    enc = BatchEncoder("wec", "t8", CHANNELS, UNITS)
    for b in batches[20:]:
        payload = bytes(enc.encode(b.sequence, b.t0_ns, b.period_ns, b.data, b.clock))
        crash.write("/wec/t8", payload, b.t0_ns, b.t0_ns + 1)
    crash.flush()
    assert crash.current_file is not None
    active = s.dir / (f"{s.name}_0002.mcap" + ACTIVE_SUFFIX)
    active.write_bytes(crash.current_file.read_bytes())
    crash.close()
    report = recover_file(active)
    assert report.recovered_to is not None
    assert report.messages == 10
    rec = fr.open_recording(s.dir)
    assert [f.index is None for f in rec.files] == [False, False, True]
    got = rec.read("wec/t8", start=T0 + 2 * SEC + SEC // 2, end=T0 + 3 * SEC)
    t, data = _expected(batches)
    assert np.array_equal(got.data, data[(t >= T0 + 2.5 * SEC) & (t < T0 + 3 * SEC)])
    assert got.files == (report.recovered_to,)


def test_pandas_and_xarray_forms_carry_utc_time_and_units(tmp_path: Path):
    batches = make_batches(5, scans=20)
    s = write_session(tmp_path, batches)
    df = fr.read_dataframe(s.dir, "wec/t8")
    t, data = _expected(batches)
    assert str(df.index.tz) == "UTC"
    assert df.index.name == "time"
    assert list(df.columns) == list(CHANNELS)
    assert np.array_equal(df.index.asi8, t)
    assert np.array_equal(df.to_numpy(), data)
    assert df.attrs["units"] == dict(zip(CHANNELS, UNITS, strict=True))
    ds = fr.read_dataset(s.dir, "wec/t8", channels=["heave"])
    assert ds["heave"].attrs["units"] == "m"
    assert np.array_equal(ds["time"].values.astype(np.int64), t)
    assert ds.attrs["node"] == "wec"
    assert ds.attrs["stream"] == "t8"


def test_events_alarms_and_health_read_back_typed(tmp_path: Path):
    extra = [
        event_message(T0 + 100_000_000, "wec", 30, "spool_full", "spool is full"),
        event_message(T0 + 2 * SEC, "hub", 20, "recorded", "file closed"),
        alarm_message(T0 + SEC, "heave_high", "active_unacked", True),
        health_message(T0 + SEC // 2, "wec", -120),
        health_message(T0 + SEC + SEC // 2, "wec", 80),
        health_message(T0 + SEC, "hub", 0),
    ]
    s = write_session(tmp_path, make_batches(30), extra=extra)
    events = fr.read_events(s.dir)
    assert [(e.tag, e.node, e.level) for e in events] == [
        ("spool_full", "wec", 30),
        ("recorded", "hub", 20),
    ]
    assert fr.read_events(s.dir, start="+1s")[0].tag == "recorded"
    (alarm,) = fr.read_alarms(s.dir)
    assert (alarm.name, alarm.state, alarm.value) == ("heave_high", "active_unacked", 2.5)
    wec = fr.read_health(s.dir, "wec")
    assert [h.clock.offset_ns for h in wec] == [-120, 80]
    assert {h.node for h in fr.read_health(s.dir)} == {"wec", "hub"}


def test_an_unchunked_file_from_another_writer_reads_the_same(tmp_path: Path):
    batches = make_batches(6, scans=50)
    enc = BatchEncoder("wec", "t8", CHANNELS, UNITS)
    path = tmp_path / "other.mcap"
    with path.open("wb") as fh:
        w = Writer(fh, use_chunking=False)
        w.start(profile="ros2")
        sid = w.register_schema(SAMPLE_BATCH_TYPE, "ros2msg", SAMPLE_BATCH_SCHEMA.encode())
        cid = w.register_channel("/wec/t8", "cdr", sid)
        for b in batches:
            payload = bytes(enc.encode(b.sequence, b.t0_ns, b.period_ns, b.data, b.clock))
            w.add_message(cid, log_time=b.t0_ns, data=payload, publish_time=b.t0_ns)
        w.finish()
    got = fr.read_stream(path, "wec/t8", start=batches[2].t0_ns)
    t, data = _expected(batches[2:])
    assert np.array_equal(got.time_ns, t)
    assert np.array_equal(got.data, data)
    assert got.files == (path,)
