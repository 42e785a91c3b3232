"""Nothing lost: real hub and edge processes through crashes, outages, a full disk and garbage.

Each test runs a hub and an edge as separate OS processes on loopback (the edge spools to
disk and replays from the hub's last ack), breaks something for real (kill -9, SIGTERM and a
long wait, a disk that refuses writes, 10 000 malformed payloads), and then reads every
recorded file back with rosbags to check which sequence numbers made it. Tests wait on what the
processes say (the hub's status request, acks, the spool on disk), never on a guess of how long
start-up takes.
"""

from __future__ import annotations

import datetime as dt
import errno
import json
import logging
import queue
import re
import resource
import shutil
import signal
import subprocess
import threading
import time
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from rosbags.highlevel import AnyReader

from fleetdaq.contract.cdr import decode
from fleetdaq.contract.messages import NodeHealth
from fleetdaq.hub.recording.verify import verify_path
from tests.procs import (
    HubClient,
    Proc,
    free_port,
    sessions,
    spooled,
    stream_view,
    wait_for_port,
    wait_until,
)

SITE = """\
site: deliv
hub:
  listen: [tcp/127.0.0.1:{port}]
  recorder: {{file_duration_s: {split}, flush_interval_s: 0.5}}
nodes:
  wec:
    spool: {{replay_after_s: 2, fsync_interval_s: 0.5}}
    streams:
      t8:
        driver: wave_sim          # 8 x 10 kS/s, 100 ms batches
        rate_hz: 10000
        channels:
          - {{name: c0, unit: V}}
          - {{name: c1, unit: V}}
          - {{name: c2, unit: V}}
          - {{name: c3, unit: V}}
          - {{name: c4, unit: V}}
          - {{name: c5, unit: V}}
          - {{name: c6, unit: V}}
          - {{name: c7, unit: V}}
"""


@dataclass
class Rig:
    tmp: Path
    port: int
    data: Path
    cfg: Path
    procs: list[Proc] = field(default_factory=list)
    hubs: int = 0
    _client: HubClient | None = None

    def hub(self, relay_output: bool = False) -> Proc:
        """Start a hub and return once it answers its status request (it starts that last)."""
        self.hubs += 1
        p = Proc(
            [
                "hub",
                "--config",
                str(self.cfg),
                "--data",
                str(self.data),
                "--summary",
                str(self.tmp / f"summary{self.hubs}.json"),
            ],
            self.tmp / f"hub{self.hubs}.log",
            relay_output=relay_output,
        )
        self.procs.append(p)
        wait_for_port(self.port, 60)
        wait_until(self.status, 60, "the hub to answer its status request")
        return p

    def edge(self, name: str = "edge") -> Proc:
        p = Proc(
            [
                "edge",
                "--config",
                str(self.cfg),
                "--node",
                "wec",
                "--spool",
                str(self.tmp / "spool"),
            ],
            self.tmp / f"{name}.log",
        )
        self.procs.append(p)
        return p

    @property
    def client(self) -> HubClient:
        if self._client is None:
            self._client = HubClient(self.port, "deliv")
        return self._client

    def status(self) -> dict[str, Any] | None:
        return self.client.status()

    def t8(self) -> dict[str, Any]:
        """The hub's accounting of the stream right now."""
        status = self.status()
        assert status is not None, "the hub does not answer"
        view = stream_view(status, "wec", "t8")
        assert view is not None
        return view

    def spool_dir(self) -> Path:
        return self.tmp / "spool" / "wec" / "t8"

    def acked(self) -> int:
        f = self.tmp / "spool" / "wec" / "t8" / "acked"
        try:
            return int(f.read_text())
        except (FileNotFoundError, ValueError):
            return -1

    def health(self, timeout: float = 10.0) -> NodeHealth:
        """The edge's next health message (published ~1 Hz on its health key)."""
        import zenoh

        from fleetdaq.contract.keys import SiteKeys
        from fleetdaq.runtime.zenoh_session import client_config

        got: queue.Queue[bytes] = queue.Queue()
        session = zenoh.open(client_config([f"tcp/127.0.0.1:{self.port}"]))
        sub = session.declare_subscriber(
            SiteKeys("deliv").health("wec"), lambda s: got.put(s.payload.to_bytes())
        )
        try:
            return decode(got.get(timeout=timeout), NodeHealth)
        finally:
            sub.undeclare()
            session.close()

    def caught_up(self, within: int = 30) -> bool:
        """The hub has acked everything but the last `within` batches the edge acquired."""
        t8 = self.health().stream("t8")
        assert t8 is not None
        return t8.spool_acked >= t8.next_sequence - within

    def spooled(self) -> list[int]:
        """Sequences still in the (stopped) edge's spool: not lost, delivered on next contact."""
        from fleetdaq.edge.spool import StreamSpool

        sp = StreamSpool(self.tmp / "spool" / "wec" / "t8", 10**12, 10**9)
        try:
            return [seq for seq, _, _ in sp.read_from(sp.acked + 1, 2**62)]
        finally:
            sp.close()

    def summary(self, n: int) -> dict[str, object]:
        out: dict[str, object] = json.loads((self.tmp / f"summary{n}.json").read_text())
        return out

    def sequences(self) -> list[int]:
        """Every recorded t8 sequence number, over every file of every session."""
        files = sorted(self.data.glob("*/*.mcap"))
        assert files, "no recording"
        seqs: list[int] = []
        with AnyReader(files) as reader:
            conns = [c for c in reader.connections if c.topic == "/wec/t8"]
            for c, _, raw in reader.messages(conns):
                seqs.append(reader.deserialize(raw, c.msgtype).sequence)
        return seqs

    def recorded_events(self) -> list[Any]:
        """Every recorded event as decoded from the recording (its fields included)."""
        files = sorted(self.data.glob("*/*.mcap"))
        with AnyReader(files) as reader:
            conns = [c for c in reader.connections if c.topic == "/events"]
            return [reader.deserialize(raw, c.msgtype) for c, _, raw in reader.messages(conns)]

    def first_after_time_jump(self, at_least_s: float = 1.0) -> int:
        """The recorded t8 batch whose first sample comes `at_least_s` or more after where the
        batch before it ended (its own times, not when it arrived)."""
        files = sorted(self.data.glob("*/*.mcap"))
        spans: dict[int, tuple[int, int]] = {}
        with AnyReader(files) as reader:
            conns = [c for c in reader.connections if c.topic == "/wec/t8"]
            for c, _, raw in reader.messages(conns):
                m = reader.deserialize(raw, c.msgtype)
                start = int(m.first_sample_time_ns)
                spans[int(m.sequence)] = (start, start + round(m.scan_count * m.sample_period_ns))
        jumps = [
            seq
            for seq, (start, _) in spans.items()
            if seq - 1 in spans and start - spans[seq - 1][1] >= at_least_s * 1e9
        ]
        assert len(jumps) == 1, jumps
        return jumps[0]

    def events(self) -> list[tuple[str, str, str]]:
        """(node, tag, message) of every recorded event."""
        return [(node, tag, message) for _, node, tag, message in self.timed_events()]

    def leveled_events(self) -> list[tuple[str, str, str]]:
        """(level name, node, tag) of every recorded event."""
        return [
            (logging.getLevelName(m.level).lower(), m.node, m.tag) for m in self.recorded_events()
        ]

    def timed_events(self) -> list[tuple[int, str, str, str]]:
        """(time ns, node, tag, message) of every recorded event, in time order."""
        return sorted((m.time_ns, m.node, m.tag, m.message) for m in self.recorded_events())


@pytest.fixture
def rig(tmp_path: Path, request: pytest.FixtureRequest) -> Iterator[Rig]:
    port = free_port()
    split = getattr(request, "param", 5)
    cfg = tmp_path / "site.yaml"
    cfg.write_text(SITE.format(port=port, split=split))
    r = Rig(tmp_path, port, tmp_path / "data", cfg)
    try:
        yield r
    finally:
        for p in r.procs:
            p.kill()
        if r._client is not None:
            r._client.close()


def _complete(seqs: list[int]) -> tuple[int, list[int]]:
    """(highest, missing) of a set of sequences that should be 0..highest."""
    have = set(seqs)
    top = max(have)
    return top, sorted(set(range(top + 1)) - have)


def _nothing_lost(rig: Rig) -> int:
    """Everything the edge acquired is in the recording or still in its spool (0 lost), and
    the spool holds only the last moments. Returns the highest recorded sequence."""
    recorded = rig.sequences()
    spooled = rig.spooled()
    top, missing = _complete(recorded + spooled)
    assert missing == [], f"lost {len(missing)} of {top + 1}: {missing[:20]}"
    assert len(spooled) <= 40, f"{len(spooled)} batches were never delivered"
    return max(recorded)


def test_kill_9_of_the_hub_loses_nothing(rig: Rig):
    hub = rig.hub()
    edge = rig.edge()
    wait_until(lambda: rig.acked() >= 20, 60, "acks from the first hub")
    # Kill it mid-recording: with a file open (.active) and batches received but not acked.
    rig.client.wait(
        lambda s: (
            s["recorder"]["current_file"]
            and (t8 := stream_view(s, "wec", "t8"))
            and t8["last_sequence"] > t8["acked"]
        ),
        30,
        "received batches not acked yet",
    )
    hub.popen.send_signal(signal.SIGKILL)
    hub.popen.wait()
    acked_at_kill = rig.acked()
    # The edge keeps acquiring into its spool while no hub runs.
    wait_until(
        lambda: max((seq for seq, _ in spooled(rig.spool_dir())), default=-1) >= acked_at_kill + 30,
        30,
        "the edge to spool 30 batches past the last ack",
    )
    hub2 = rig.hub()
    wait_until(lambda: rig.acked() >= acked_at_kill + 80, 40, "the backlog to be acked")
    wait_until(rig.caught_up, 30, "the hub to catch up with the live edge")
    assert edge.terminate() == 0
    assert hub2.terminate() == 0
    # The second hub recovered the first one's crash-cut file at start.
    assert not list(rig.data.glob("*/*.mcap.active"))
    assert list(rig.data.glob("*/*.mcap.damaged"))
    assert _nothing_lost(rig) >= acked_at_kill + 80
    s = rig.summary(2)["streams"]["wec/t8"]  # type: ignore[index]
    assert s["lost"] == 0, s  # holes still "missing" at exit are in the spool (checked above)
    assert s["late"] > 0, "the gap was filled by replay"
    assert any(tag == "recovered" for _, tag, _ in rig.events())


def test_hub_down_for_60_s_loses_nothing_and_the_backlog_drains(rig: Rig):
    hub = rig.hub()
    edge = rig.edge()
    wait_until(lambda: rig.acked() >= 10, 30, "first acks")
    assert hub.terminate() == 0
    down_from = rig.acked()
    time.sleep(60.0)  # 600 batches (38 MB) pile up in the edge's spool
    spool = rig.tmp / "spool" / "wec" / "t8"
    backlog = sum(f.stat().st_size for f in spool.glob("*.seg"))
    assert backlog > 30e6, backlog
    t_back = time.monotonic()
    hub2 = rig.hub()
    wait_until(lambda: rig.acked() >= down_from + 600, 60, "the backlog to be acked")
    drain_s = time.monotonic() - t_back
    wait_until(rig.caught_up, 30, "the hub to catch up with the live edge")
    assert edge.terminate() == 0
    assert hub2.terminate() == 0
    assert _nothing_lost(rig) >= down_from + 600
    after = sum(f.stat().st_size for f in spool.glob("*.seg"))
    assert after < 20e6, f"spool still holds {after} bytes after draining in {drain_s:.1f} s"


def test_kill_9_of_an_edge_loses_a_bounded_reported_stretch(rig: Rig):
    hub = rig.hub()
    edge = rig.edge("edge1")
    wait_until(lambda: rig.acked() >= 20, 30, "acks")
    edge.popen.send_signal(signal.SIGKILL)
    edge.popen.wait()
    killed_at = time.time()
    time.sleep(2.0)
    edge2 = rig.edge("edge2")  # after 2 s down: the stretch the hub must report
    restarted_at = time.time()
    wait_until(lambda: rig.acked() >= 60, 30, "acks from the restarted edge")
    wait_until(rig.caught_up, 30, "the hub to catch up with the live edge")
    assert edge2.terminate() == 0
    assert hub.terminate() == 0
    _nothing_lost(rig)  # sequence numbers continue across the crash: none is skipped
    s = rig.summary(1)["streams"]["wec/t8"]  # type: ignore[index]
    assert s["acquisition_gaps"] == 1, s
    # The stretch without scans is bounded by the time the edge was down (plus start-up).
    down = restarted_at - killed_at
    assert down <= s["acquisition_gap_s"] <= down + 5.0, (down, s["acquisition_gap_s"])
    tags = [(node, tag) for node, tag, _ in rig.events()]
    assert ("wec", "unclean_stop") in tags
    # The event names, as a field a tool can match against the edge's own events (a
    # `time_restart` at the same sequence would mean the clock moved, not lost scans), the
    # first batch after the stretch: where the recorded batches' own times jump.
    (gap,) = [e for e in rig.recorded_events() if e.tag == "acquisition_gap"]
    fields = {kv.key: kv.value for kv in gap.fields}
    assert fields["sequence"] == str(rig.first_after_time_jump()), fields


EVENT_LINE = re.compile(r"fleetdaq\.events: (\S+) +[A-Z]+ +\S+ \[(\w+)\]")


def logged_event_times(log: str, tag: str) -> list[int]:
    """When each event `tag` was raised, as a process logged it (ns, millisecond precision)."""
    return [
        int(dt.datetime.fromisoformat(when).timestamp() * 1000) * 1_000_000
        for when, t in EVENT_LINE.findall(log)
        if t == tag
    ]


class FullDisk:
    """Makes the hub's disk refuse writes (`fill`) and accept them again (`free`)."""

    def fill(self, hub: Proc) -> None:
        raise NotImplementedError

    def free(self, hub: Proc) -> None:
        raise NotImplementedError

    def close(self) -> None:
        """Undo whatever `fill` left."""


class FileSizeLimit(FullDisk):
    """RLIMIT_FSIZE 0 on the running hub, set from here (prlimit, no root needed): every write
    of the hub process to a file fails with EFBIG as it would with ENOSPC on a full disk, its
    logs included (they go through a pipe, see `Proc(relay_output=True)`); lifting the limit is
    the space coming back."""

    def __init__(self) -> None:
        self._soft: dict[int, int] = {}

    def fill(self, hub: Proc) -> None:
        pid = hub.popen.pid
        # Writing past RLIMIT_FSIZE also sends SIGXFSZ, which kills a process that does not
        # ignore it; Python ignores it at start-up (writes then raise OSError(EFBIG)).
        ignored = Path(f"/proc/{pid}/status").read_text().split("SigIgn:")[1].split()[0]
        assert int(ignored, 16) & (1 << (signal.SIGXFSZ - 1)), "the hub would die of SIGXFSZ"
        soft, hard = resource.prlimit(pid, resource.RLIMIT_FSIZE)
        self._soft[pid] = soft
        resource.prlimit(pid, resource.RLIMIT_FSIZE, (0, hard))

    def free(self, hub: Proc) -> None:
        pid = hub.popen.pid
        _, hard = resource.prlimit(pid, resource.RLIMIT_FSIZE)
        resource.prlimit(pid, resource.RLIMIT_FSIZE, (self._soft.pop(pid), hard))


class SmallTmpfs(FullDisk):
    """The recording on a tmpfs of its own that a file of ours fills to the last byte: a real
    ENOSPC. Mounting needs root; elsewhere `FileSizeLimit` shows the same guarantee."""

    def __init__(self, mnt: Path) -> None:
        self.mnt = mnt
        self.filler = mnt / "filler"
        mnt.mkdir()
        r = subprocess.run(
            ["mount", "-t", "tmpfs", "-o", "size=64m", "tmpfs", str(mnt)],
            capture_output=True,
            text=True,
            check=False,
        )
        if r.returncode != 0:
            pytest.skip(f"cannot mount a tmpfs here (needs root): {r.stderr.strip()}")

    def fill(self, hub: Proc) -> None:
        block = b"\x00" * (1 << 20)
        with self.filler.open("wb", buffering=0) as fh:
            while _written(fh, block):
                pass
        # Kept full until `free`: a page the hub itself frees meanwhile (a file it replaces or
        # truncates) is taken back within 20 ms, so its next retry, 2 s on, meets a full disk.
        self._stop = threading.Event()
        self._keeper = threading.Thread(target=self._keep_full, daemon=True)
        self._keeper.start()

    def _keep_full(self) -> None:
        page = b"\x00" * 4096
        with self.filler.open("ab", buffering=0) as fh:
            while not self._stop.wait(0.02):
                while _written(fh, page):
                    pass

    def free(self, hub: Proc) -> None:
        self._stop.set()
        self._keeper.join(5)
        self.filler.unlink()

    def close(self) -> None:
        if hasattr(self, "_stop"):
            self._stop.set()
            self._keeper.join(5)
        subprocess.run(["umount", "-l", str(self.mnt)], check=False, capture_output=True)


def _written(fh: Any, data: bytes) -> bool:
    """Write what fits; False once the disk is full."""
    try:
        fh.write(data)
    except OSError as err:
        if err.errno != errno.ENOSPC:
            raise
        return False
    return True


@pytest.fixture(params=["file_size_limit", "tmpfs"])
def full_disk(request: pytest.FixtureRequest, rig: Rig) -> Iterator[FullDisk]:
    disk: FullDisk
    if request.param == "tmpfs":
        disk = SmallTmpfs(rig.tmp / "disk")
        rig.data = disk.mnt / "data"
    else:
        disk = FileSizeLimit()
    try:
        yield disk
    finally:
        for p in rig.procs:  # nothing of ours may keep the mount busy
            p.kill()
        disk.close()


@pytest.mark.parametrize("rig", [600], indirect=True)
def test_a_full_hub_disk_is_an_event_and_recording_resumes_when_space_returns(
    rig: Rig, full_disk: FullDisk
):
    hub = rig.hub(relay_output=True)
    edge = rig.edge()
    wait_until(lambda: rig.acked() >= 20, 60, "acks")
    full_disk.fill(hub)
    rig.client.wait(lambda s: s["recorder"]["write_errors"] >= 1, 30, "a refused write")
    acked_when_full = rig.acked()
    # The recorder retries every 2 s: wait for a retry to be refused too.
    rig.client.wait(lambda s: s["recorder"]["write_errors"] >= 2, 30, "a refused retry")
    assert rig.acked() == acked_when_full, "nothing is acked while nothing can be written"
    deferred = rig.t8()["deferred"]
    assert deferred > 0, "batches received while the disk refused are counted"
    assert hub.popen.poll() is None, "the hub must not crash"
    assert edge.popen.poll() is None
    freed_ns = time.time_ns()
    full_disk.free(hub)  # space returns
    wait_until(lambda: rig.acked() >= acked_when_full + 50, 60, "recording to resume")
    wait_until(rig.caught_up, 30, "the hub to catch up with the live edge")
    assert edge.terminate() == 0
    assert hub.terminate() == 0
    summary = rig.summary(1)
    assert summary["write_errors"] >= 2  # type: ignore[operator]
    assert summary["streams"]["wec/t8"]["deferred"] >= deferred  # type: ignore[index]
    abandoned = [Path(f) for f in summary["abandoned_files"]]  # type: ignore[attr-defined]
    assert abandoned, "the file being written when the disk filled was abandoned"
    assert all(f.name.endswith(".mcap.active") for f in abandoned)
    # What the abandoned files hold is recoverable; with them, nothing is lost.
    reports = verify_path(sessions(rig.data)[0], recover=True)
    assert {r.status for r in reports} <= {"ok", "recovered"}, [r.line() for r in reports]
    assert sum(r.status == "recovered" for r in reports) == len(abandoned)
    _nothing_lost(rig)
    events = rig.timed_events()
    tags = [tag for _, _, tag, _ in events]
    assert "disk_full" in tags
    assert "write_resumed" in tags
    # `write_resumed` means writing really works again: it comes after the space returned. And
    # the events raised while the disk refused are "written then": the recording has them all.
    mismatches = []
    # (From the hub's log: a write_resumed raised too early may be missing from the recording.)
    resumed = logged_event_times(hub.output(), "write_resumed")
    premature = [t for t in resumed if t < freed_ns - 1_000_000]  # logged to the millisecond
    if premature:
        mismatches.append(f"write_resumed raised {len(premature)}x while the disk was still full")
    raised = rig.summary(1)["events"]  # counts by level of every event the hub handled
    recorded = Counter(level for level, *_ in rig.leveled_events())
    if recorded != Counter(raised):  # type: ignore[arg-type]
        mismatches.append(f"events raised {raised}, recorded {dict(recorded)}")
    assert not mismatches, "; ".join(mismatches)


def test_ten_thousand_malformed_payloads_are_counted_and_good_data_flows(rig: Rig):
    import zenoh

    from fleetdaq.contract.keys import SiteKeys
    from fleetdaq.contract.wire import BatchEncoder
    from fleetdaq.ptp.quality import UNSYNCED
    from fleetdaq.runtime.zenoh_session import client_config

    hub = rig.hub()
    edge = rig.edge()
    wait_until(lambda: rig.acked() >= 10, 30, "acks")
    rng = np.random.default_rng(11)
    # A well-formed batch that claims to be a stream neither key names: however it is mangled,
    # no payload below can pass as a real batch.
    good = bytes(
        BatchEncoder("liar", "y", ("a",), ("V",)).encode(
            0, 1, 1.0, rng.normal(size=(50, 1)), UNSYNCED
        )
    )
    session = zenoh.open(client_config([f"tcp/127.0.0.1:{rig.port}"]))
    try:
        keys = [SiteKeys("deliv").data("evil", "x"), SiteKeys("deliv").data("wec", "t8")]
        for i in range(10_000):
            kind = i % 4
            if kind == 0:
                bad = rng.bytes(int(rng.integers(0, 600)))  # random bytes
            elif kind == 1:
                bad = good[: int(rng.integers(0, len(good)))]  # truncated CDR
            elif kind == 2:  # a lying length in the middle
                arr = bytearray(good)
                pos = int(rng.integers(4, len(arr) - 4))
                arr[pos : pos + 4] = int(rng.integers(2**31, 2**32)).to_bytes(4, "little")
                bad = bytes(arr)
            else:  # a huge claimed array
                arr = bytearray(good)
                arr[-8 * 50 - 8 : -8 * 50 - 4] = (0x7FFFFFFF).to_bytes(4, "little")
                bad = bytes(arr)
            # BLOCK: this sender must deliver all 10 000 (Zenoh's default for put is DROP).
            session.put(keys[i % 2], bad, congestion_control=zenoh.CongestionControl.BLOCK)
    finally:
        session.close()
    n_before = rig.acked()
    wait_until(lambda: rig.acked() >= n_before + 20, 30, "good data to keep flowing")
    wait_until(rig.caught_up, 30, "the hub to catch up with the live edge")
    assert edge.terminate() == 0
    assert hub.terminate() == 0
    summary = rig.summary(1)
    # Half went to a stream the site file does not define: refused at the subscriber, never
    # decoded; half to the real stream's key: decoded, found malformed, never written.
    assert summary["refused"] == 5_000, summary["refused"]
    assert summary["malformed"] == 5_000, summary["malformed"]
    _nothing_lost(rig)
    assert set(summary["streams"]) == {"wec/t8"}  # type: ignore[arg-type]


def test_an_edge_that_boots_before_its_hub_spools_from_the_first_scan(rig: Rig):
    edge = rig.edge()
    # The link is down at boot: acquisition must not wait for it.
    wait_until(lambda: len(spooled(rig.spool_dir())) >= 30, 60, "30 batches in the spool")
    hub = rig.hub()
    wait_until(lambda: rig.acked() >= 60, 40, "the spooled start to be acked")
    wait_until(rig.caught_up, 30, "the hub to catch up with the live edge")
    assert edge.terminate() == 0
    assert hub.terminate() == 0
    _nothing_lost(rig)
    assert min(rig.sequences()) == 0, "the first batch of the run is recorded"


def test_an_edge_without_any_hub_still_stops_cleanly_and_quickly(rig: Rig):
    edge = rig.edge()
    wait_until(lambda: len(spooled(rig.spool_dir())) >= 20, 60, "20 batches in the spool")
    t = time.monotonic()
    assert edge.terminate(timeout=10) == 0
    assert time.monotonic() - t < 8
    # Acquisition started at once when the spool opened, hub or not: an edge that waited for
    # a hub subscription would have started 3 s later.
    opened_ns = rig.spool_dir().stat().st_ctime_ns
    first_ns = min(t_ns for _, t_ns in spooled(rig.spool_dir()))
    assert (first_ns - opened_ns) / 1e9 < 2.0
    assert len(rig.spooled()) >= 20, "what it acquired meanwhile is in the spool"


def test_a_wiped_edge_spool_numbers_again_from_0_and_the_hub_records_it_all(rig: Rig):
    """A new SD card, or a spool deleted by hand, while the hub runs on: the edge numbers its
    batches from 0 again. They are new batches, not replays of the ones the hub has: every
    one is recorded and only then acked (before spool epochs the hub took them for
    duplicates, recorded none, and in time acked them away)."""
    from fleetdaq.edge.spool import StreamSpool

    hub = rig.hub()
    edge = rig.edge("edge1")
    wait_until(lambda: rig.acked() >= 30, 60, "acks of the first spool")
    assert edge.terminate() == 0
    wiped_ns = time.time_ns()
    shutil.rmtree(rig.spool_dir())
    edge2 = rig.edge("edge2")
    wait_until(lambda: rig.acked() >= 40, 60, "acks of the new spool")
    wait_until(rig.caught_up, 30, "the hub to catch up with the new spool")
    assert edge2.terminate() == 0
    assert hub.terminate() == 0
    sp = StreamSpool(rig.spool_dir(), 10**12, 10**9)
    try:
        new_top = sp.next_sequence - 1
    finally:
        sp.close()
    before: list[int] = []
    after: list[int] = []
    with AnyReader(sorted(rig.data.glob("*/*.mcap"))) as reader:
        conns = [c for c in reader.connections if c.topic == "/wec/t8"]
        for c, t_ns, raw in reader.messages(conns):
            seq = reader.deserialize(raw, c.msgtype).sequence
            (after if t_ns > wiped_ns else before).append(seq)
    top, missing = _complete(before)
    assert top >= 30
    assert missing == []
    spooled = rig.spooled()  # the last few, recorded or not: sent again on the next contact
    assert sorted(set(after + spooled)) == list(range(new_top + 1)), "the new spool, all of it"
    assert len(after) == len(set(after)), "each recorded once"
    assert len(spooled) <= 40
    s = rig.summary(1)["streams"]["wec/t8"]  # type: ignore[index]
    assert s["spool_restarts"] == 1, s
    assert s["duplicates"] == 0, s
    assert ("hub", "spool_restarted") in [(node, tag) for node, tag, _ in rig.events()]


@pytest.mark.parametrize("rig", [600], indirect=True)
def test_after_a_full_disk_the_held_events_are_written_even_with_every_edge_down(
    rig: Rig, full_disk: FullDisk
):
    """The disk fills, the only edge stops, the space returns: no batch comes to open a file,
    yet writing resumes and the events raised meanwhile go into the recording."""
    hub = rig.hub(relay_output=True)
    edge = rig.edge()
    wait_until(lambda: rig.acked() >= 20, 60, "acks")
    full_disk.fill(hub)
    rig.client.wait(lambda s: s["recorder"]["write_errors"] >= 1, 30, "a refused write")
    assert edge.terminate() == 0  # its events come to the hub, which cannot write them
    full_disk.free(hub)
    log = rig.data / "events.log"
    wait_until(lambda: log.exists() and "write_resumed" in log.read_text(), 60, "writing to resume")
    assert hub.terminate() == 0
    # The file open when the disk filled was abandoned; what it holds is recoverable.
    reports = verify_path(sessions(rig.data)[0], recover=True)
    assert {r.status for r in reports} <= {"ok", "recovered"}, [r.line() for r in reports]
    tags = [tag for _, _, tag, _ in rig.timed_events()]
    assert "disk_full" in tags
    assert "write_resumed" in tags
    assert ("wec", "stopped") in [(node, tag) for node, tag, _ in rig.events()], (
        "held, then written"
    )
    raised = rig.summary(1)["events"]
    recorded = Counter(level for level, *_ in rig.leveled_events())
    assert recorded == Counter(raised)  # type: ignore[arg-type]
