"""The edge disk spool: kept until acked, bounded (what a limit drops is reported exactly, as
sequence ranges), crash-safe, sequences continue."""

from __future__ import annotations

import os
from pathlib import Path

from fleetdaq.edge.spool import HEADER_SIZE, StreamSpool

T0 = 1_795_000_000_000_000_000
SEC = 1_000_000_000


def _fill(sp: StreamSpool, first: int, n: int, size: int = 1000, dt: int = SEC // 10) -> None:
    for seq in range(first, first + n):
        assert not sp.append(seq, T0 + seq * dt, bytes([seq % 256]) * size)


def test_batches_read_back_in_order_until_acked(tmp_path: Path):
    sp = StreamSpool(tmp_path, max_bytes=10**9, max_age_s=3600, segment_bytes=5000)
    _fill(sp, 0, 20)
    got = list(sp.read_from(5, 12))
    assert [s for s, _, _ in got] == list(range(5, 13))
    assert got[0][2] == bytes([5]) * 1000
    assert got[0][1] == T0 + 5 * SEC // 10
    assert sp.floor == 0
    sp.ack(11)
    assert sp.floor == 12
    assert next(s for s, _, _ in sp.read_from(0, 100)) <= 12  # segments go whole
    # Segments wholly acked are gone from disk.
    first_seqs = sorted(int(p.stem) for p in tmp_path.glob("*.seg"))
    assert first_seqs[0] > 5
    sp.close()


def test_sequences_continue_after_reopen(tmp_path: Path):
    sp = StreamSpool(tmp_path, 10**9, 3600)
    _fill(sp, 0, 7)
    sp.ack(3)
    sp.close()
    again = StreamSpool(tmp_path, 10**9, 3600)
    assert again.recovery.clean
    assert again.next_sequence == 7
    assert again.acked == 3
    assert [s for s, _, _ in again.read_from(again.floor, 100)] == [4, 5, 6]
    again.close()


def test_a_crash_is_detected_and_a_torn_record_is_cut(tmp_path: Path):
    sp = StreamSpool(tmp_path, 10**9, 3600)
    _fill(sp, 0, 5)
    sp.sync()
    # kill -9 mid-write: no close(), and half a record at the end of the segment.
    (seg,) = list(tmp_path.glob("*.seg"))
    with seg.open("ab") as fh:
        fh.write(b"FDQ1" + b"\x00" * 10)
    reopened = StreamSpool(tmp_path, 10**9, 3600)
    assert not reopened.recovery.clean
    assert reopened.recovery.torn_bytes == 14
    assert reopened.recovery.last_seq == 4
    assert reopened.next_sequence == 5
    assert [s for s, _, _ in reopened.read_from(0, 10)] == [0, 1, 2, 3, 4]
    reopened.close()


def test_a_corrupted_record_ends_the_segment_not_the_spool(tmp_path: Path):
    sp = StreamSpool(tmp_path, 10**9, 3600)
    _fill(sp, 0, 4, size=100)
    sp.close()
    (seg,) = list(tmp_path.glob("*.seg"))
    data = bytearray(seg.read_bytes())
    data[2 * (HEADER_SIZE + 100) + HEADER_SIZE + 5] ^= 0xFF  # flip a payload byte of seq 2
    seg.write_bytes(bytes(data))
    reopened = StreamSpool(tmp_path, 10**9, 3600)
    assert [s for s, _, _ in reopened.read_from(0, 10)] == [0, 1]
    assert reopened.next_sequence == 2
    reopened.close()


def test_spool_full_drops_oldest_unacked_and_says_exactly_what(tmp_path: Path):
    sp = StreamSpool(
        tmp_path,
        max_bytes=10 * (HEADER_SIZE + 1000),
        max_age_s=3600,
        segment_bytes=3 * (HEADER_SIZE + 1000),
    )
    dropped = []
    for seq in range(30):
        dropped += sp.append(seq, T0 + seq, b"x" * 1000)
    assert dropped, "the byte limit must drop something"
    lost = [s for d in dropped for s in range(d.first_seq, d.last_seq + 1)]
    assert lost == list(range(len(lost))), "oldest first, contiguous"
    assert sum(d.batches for d in dropped) == len(lost) == sp.dropped_batches
    kept = [s for s, _, _ in sp.read_from(0, 100)]
    assert kept == list(range(len(lost), 30)), "everything not reported dropped is still there"
    assert sp.floor == len(lost)
    assert sp.bytes <= 10 * (HEADER_SIZE + 1000) + 3 * (HEADER_SIZE + 1000)
    sp.close()


def test_spool_drops_by_age(tmp_path: Path):
    sp = StreamSpool(tmp_path, max_bytes=10**9, max_age_s=5, segment_bytes=5 * 1028)
    dropped = []
    for seq in range(100):  # 10 s at 10 Hz
        dropped += sp.append(seq, T0 + seq * SEC // 10, b"y" * 1000)
    assert dropped
    oldest = sp.oldest_unacked_time_ns()
    assert oldest is not None
    assert T0 + 99 * SEC // 10 - oldest <= 6 * SEC
    sp.close()


def test_acked_batches_are_not_counted_as_dropped(tmp_path: Path):
    sp = StreamSpool(tmp_path, max_bytes=8 * 1028, max_age_s=3600, segment_bytes=2 * 1028)
    for seq in range(6):
        sp.append(seq, T0 + seq, b"z" * 1000)
    sp.ack(5)
    dropped = []
    for seq in range(6, 12):
        dropped += sp.append(seq, T0 + seq, b"z" * 1000)
    assert dropped == []
    assert sp.dropped_batches == 0
    sp.close()


def test_files_on_disk_are_append_only_segments(tmp_path: Path):
    sp = StreamSpool(tmp_path, 10**9, 3600, segment_bytes=2000)
    _fill(sp, 0, 6)
    sp.close()
    names = sorted(p.name for p in tmp_path.glob("*.seg"))
    assert names == [f"{s:020d}.seg" for s in (0, 2, 4)]
    assert all(os.path.getsize(tmp_path / n) == 2 * (HEADER_SIZE + 1000) for n in names)


def test_a_partly_acked_segment_that_is_dropped_reports_only_its_unacked_batches(tmp_path: Path):
    record = HEADER_SIZE + 1000
    sp = StreamSpool(tmp_path, max_bytes=6 * record, max_age_s=3600, segment_bytes=4 * record)
    for seq in range(4):  # one segment: 0..3
        assert not sp.append(seq, T0 + seq, b"a" * 1000)
    sp.ack(1)  # the hub has 0 and 1; the segment stays (2 and 3 are not acked)
    dropped = []
    for seq in range(4, 8):  # a second segment pushes the spool past 6 records
        dropped += sp.append(seq, T0 + seq, b"a" * 1000)
    assert [(d.first_seq, d.last_seq, d.batches) for d in dropped] == [(2, 3, 2)]
    assert "over" in dropped[0].reason
    assert sp.dropped_batches == 2
    assert sp.floor == 4
    assert [s for s, _, _ in sp.read_from(0, 100)] == [4, 5, 6, 7]
    sp.close()


def test_age_drops_say_exactly_what_and_why(tmp_path: Path):
    sp = StreamSpool(tmp_path, max_bytes=10**9, max_age_s=5, segment_bytes=5 * (HEADER_SIZE + 100))
    dropped = []
    for seq in range(100):  # 10 s at 10 Hz
        dropped += sp.append(seq, T0 + seq * SEC // 10, b"y" * 100)
    ranges = [(d.first_seq, d.last_seq) for d in dropped]
    assert ranges == [(a, a + 4) for a in range(0, 5 * len(ranges), 5)], "whole segments, in order"
    assert all("older than 5 s" in d.reason for d in dropped)
    kept = [s for s, _, _ in sp.read_from(0, 100)]
    assert kept == list(range(5 * len(ranges), 100)), "everything not reported is still there"
    # Segments go whole: the oldest one kept still has its newest batch within the limit.
    assert T0 + 99 * SEC // 10 - (T0 + kept[4] * SEC // 10) <= 5 * SEC
    sp.close()


def test_a_spool_keeps_its_epoch_and_a_new_or_wiped_one_draws_another(tmp_path: Path):
    sp = StreamSpool(tmp_path / "s", 10**9, 3600)
    first = sp.epoch
    assert first > 0
    _fill(sp, 0, 5)
    sp.close()
    again = StreamSpool(tmp_path / "s", 10**9, 3600)
    assert again.epoch == first, "the numbering goes on: so does the epoch"
    assert again.ack(2, first)
    assert not again.ack(4, first + 1), "an ack for another spool's numbering"
    assert again.acked == 2
    assert again.acks_refused == 1
    again.close()
    for p in (tmp_path / "s").iterdir():  # wiped: numbering starts at 0 again
        p.unlink()
    wiped = StreamSpool(tmp_path / "s", 10**9, 3600)
    assert wiped.next_sequence == 0
    assert wiped.epoch != first
    wiped.close()
    # A spool written before epochs (no epoch file) goes on numbering under a new one.
    old = StreamSpool(tmp_path / "old", 10**9, 3600)
    _fill(old, 0, 3)
    old.close()
    (tmp_path / "old" / "epoch").unlink()
    reopened = StreamSpool(tmp_path / "old", 10**9, 3600)
    assert reopened.next_sequence == 3
    assert reopened.epoch > 0
    reopened.close()
    last = StreamSpool(tmp_path / "old", 10**9, 3600)
    assert last.epoch == reopened.epoch
    last.close()
