"""`fleetdaq verify`: sound files pass, damage is found, crash-cut files are rebuilt."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
from mcap.reader import make_reader
from rosbags.highlevel import AnyReader

from fleetdaq.contract.wire import BatchEncoder
from fleetdaq.hub.config.hub import RecorderConfig
from fleetdaq.hub.recording.session import ACTIVE_SUFFIX, RecordingSession
from fleetdaq.hub.recording.verify import check_file, recover_file, scan_active, verify_path
from fleetdaq.ptp.quality import UNSYNCED
from tests.procs import REPO

T0 = 1_795_000_000_000_000_000


def _session(tmp: Path, n: int, flush_every: int) -> tuple[RecordingSession, list[tuple[int, int]]]:
    """Write n batches with a flush every `flush_every`; return the session (file left open)
    and (file size, messages) right after each flush: what was durable then."""
    cfg = RecorderConfig(file_duration_s=3600, chunk_size=1 << 20)
    s = RecordingSession(tmp, "demo", ["wec"], cfg, "site: demo\n", T0)
    enc = BatchEncoder("wec", "t8", ("a", "b"), ("V", "V"))
    rng = np.random.default_rng(0)
    durable = []
    for i in range(n):
        p = bytes(enc.encode(i, T0 + i * 10**8, 1e6, rng.normal(size=(50, 2)), UNSYNCED))
        s.write("/wec/t8", p, T0 + i * 10**8, T0 + i * 10**8 + 1)
        if (i + 1) % flush_every == 0:
            s.flush()
            assert s.current_file is not None
            durable.append((s.current_file.stat().st_size, i + 1))
    return s, durable


def _sequences(path: Path) -> list[int]:
    with AnyReader([path]) as r:
        return [r.deserialize(raw, c.msgtype).sequence for c, _, raw in r.messages()]


def test_a_file_cut_anywhere_recovers_every_flushed_message(tmp_path: Path):
    s, durable = _session(tmp_path / "rec", 120, 10)
    active = s.current_file
    assert active is not None
    data = active.read_bytes()  # as a kill -9 leaves it: no summary, no footer
    sizes = [len(data), *list(range(len(data) - 1, 20, -(len(data) // 23)))]
    for i, cut in enumerate(sizes):
        case = tmp_path / f"cut{i}"
        case.mkdir()
        f = case / ("x.mcap" + ACTIVE_SUFFIX)
        f.write_bytes(data[:cut])
        report = recover_file(f)
        assert report.recovered_to is not None
        assert report.recovered_to.exists()
        assert not f.exists()
        assert (case / "x.mcap.damaged").exists()
        seqs = _sequences(report.recovered_to)
        assert seqs == list(range(len(seqs))), "a prefix of the stream, in order"
        assert report.messages == len(seqs)
        flushed = max((n for size, n in durable if size <= cut), default=0)
        assert len(seqs) >= flushed, (cut, len(seqs), flushed)
        assert 0 <= report.lost_bytes < cut
        if cut == len(data):
            assert seqs == list(range(120)), "nothing is lost from a file that was flushed"
            assert report.lost_bytes == 0
    s.close()


def test_a_cut_inside_a_chunk_reports_the_time_span_it_held(tmp_path: Path):
    s, _ = _session(tmp_path / "rec", 40, 10)
    active = s.current_file
    assert active is not None
    data = active.read_bytes()
    f = tmp_path / ("y.mcap" + ACTIVE_SUFFIX)
    f.write_bytes(data[: len(data) - 200])  # the last chunk loses its tail
    report = scan_active(f)
    assert report.messages == 30
    assert report.lost_bytes > 0
    assert report.lost_span_ns is not None
    start, end = report.lost_span_ns
    assert (start, end) == (T0 + 30 * 10**8 + 1, T0 + 39 * 10**8 + 1)
    assert "not recoverable" in report.line()
    s.close()


def test_a_flipped_byte_in_a_closed_file_fails_its_chunk_crc(tmp_path: Path):
    s, _ = _session(tmp_path / "rec", 30, 10)
    s.close()
    (f,) = s.files()
    assert check_file(f).status == "ok"
    with f.open("rb") as fh:
        summary = make_reader(fh).get_summary()
    assert summary is not None
    chunk = summary.chunk_indexes[1]
    data = bytearray(f.read_bytes())
    data[chunk.chunk_start_offset + chunk.chunk_length // 2] ^= 0x40  # inside the chunk
    f.write_bytes(bytes(data))
    report = check_file(f)
    assert report.status == "damaged", report.line()


def test_verify_cli_finds_and_recovers_a_crashed_session(tmp_path: Path):
    s, _ = _session(tmp_path / "rec", 25, 5)
    folder = s.dir
    active = s.current_file
    assert active is not None
    s.split()  # a first, closed file ...
    s2_payload_file = folder / ("late.mcap" + ACTIVE_SUFFIX)
    s2_payload_file.write_bytes(
        active.with_name(active.name.removesuffix(ACTIVE_SUFFIX)).read_bytes()[:-100]
    )  # ... and a second one cut by a crash

    def run(*args: str) -> subprocess.CompletedProcess[str]:
        return subprocess.run(
            [sys.executable, "-m", "fleetdaq", "verify", *args],
            cwd=REPO,
            capture_output=True,
            text=True,
            check=False,
            timeout=60,
        )

    r = run(str(folder))
    assert r.returncode == 1
    assert "unfinished" in r.stdout
    assert "--recover" in r.stderr
    r = run(str(folder), "--recover")
    assert r.returncode == 0, r.stdout + r.stderr
    assert "recovered" in r.stdout
    assert run(str(folder)).returncode == 0
    reports = verify_path(folder, recover=False)
    assert {p.path.name: p.status for p in reports} == {
        f"{s.name}_0000.mcap": "ok",
        "late.mcap": "ok",
        "late.mcap.damaged": "damaged original",  # listed, never silently ignored
    }
    recovered = next(r for r in reports if r.path.name == "late.mcap")
    with AnyReader([folder]) as reader:  # metadata.yaml now lists the recovered file too
        assert sum(1 for _ in reader.messages()) == 25 + recovered.messages
