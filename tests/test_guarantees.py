"""What the README's "What is guaranteed" promises and nothing else tests, end to end: a real
hub and a real edge as separate processes, the edge reaching the hub through a loopback link
the test cuts and restores (`tests.procs.Link`), every recorded file read back with rosbags.

- A spool that overflows during an outage drops its oldest batches and says exactly which
  (`spool_full`); the hub counts the ones it never received `lost` and raises `lost`.
- A backlog drains at most at `replay_mb_per_s`, and live batches keep flowing meanwhile.
- A stream the recorder excludes is still counted and acked (its edge does not spool forever).
- events.log rotates at its size and keeps five old files.
"""

from __future__ import annotations

import itertools
import json
import logging
import re
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest
from rosbags.highlevel import AnyReader

from fleetdaq.edge.spool import StreamSpool
from fleetdaq.hub.bus import EventBus
from fleetdaq.hub.config.load import parse_config
from fleetdaq.hub.read_model import ReadModel
from fleetdaq.hub.supervision.event_log import EventLog
from tests.procs import HubClient, Link, Proc, free_port, spooled, stream_view, wait_until

SITE = """\
site: guar
hub:
  listen: [tcp/127.0.0.1:{port}]
  recorder: {{file_duration_s: 600, flush_interval_s: 0.5, exclude: [wec/env]}}
nodes:
  wec:
    connect: [tcp/127.0.0.1:{link}]
    spool: {{fsync_interval_s: 0.5, replay_after_s: 2, {spool}}}
    streams:
      t8:
        driver: wave_sim          # 2 x 10 kS/s: 10 batches of 16 kB a second
        rate_hz: 10000
        channels: [{{name: c0, unit: V}}, {{name: c1, unit: V}}]
      env:
        driver: environment_sim   # not recorded (exclude above)
        rate_hz: 10
        scans_per_batch: 1
        channels: [{{name: air, unit: degC}}]
"""
RANGE = re.compile(r"sequences (\d+)\.\.(\d+)")


@dataclass(frozen=True)
class Recorded:
    log_ns: int
    sequence: int
    end_ns: int
    """Acquisition time just after the batch's last scan."""
    size: int


@dataclass
class Site:
    tmp: Path
    port: int
    link: Link
    cfg: Path
    data: Path
    procs: list[Proc] = field(default_factory=list)
    hubs: int = 0
    client: HubClient | None = None

    def configure(self, spool: str) -> None:
        text = SITE.format(port=self.port, link=self.link.port, spool=spool)
        parse_config(text, "site.yaml")  # a typo here would be a confusing failure later
        self.cfg.write_text(text)

    def hub(self) -> Proc:
        """Start a hub; return once it answers its status request (it starts that last)."""
        self.hubs += 1
        args = ["hub", "--config", str(self.cfg), "--data", str(self.data)]
        args += ["--summary", str(self.tmp / f"summary{self.hubs}.json")]
        p = Proc(args, self.tmp / f"hub{self.hubs}.log")
        self.procs.append(p)
        if self.client is None:
            self.client = HubClient(self.port, "guar")
        wait_until(self.client.status, 60, "the hub to answer its status request")
        return p

    def edge(self) -> Proc:
        args = ["edge", "--config", str(self.cfg), "--node", "wec"]
        p = Proc([*args, "--spool", str(self.tmp / "spool")], self.tmp / "edge.log")
        self.procs.append(p)
        return p

    def stream(self, name: str) -> dict[str, Any]:
        """The hub's accounting of stream `name` right now."""
        assert self.client is not None
        status = self.client.status()
        assert status is not None, "the hub does not answer"
        view = stream_view(status, "wec", name)
        assert view is not None
        return view

    def spool_dir(self, stream: str) -> Path:
        return self.tmp / "spool" / "wec" / stream

    def acked(self, stream: str) -> int:
        """The last ack the edge received (it writes it next to its spool)."""
        try:
            return int((self.spool_dir(stream) / "acked").read_text())
        except (FileNotFoundError, ValueError):
            return -1

    def newest_spooled(self, stream: str) -> int:
        return max((seq for seq, _ in spooled(self.spool_dir(stream))), default=-1)

    def oldest_spooled(self, stream: str) -> int:
        return min((seq for seq, _ in spooled(self.spool_dir(stream))), default=-1)

    def left_in_spool(self, stream: str) -> list[int]:
        """Unacked sequences in the (stopped) edge's spool: delivered on its next contact."""
        sp = StreamSpool(self.spool_dir(stream), 10**12, 10**9)
        try:
            return [seq for seq, _, _ in sp.read_from(sp.acked + 1, 2**62)]
        finally:
            sp.close()

    def summary(self, n: int) -> dict[str, Any]:
        out: dict[str, Any] = json.loads((self.tmp / f"summary{n}.json").read_text())
        return out

    def files(self) -> list[Path]:
        return sorted(self.data.glob("*/*.mcap"))

    def recorded(self, topic: str) -> list[Recorded]:
        out = []
        with AnyReader(self.files()) as reader:
            for c, log_ns, raw in reader.messages(
                [c for c in reader.connections if c.topic == topic]
            ):
                m = reader.deserialize(raw, c.msgtype)
                end = m.first_sample_time_ns + round(m.scan_count * m.sample_period_ns)
                out.append(Recorded(log_ns, m.sequence, end, len(raw)))
        return sorted(out, key=lambda r: r.log_ns)

    def events(self, node: str, tag: str) -> list[tuple[str, dict[str, str]]]:
        """(message, fields) of every recorded event `tag` raised by `node`."""
        out = []
        with AnyReader(self.files()) as reader:
            conns = [c for c in reader.connections if c.topic == "/events"]
            for c, _, raw in reader.messages(conns):
                m = reader.deserialize(raw, c.msgtype)
                if (m.node, m.tag) == (node, tag):
                    out.append((m.message, {kv.key: kv.value for kv in m.fields}))
        return out


@pytest.fixture
def site(tmp_path: Path) -> Iterator[Site]:
    port = free_port()
    link = Link(port)
    s = Site(tmp_path, port, link, tmp_path / "site.yaml", tmp_path / "data")
    try:
        yield s
    finally:
        for p in s.procs:
            p.kill()
        if s.client is not None:
            s.client.close()
        link.close()


def _acked_on_the_hub(s: Site, stream: str, at_least: int, timeout: float, what: str) -> None:
    def acked() -> bool:
        view = s.stream(stream)
        return view["acked"] is not None and view["acked"] >= at_least

    wait_until(acked, timeout, what, every=0.2)


def _caught_up(s: Site, stream: str, past: int) -> None:
    """Wait until the hub has every batch up to the live head, which is beyond `past`: no hole
    left to fill, and acked up to the last moment (its flush interval: 5 batches)."""

    def done() -> bool:
        v = s.stream(stream)
        head, acked = v["last_sequence"], v["acked"]
        if head is None or acked is None:
            return False  # a hub that has not seen the stream yet
        return head > past + 5 and v["missing"] == 0 and acked >= head - 10

    wait_until(done, 90, f"the hub to catch up with {stream}", every=0.2)


@pytest.mark.parametrize("outage", ["link down", "hub restarted"])
def test_a_spool_overflow_is_reported_exactly_and_the_hub_counts_it_lost(site: Site, outage: str):
    # 1 MB of spool holds ~6 s of this stream; past it whole 5-batch segments go, oldest first.
    site.configure("max_bytes: 1000000, segment_bytes: 65536")
    hub = site.hub()
    edge = site.edge()
    _acked_on_the_hub(site, "t8", 20, 60, "the first acks")
    if outage == "link down":
        site.link.cut()
    else:
        assert hub.terminate() == 0
    wait_until(
        lambda: site.oldest_spooled("t8") > site.acked("t8") + 20,
        60,
        "the spool to drop 20 unacked batches",
    )
    acked = site.acked("t8")  # the last ack that reached the edge before the outage
    if outage == "link down":
        site.link.restore()
    else:
        hub = site.hub()
    _caught_up(site, "t8", site.newest_spooled("t8"))
    assert edge.terminate() == 0
    assert hub.terminate() == 0

    # The edge said exactly what it dropped: the oldest unacked batches, one contiguous run.
    reports = [m for m, _ in site.events("wec", "spool_full")]
    assert reports, "the edge raised spool_full"
    ranges = [(int(a), int(b)) for m in reports for a, b in RANGE.findall(m)]
    dropped = sorted(seq for a, b in ranges for seq in range(a, b + 1))
    recorded = {r.sequence for r in site.recorded("/wec/t8")}
    assert len(set(dropped)) == len(dropped), "each batch reported once"
    assert dropped[0] == acked + 1, "oldest first"
    # One run, but for batches the returned hub acked between two drops (replayed, recorded).
    holes = set(range(dropped[0], dropped[-1] + 1)) - set(dropped)
    assert holes <= recorded, f"neither dropped nor recorded: {sorted(holes - recorded)}"
    # Everything missing from the recording (and not still spooled) is among what it reported.
    # (Not all it reported is missing: a batch that reached the hub but whose ack had not come
    # back yet, before the outage or replayed after it, may be dropped too.)
    left = set(site.left_in_spool("t8"))
    top = max(recorded | left)
    missing = sorted(set(range(top + 1)) - recorded - left)
    assert missing, "the outage cost batches"
    assert set(missing) <= set(dropped), f"lost without a report: {set(missing) - set(dropped)}"
    # The hub counts exactly those lost, and says so below the floors the edge reported.
    summary = site.summary(site.hubs)["streams"]["wec/t8"]
    assert summary["missing"] == 0, summary
    lost_events = [f for _, f in site.events("hub", "lost")]
    floors = [int(f["floor"]) for f in lost_events]
    counted = {
        "summary lost": summary["lost"],
        "lost events": sum(int(f["lost"]) for f in lost_events),
        "floors reported by the edge": bool(floors) and set(floors) <= {b + 1 for _, b in ranges},
        "every lost batch below a floor": bool(floors) and max(missing) < max(floors),
    }
    expected = {
        "summary lost": len(missing),
        "lost events": len(missing),
        "floors reported by the edge": True,
        "every lost batch below a floor": True,
    }
    assert counted == expected


def test_a_backlog_drains_at_the_replay_limit_while_live_batches_keep_flowing(site: Site):
    site.configure("replay_mb_per_s: 0.25")  # 250 kB/s: the 16 kB batches at ~15 a second
    hub = site.hub()
    edge = site.edge()
    _acked_on_the_hub(site, "t8", 20, 60, "the first acks")
    site.link.cut()
    acked = site.acked("t8")
    wait_until(lambda: site.newest_spooled("t8") >= acked + 40, 60, "a 4 s backlog")
    site.link.restore()
    _caught_up(site, "t8", site.newest_spooled("t8"))
    assert edge.terminate() == 0
    assert hub.terminate() == 0

    batches = site.recorded("/wec/t8")
    assert sorted(r.sequence for r in batches) == list(range(len(batches))), "nothing lost"
    # The edge replays only batches older than replay_after_s (2 s); live ones arrive at once.
    replayed = [r for r in batches if r.log_ns - r.end_ns >= 2_000_000_000]
    live = [r for r in batches if r.log_ns - r.end_ns < 1_000_000_000]
    assert len(replayed) >= 30, len(replayed)
    start, end = replayed[0].log_ns, replayed[-1].log_ns
    drain_s = (end - start) / 1e9
    rate = sum(r.size for r in replayed[1:]) / drain_s
    assert rate <= 1.25 * 250_000, f"replayed at {rate / 1e3:.0f} kB/s over {drain_s:.1f} s"
    # Meanwhile live batches (10 a second) kept arriving, with no stall.
    during = [start, *(r.log_ns for r in live if start < r.log_ns < end), end]
    stall_s = max(b - a for a, b in itertools.pairwise(during)) / 1e9
    assert stall_s < 1.0, f"no live batch for {stall_s:.2f} s during the {drain_s:.1f} s drain"
    assert len(during) - 2 >= 0.7 * 10 * drain_s, (len(during) - 2, drain_s)


def test_an_excluded_stream_is_counted_and_acked_but_not_recorded(site: Site):
    site.configure("max_bytes: 1000000")
    hub = site.hub()
    edge = site.edge()
    wait_until(lambda: site.acked("env") >= 30, 60, "acks for the excluded stream")
    assert edge.terminate() == 0
    assert hub.terminate() == 0
    env = site.summary(1)["streams"]["wec/env"]
    assert env["recorded"] is False
    assert env["batches"] == env["last_sequence"] - env["first_sequence"] + 1 >= 30
    assert (env["gaps"], env["lost"], env["missing"]) == (0, 0, 0)
    assert env["acked"] >= 30
    assert len(site.left_in_spool("env")) <= 10, "acked batches leave the edge's spool"
    with AnyReader(site.files()) as reader:
        topics = {c.topic for c in reader.connections}
    assert "/wec/t8" in topics
    assert "/wec/env" not in topics


def test_events_log_rotates_at_its_size_and_keeps_five_old_files(tmp_path: Path):
    bus = EventBus()
    path = tmp_path / "events.log"
    events = EventLog(path, bus, ReadModel("s"), max_bytes=4000, backups=5)
    bus.start()
    events.start()
    for i in range(600):  # ~100 bytes a line: 60 kB, far past 6 files of 4 kB
        bus.emit(logging.INFO, "test", "tick", f"event {i:04d}")
    bus.stop()
    events.stop()
    files = [path.with_name(f"events.log.{n}") for n in range(5, 0, -1)] + [path]
    assert sorted(tmp_path.iterdir()) == sorted(files), "events.log and .1 to .5, no more"
    assert all(0 < f.stat().st_size <= 4000 for f in files)
    numbers = [
        int(m.group(1))
        for f in files
        for m in re.finditer(r"\[tick\]: event (\d+)$", f.read_text(), re.M)
    ]
    # Oldest file first, newest last: an unbroken run ending with the last event.
    assert numbers == list(range(600 - len(numbers), 600))
    assert len(numbers) > 5 * 4000 // 100 / 2


def test_the_hub_rotates_events_log_at_10_mb_and_keeps_5(tmp_path: Path):
    from fleetdaq.hub.runtime import HubRuntime

    site = parse_config(SITE.format(port=free_port(), link=free_port(), spool="max_age_s: 60"), "s")
    runtime = HubRuntime(site, tmp_path)  # composed, not started: nothing opened
    assert runtime.event_log.path == tmp_path / "events.log"
    assert (runtime.event_log.max_bytes, runtime.event_log.backups) == (10_000_000, 5)
