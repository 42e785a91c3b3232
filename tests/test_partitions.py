"""Partitioned hubs: a main hub and a partition hub, their routers meshed, and four edges, as
separate OS processes on loopback. Each hub records exactly its slice with no gap; with the
partition hub down its edges spool and replay into it when it returns, while the main hub's
slice records on untouched. The main hub sees the whole fleet through the mesh."""

from __future__ import annotations

import contextlib
import json
import re
import subprocess
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from rosbags.highlevel import AnyReader

from fleetdaq.contract.cdr import encode
from fleetdaq.contract.keys import SiteKeys
from fleetdaq.contract.messages import OutputCommand, make_event
from fleetdaq.contract.wire import BatchEncoder, encode_u64
from fleetdaq.hub.config.load import load_config
from fleetdaq.hub.live.status_query import query_status
from fleetdaq.hub.partitions.runtime import partition_key
from fleetdaq.ptp.quality import UNSYNCED
from tests.procs import HubClient, Proc, free_port, node_alive, stream_view, wait_until

REPO = Path(__file__).resolve().parent.parent

SITE = """\
site: parts
hub:
  listen: [tcp/127.0.0.1:{main}]
  recorder: {{file_duration_s: {file_duration_s}, flush_interval_s: 0.5}}
  partitions:
    bay2:
      listen: [tcp/127.0.0.1:{bay2}]
      nodes: ["cell-*"]
nodes:
{nodes}
"""
NODE = """\
  {name}:
    spool: {{replay_after_s: 2, fsync_interval_s: 0.5}}
    streams:
      wave:
        driver: wave_sim          # 2 x 1 kS/s, 100 ms batches
        rate_hz: 1000
        channels: [{{name: c0, unit: V}}, {{name: c1, unit: V}}]
"""
MAIN_SLICE = ("wec-a", "wec-b")
BAY2_SLICE = ("cell-a", "cell-b")


def _topic(node: str) -> str:
    """Where a node's `wave` stream is recorded: ``wec-a`` as the ROS 2 name ``/wec_a/wave``."""
    return f"/{node.replace('-', '_')}/wave"


@dataclass
class Rig:
    tmp: Path
    cfg: Path
    main_port: int
    procs: list[Proc] = field(default_factory=list)
    bay2_runs: int = 0
    _client: HubClient | None = None

    @property
    def client(self) -> HubClient:
        """A session on the main hub's router: the partition hub answers through the mesh."""
        if self._client is None:
            self._client = HubClient(self.main_port, "parts")
        return self._client

    def main_hub(self) -> Proc:
        p = self._proc(["hub", "--data", str(self.tmp / "main")], "main", "main")
        wait_until(self.client.status, 60, "the main hub to answer its status request")
        return p

    def bay2_hub(self) -> Proc:
        self.bay2_runs += 1
        p = self._proc(
            ["hub", "--partition", "bay2", "--data", str(self.tmp / "bay2")],
            f"bay2-{self.bay2_runs}",
            f"bay2-{self.bay2_runs}",
        )
        wait_until(self.bay2_status, 60, "the partition hub to answer through the mesh")
        return p

    def edge(self, node: str) -> Proc:
        return self._proc(["edge", "--node", node, "--spool", str(self.tmp / "spool")], node)

    def _proc(self, args: list[str], log: str, summary: str = "") -> Proc:
        more = ["--summary", str(self.tmp / f"{summary}.json")] if summary else []
        p = Proc([args[0], "--config", str(self.cfg), *args[1:], *more], self.tmp / f"{log}.log")
        self.procs.append(p)
        return p

    def bay2_status(self) -> dict[str, Any] | None:
        key = partition_key(SiteKeys("parts"), "bay2", "status")
        return query_status(self.client.session, self.client.keys, 2.0, key=key)

    def spool_bytes(self, node: str) -> int:
        """What an edge's spool holds on disk (its segments), read from outside."""
        return sum(f.stat().st_size for f in (self.tmp / "spool" / node).glob("*/*.seg"))

    def summary(self, name: str) -> dict[str, Any]:
        out: dict[str, Any] = json.loads((self.tmp / f"{name}.json").read_text())
        return out


@contextlib.contextmanager
def running_rig(
    tmp_path: Path, nodes: tuple[str, ...], hub_extra: str = "", file_duration_s: float = 5
) -> Iterator[Rig]:
    """A site of `nodes` (``cell-*`` are bay2's) with `hub_extra` lines under ``hub:``, files
    split every `file_duration_s`; every process the rig starts is ended on the way out."""
    main, bay2 = free_port(), free_port()
    text = SITE.format(
        main=main,
        bay2=bay2,
        nodes="".join(NODE.format(name=n) for n in nodes),
        file_duration_s=file_duration_s,
    )
    cfg = tmp_path / "site.yaml"
    cfg.write_text(text.replace("  partitions:\n", hub_extra + "  partitions:\n"))
    r = Rig(tmp_path, cfg, main)
    try:
        yield r
    finally:
        for p in r.procs:
            p.kill()
        if r._client is not None:
            r._client.close()


@pytest.fixture
def rig(tmp_path: Path) -> Iterator[Rig]:
    with running_rig(tmp_path, (*MAIN_SLICE, *BAY2_SLICE)) as r:
        yield r


def _acked(status: dict[str, Any], node: str) -> int:
    view = stream_view(status, node, "wave")
    return -1 if view is None or view["acked"] is None else int(view["acked"])


def _edge_stream(status: dict[str, Any], node: str) -> dict[str, Any] | None:
    """A node's `wave` stream as its own health says (relayed by the main hub's node watch),
    with the health's time: {"time_ns": ..., "stream": StreamHealth as JSON}."""
    n = next((n for n in status["nodes"] if n["node"] == node), None)
    if n is None or n["health"] is None:
        return None
    st = next((s for s in n["health"]["streams"] if s["name"] == "wave"), None)
    return None if st is None else {"time_ns": n["health"]["time_ns"], "stream": st}


def _recorded(data: Path) -> dict[str, list[int]]:
    """Sequence numbers per data topic over every file of every session under `data`."""
    files = sorted(data.glob("*/*.mcap"))
    assert files, f"nothing recorded under {data}"
    out: dict[str, list[int]] = {}
    with AnyReader(files) as reader:
        conns = [c for c in reader.connections if c.topic.endswith("/wave")]
        if not conns:  # rosbags reads every connection when given none
            return out
        for c, _, raw in reader.messages(conns):
            out.setdefault(c.topic, []).append(reader.deserialize(raw, c.msgtype).sequence)
    return out


def wait_logged(log: Path, *texts: str, timeout: float = 30, what: str) -> str:
    """Wait until one line of the events log `log` holds every one of `texts`; that line."""

    def line() -> str | None:
        lines = log.read_text().splitlines() if log.exists() else []
        return next((x for x in lines if all(t in x for t in texts)), None)

    found: str = wait_until(line, timeout, what)
    return found


def _status_screen(rig: Rig) -> subprocess.CompletedProcess[str]:
    """`fleetdaq status` of the main hub, as an operator runs it."""
    return subprocess.run(
        [sys.executable, "-m", "fleetdaq", "status", "--config", str(rig.cfg)],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )


def _contiguous(seqs: list[int]) -> bool:
    return sorted(set(seqs)) == list(range(max(seqs) + 1))


def test_two_hubs_record_their_slices_and_a_partition_outage_replays_into_its_own_hub(rig: Rig):
    main = rig.main_hub()
    bay2 = rig.bay2_hub()
    edges = {node: rig.edge(node) for node in (*MAIN_SLICE, *BAY2_SLICE)}

    # The main hub sees the whole fleet through the mesh: every node alive, its own streams
    # acked by itself, bay2's as bay2's report says.
    def fleet_up(s: dict[str, Any]) -> dict[str, Any] | None:
        nodes = (*MAIN_SLICE, *BAY2_SLICE)
        up = all(node_alive(s, n) for n in nodes) and all(_acked(s, n) >= 10 for n in nodes)
        return s if up else None

    status = rig.client.wait(fleet_up, 60, "all four nodes alive and acked on both hubs")
    for node in BAY2_SLICE:
        assert stream_view(status, node, "wave")["hub"] == "bay2"  # type: ignore[index]
    for node in MAIN_SLICE:
        assert stream_view(status, node, "wave")["hub"] == ""  # type: ignore[index]
    assert status["partitions"]["bay2"]["alive"] is True
    assert status["partitions"]["bay2"]["data_disk"]["total_bytes"] > 0  # for its disk alarm
    own = rig.bay2_status()
    assert own is not None
    assert {s["node"] for s in own["streams"]} == set(BAY2_SLICE)
    # What `fleetdaq fleet status` runs on a partition hub's host: its own recorder.
    args = ["rec", "status", "--json", "--config", str(rig.cfg), "--partition", "bay2"]
    rec = subprocess.run(
        [sys.executable, "-m", "fleetdaq", *args],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=60,
        check=True,
    )
    recorder = json.loads(rec.stdout)["recorder"]
    assert recorder["state"] == "recording"
    assert Path(recorder["session_dir"]).parent == rig.tmp / "bay2"

    # bay2's own machine is one of the fleet's on the main hub (hub/bay2), as a node's health.
    rig.client.wait(
        lambda s: any(h["health"] and h["alive"] for h in s["partition_hubs"]),
        20,
        "bay2's own health on the main hub",
    )
    screen = _status_screen(rig)
    assert screen.returncode in (0, 1), screen.stderr  # 1 if the host's disk is nearly full
    rows = {line.split()[0]: line.split() for line in screen.stdout.splitlines() if line}
    assert rows["hub/bay2"][1:3] == ["yes", "0.1.0"], screen.stdout
    for node in BAY2_SLICE:
        assert rows[f"{node}/wave"][1] == "bay2", screen.stdout  # recorded by bay2
    assert "partition bay2: recording" in screen.stdout

    # The partition hub goes away: its edges spool, the main slice records on.
    main_before = {n: _acked(status, n) for n in MAIN_SLICE}
    assert bay2.terminate() == 0
    spooled_at_stop = {n: rig.spool_bytes(n) for n in BAY2_SLICE}
    rig.client.wait(
        lambda s: s["partitions"]["bay2"]["alive"] is False, 20, "the main hub to see bay2 gone"
    )
    wait_until(
        lambda: all(rig.spool_bytes(n) > spooled_at_stop[n] + 20_000 for n in BAY2_SLICE),
        30,
        "bay2's edges to spool what no hub acks",
    )
    rig.client.wait(
        lambda s: all(_acked(s, n) >= main_before[n] + 20 for n in MAIN_SLICE),
        30,
        "the main slice to go on being acked while bay2 is down",
    )
    main_log = rig.tmp / "main" / "events.log"
    wait_logged(
        main_log,
        "node_down/hub/bay2 raised",
        what="the main hub's alarm for the partition hub gone (10 s by default)",
    )
    screen = _status_screen(rig)
    assert screen.returncode == 1, screen.stdout + screen.stderr
    assert "partition hub bay2: gone" in screen.stdout
    assert "alarm node_down/hub/bay2: active_unacked (critical)" in screen.stdout
    assert "partition bay2: GONE" in screen.stdout
    hub_row = next(line for line in screen.stdout.splitlines() if line.startswith("hub/bay2 "))
    assert hub_row.split()[1] == "NO", hub_row

    # It returns: its edges replay into it, and catch up with live.
    back_ns = time.time_ns()
    bay2 = rig.bay2_hub()

    def bay2_caught_up(s: dict[str, Any]) -> bool:
        if not s["partitions"]["bay2"]["alive"]:
            return False
        for node in BAY2_SLICE:
            health = _edge_stream(s, node)
            if health is None or health["time_ns"] < back_ns:  # from before the outage
                return False
            st = health["stream"]
            if st["spool_acked"] < st["next_sequence"] - 10:
                return False
        return True

    rig.client.wait(bay2_caught_up, 60, "bay2's edges to replay into bay2 and catch up")
    events = [e["tag"] for e in rig.client.status()["recent_events"]]  # type: ignore[index]
    assert "partition_gone" in events
    assert "partition_up" in events

    for p in edges.values():
        assert p.terminate() == 0
    assert main.terminate() == 0
    # No main hub: `fleetdaq status` says so (exit 2) and shows what bay2 answers for its slice.
    gone = _status_screen(rig)
    assert gone.returncode == 2, gone.stdout + gone.stderr
    assert "cannot reach the hub" in gone.stderr, gone.stderr
    assert "the main hub does not answer; each partition hub" in gone.stdout, gone.stdout
    assert "partition hub bay2 · site" in gone.stdout, gone.stdout
    assert "recorder: recording" in gone.stdout, gone.stdout
    for node in BAY2_SLICE:
        assert f"{node}/wave" in gone.stdout, gone.stdout
    for node in MAIN_SLICE:
        assert f"{node}/wave" not in gone.stdout, gone.stdout  # the main hub's slice: unknown
    as_json = subprocess.run(
        [sys.executable, "-m", "fleetdaq", "status", "--json", "--config", str(rig.cfg)],
        cwd=REPO, capture_output=True, text=True, timeout=60, check=False,
    )  # fmt: skip
    assert as_json.returncode == 2, as_json.stderr
    answer = json.loads(as_json.stdout)
    assert "cannot reach the hub" in answer["error"]
    assert answer["partitions"]["bay2"]["recorder"]["state"] == "recording"
    assert bay2.terminate() == 0
    gone = _status_screen(rig)  # nobody at all: each hub's reason, still exit 2
    assert gone.returncode == 2, gone.stdout + gone.stderr
    assert "partition hub bay2: no answer either (cannot reach the hub" in gone.stdout, gone.stdout

    # Each hub holds exactly its slice, without a gap, across both runs of bay2.
    main_rec = _recorded(rig.tmp / "main")
    bay2_rec = _recorded(rig.tmp / "bay2")
    assert set(main_rec) == {_topic(n) for n in MAIN_SLICE}
    assert set(bay2_rec) == {_topic(n) for n in BAY2_SLICE}
    assert len([d for d in (rig.tmp / "bay2").iterdir() if d.name[:1].isdigit()]) == 2
    for topic, seqs in {**main_rec, **bay2_rec}.items():
        assert _contiguous(seqs), f"{topic}: gaps in {len(seqs)} recorded batches"
        assert len(seqs) == len(set(seqs)), f"{topic}: a batch recorded twice"
    for node in MAIN_SLICE:
        s = rig.summary("main")["streams"][f"{node}/wave"]
        assert (s["gaps"], s["lost"], s["late"]) == (0, 0, 0), s  # untouched by bay2's outage
        assert max(main_rec[_topic(node)]) >= main_before[node] + 20
    for node in BAY2_SLICE:
        seqs = bay2_rec[_topic(node)]
        at_stop = max(rig.summary("bay2-1")["streams"][f"{node}/wave"]["last_sequence"], 0)
        assert max(seqs) >= at_stop + 20, "the outage's batches were replayed into bay2"


# --- the site file ---------------------------------------------------------------------------


def test_each_node_connects_to_its_own_hubs_router_and_partitions_mesh_with_earlier_hubs():
    site = load_config(REPO / "tests/data/config/good_partitions.yaml")
    assert site.endpoints_for("wec-1") == ["tcp/10.0.0.1:7447"]
    assert site.endpoints_for("cell-2") == ["tcp/10.0.0.2:7447"]
    assert site.nodes_of(None) == ["wec-1", "wec-2"]
    assert site.nodes_of("bay2") == ["cell-1", "cell-2"]
    assert site.mesh_connect(None) == []
    assert site.mesh_connect("bay2") == ["tcp/10.0.0.1:7447"]


def test_a_site_without_partitions_is_one_hub_recording_every_node():
    site = load_config(REPO / "tests/data/config/good_minimal.yaml")
    assert site.nodes_of(None) == list(site.nodes)
    assert site.mesh_connect(None) == []


def test_an_unknown_partition_on_the_command_line_is_one_line_and_exit_2():
    cfg = "tests/data/config/good_partitions.yaml"
    run = subprocess.run(
        [sys.executable, "-m", "fleetdaq", "hub", "--config", cfg, "--partition", "bay3"],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    assert run.returncode == 2
    assert run.stderr.strip().splitlines() == [
        "--partition: tests/data/config/good_partitions.yaml has no partition 'bay3' in "
        "hub.partitions (bay2)"
    ]


def test_the_main_hub_shows_a_partition_stream_live_only_while_somebody_looks_at_it(
    tmp_path: Path,
):
    """The partition's batches never cross the mesh to the main hub, except while a viewer of
    the main hub's dashboard plots one of its streams, or a Foxglove client subscribes to it:
    then they come, are shown, and are not recorded by the main hub; when the viewer leaves,
    they stop coming."""
    import asyncio
    import urllib.request

    import aiohttp
    import numpy as np

    from fleetdaq.hub.live.web import frames
    from tests.foxglove_client import FoxgloveClient

    dash = (
        f'  dashboard: {{enabled: true, listen: "127.0.0.1:0", users_file: {tmp_path / "users"},'
        ' foxglove: {enabled: true, listen: "127.0.0.1:0"}}\n'
    )
    with running_rig(tmp_path, ("wec-a", "cell-a"), dash) as rig:
        main = rig.main_hub()
        rig.bay2_hub()
        rig.edge("wec-a")
        rig.edge("cell-a")
        m = wait_until(
            lambda: re.search(r"dashboard on (http://\S+)", main.output()), 60, "the dashboard"
        )
        url = m.group(1)
        wait_until(
            lambda: (stream_view(rig.client.status() or {}, "cell-a", "wave") or {}).get("batches"),
            60,
            "cell-a's batches recorded by bay2",
        )
        plot = json.dumps(
            {"type": "plots", "plots": [
                {"id": "p", "stream": "cell-a/wave", "channels": ["c0", "c1"], "width": 200,
                 "span_s": 5}]}
        )  # fmt: skip

        async def view() -> np.ndarray:
            assembled = frames.Assembler()
            async with (
                aiohttp.ClientSession() as s,
                s.ws_connect(url.replace("http", "ws") + "api/live") as ws,
            ):
                await ws.send_str(plot)
                deadline = time.monotonic() + 60
                hostile_at: int | None = None
                frames_seen = 0
                while time.monotonic() < deadline:
                    msg = await asyncio.wait_for(ws.receive(), 20)
                    if msg.type != aiohttp.WSMsgType.BINARY:
                        continue
                    assert assembled.apply(msg.data), "every frame applies to the one before"
                    assert assembled.minmax is not None
                    frames_seen += 1
                    if hostile_at is None and np.isfinite(assembled.minmax).sum() >= 2 * 2 * 50:
                        # Garbage on the stream's key while it is followed: dropped, counted,
                        # and the plot goes on.
                        rig.client.session.put(SiteKeys("parts").data("cell-a", "wave"), b"junk")
                        hostile_at = frames_seen
                    if hostile_at is not None and frames_seen >= hostile_at + 5:
                        return assembled.minmax
                raise AssertionError("no data of cell-a/wave drawn within 60 s")

        drawn = asyncio.run(view())
        assert np.isfinite(drawn).all(axis=(0, 1)).sum() >= 50, "both channels, 50+ columns"
        assert "live view of cell-a/wave: following it across the mesh" in main.output()
        wait_until(
            lambda: "cell-a/wave: nobody looks at it, no longer followed" in main.output(),
            30,
            "the main hub to let go of cell-a/wave once the viewer left",
        )

        def latest() -> list[Any]:
            with urllib.request.urlopen(url + "api/streams", timeout=10) as r:
                got: list[Any] = json.loads(r.read())["streams"]["cell-a/wave"]["latest"]
            return got

        # No frozen values once nobody follows it (the partition's report still says its age).
        wait_until(lambda: latest() == [None, None], 10, "cell-a/wave's values withdrawn")

        # Foxglove: the same stream while a client subscribes to it.
        fox = wait_until(
            lambda: re.search(r"Foxglove live view on (ws://\S+)", main.output()), 10, "Foxglove"
        )
        with FoxgloveClient(fox.group(1)) as client:
            client.wait(lambda: "/cell_a/wave" in client.topics(), 10, "the advertise")
            sub = client.subscribe("/cell_a/wave")
            client.wait(lambda: len(client.messages(sub)) >= 20 or None, 30, "its messages")
            assert {"c0", "c1"} <= set(client.messages(sub)[-1].json()), "a plottable channel each"
        wait_until(
            lambda: main.output().count("cell-a/wave: nobody looks at it, no longer followed") == 2,
            30,
            "the main hub to let go of cell-a/wave once the Foxglove client left",
        )
        assert main.output().count("live view of cell-a/wave: following it across the mesh") == 2
        for proc in rig.procs[2:]:  # the edges, then the main hub: every file closed
            assert proc.terminate(30) == 0, proc.output()[-3000:]
        assert main.terminate(30) == 0, main.output()[-3000:]
    events = (tmp_path / "main" / "events.log").read_text()
    assert "live view of cell-a/wave: dropped a payload that is not a valid batch" in events
    recorded = _recorded(tmp_path / "main")
    assert any("wec" in topic for topic in recorded), recorded
    assert not any("cell" in topic for topic in recorded), "the main hub records its slice only"


def test_a_snapshot_on_the_main_hub_is_one_on_every_partition_hub_too(tmp_path: Path):
    """`fleetdaq rec snapshot` asks the main hub, which asks each partition hub: each keeps a
    buffer of its own slice and writes it too; the reply names every hub's file, and the
    partition's event reaches the main hub's log. Junk on the trigger key (what rules and
    alarms use) is refused and said, never taken."""
    from fleetdaq.analysis.errors import UnknownStream
    from fleetdaq.read import read_stream

    with running_rig(tmp_path, ("wec-a", "cell-a")) as rig:
        # bay2's machine keeps a smaller buffer than the main hub's (its own bounds).
        own = '      nodes: ["cell-*"]\n      snapshot: {seconds: 20, max_bytes: 50000000}\n'
        rig.cfg.write_text(rig.cfg.read_text().replace('      nodes: ["cell-*"]\n', own))
        main = rig.main_hub()
        bay2 = rig.bay2_hub()
        edges = [rig.edge("wec-a"), rig.edge("cell-a")]
        wait_until(
            lambda: (
                (stream_view(rig.client.status() or {}, "cell-a", "wave") or {}).get("batches", 0)
                >= 30
            ),
            60,
            "3 s of cell-a's batches taken by bay2",
        )
        rig.client.session.put(SiteKeys("parts").hub("snapshot/trigger"), b'{"kind": "wipe"}')
        r = subprocess.run(
            [sys.executable, "-m", "fleetdaq", "rec", "snapshot", "--config", str(rig.cfg),
             "--note", "before the storm"],
            cwd=REPO, capture_output=True, text=True, timeout=200, check=False,
        )  # fmt: skip
        assert r.returncode == 0, r.stdout + r.stderr
        bay2_view = (rig.bay2_status() or {}).get("snapshots") or {}
        assert bay2_view["written"] == 1  # written before the main hub replied
        assert (bay2_view["seconds"], bay2_view["max_bytes"]) == (20, 50_000_000)
        assert f"partition bay2: {bay2_view['last']}" in r.stdout, "the reply names its file"
        main_view = (rig.client.status() or {})["snapshots"]
        assert main_view["written"] == 1
        assert main_view["seconds"] == 60, "the site's hub.snapshot"
        ours = read_stream(Path(bay2_view["last"]), "cell-a/wave")
        assert ours.data.shape[0] >= 2000, "bay2's seconds of its own slice"
        assert Path(bay2_view["last"]).is_relative_to(tmp_path / "bay2")
        with pytest.raises(UnknownStream):
            read_stream(Path(main_view["last"]), "cell-a/wave")  # the main hub's: its slice
        assert read_stream(Path(main_view["last"]), "wec-a/wave").data.shape[0] >= 1000
        main_log = tmp_path / "main" / "events.log"
        wait_logged(
            main_log,
            f"written to {bay2_view['last']} (requested by ",
            what="bay2's snapshot event in the main hub's log",
        )
        assert "): before the storm" in main_log.read_text()
        events = main_log.read_text()
        assert "refused a snapshot trigger that is not one (kind 'wipe'" in events
        for proc in (*edges, bay2, main):
            assert proc.terminate(30) == 0, proc.output()[-3000:]


def test_start_stop_and_split_on_the_main_hub_reach_every_partition_hub(tmp_path: Path):
    """`fleetdaq rec split|stop|start` asks the main hub, which passes the request on to every
    partition hub and replies with each hub's answer; `--partition NAME` asks that hub alone.
    With the partition hub down the main hub still acts, and the reply names the hub that did
    not answer (exit 1)."""

    def rec(rig: Rig, *args: str) -> subprocess.CompletedProcess[str]:
        return subprocess.run(
            [sys.executable, "-m", "fleetdaq", "rec", *args, "--config", str(rig.cfg)],
            cwd=REPO, capture_output=True, text=True, timeout=200, check=False,
        )  # fmt: skip

    def recorder(rig: Rig, partition: str | None = None) -> dict[str, Any]:
        more = ("--partition", partition) if partition else ()
        r = rec(rig, "status", "--json", *more)
        assert r.returncode == 0, r.stdout + r.stderr
        out: dict[str, Any] = json.loads(r.stdout)
        return out

    # Files split only by request here: with the rig's 5 s files a slow machine saw the main
    # hub close a second file by duration between the split and the count.
    with running_rig(tmp_path, ("wec-a", "cell-a"), file_duration_s=3600) as rig:
        main = rig.main_hub()
        bay2 = rig.bay2_hub()
        edges = [rig.edge("wec-a"), rig.edge("cell-a")]
        wait_until(
            lambda: all(recorder(rig, p)["recorder"]["current_file"] for p in (None, "bay2")),
            60,
            "a file open on both hubs",
        )

        # Split on the main hub: both hubs close a file.
        r = rec(rig, "split")
        assert r.returncode == 0, r.stdout + r.stderr
        assert "split: closed " in r.stdout
        assert "partition bay2: closed " in r.stdout
        wait_until(
            lambda: recorder(rig, "bay2")["recorder"]["files"] and True,
            30,
            "bay2's closed file in its status",
        )
        main_files = len(recorder(rig)["recorder"]["files"])
        assert main_files == 1

        # Split on bay2 alone: the main hub's files stay as they were.
        wait_until(
            lambda: recorder(rig, "bay2")["recorder"]["current_file"], 30, "bay2's next file"
        )
        r = rec(rig, "split", "--partition", "bay2", "--json")
        assert r.returncode == 0, r.stdout + r.stderr
        assert json.loads(r.stdout)["result"].startswith("closed ")
        assert len(recorder(rig, "bay2")["recorder"]["files"]) == 2
        assert len(recorder(rig)["recorder"]["files"]) == main_files

        # Stop on the main hub: both stop; the main hub's status shows bay2's recorder, and
        # bay2's event (naming who) reaches the main hub's log.
        r = rec(rig, "stop", "--note", "tide turning")
        assert r.returncode == 0, r.stdout + r.stderr
        assert "partition bay2: stopped; session " in r.stdout
        assert recorder(rig)["recorder"]["state"] == "stopped"
        assert recorder(rig, "bay2")["recorder"]["state"] == "stopped"

        def stopped_shown() -> str | None:
            out = rec(rig, "status").stdout
            return out if "bay2: stopped " in out else None

        shown = wait_until(
            stopped_shown, 30, "bay2's stopped recorder in the main hub's status (its report)"
        )
        assert re.search(r"partition    bay2: stopped .*; disk \d+ % free", shown), shown
        main_log = tmp_path / "main" / "events.log"
        wait_logged(
            main_log, "hub/bay2", "recording stopped by ", what="bay2's stop in the main hub's log"
        )

        # Start on the main hub: both record again, each into a new session.
        r = rec(rig, "start", "--json")
        assert r.returncode == 0, r.stdout + r.stderr
        answer = json.loads(r.stdout)
        assert answer["partition_results"]["bay2"]["ok"] is True
        assert answer["partition_results"]["bay2"]["result"].startswith("recording into ")
        assert recorder(rig, "bay2")["recorder"]["state"] == "recording"
        assert len([d for d in (tmp_path / "bay2").iterdir() if d.name[:1].isdigit()]) == 2

        # bay2 down: the main hub stops all the same, and says which hub did not answer.
        assert bay2.terminate(30) == 0, bay2.output()[-3000:]
        rig.client.wait(
            lambda s: s["partitions"]["bay2"]["alive"] is False, 20, "the main hub to see bay2 gone"
        )
        r = rec(rig, "stop")
        assert r.returncode == 1, r.stdout + r.stderr
        assert "partition bay2: no answer (is its hub running and linked?" in r.stderr
        assert "partition    bay2: gone" in r.stdout
        assert recorder(rig)["recorder"]["state"] == "stopped"
        for proc in (*edges, main):
            assert proc.terminate(30) == 0, proc.output()[-3000:]


def test_a_rules_record_action_reaches_the_partition_hubs_and_one_not_done_is_said(
    tmp_path: Path,
):
    """A rule's `record: split` on the main hub splits every partition hub's file too, without
    the rule waiting on another machine; a partition hub that is down is a warning event. Its
    `record: snapshot` reaches the partition hubs by the snapshot trigger."""
    with running_rig(tmp_path, ("wec-a", "cell-a")) as rig:
        bay3 = free_port()
        text = rig.cfg.read_text().replace(
            "\nnodes:\n",
            f'\n    bay3:\n      listen: [tcp/127.0.0.1:{bay3}]\n      nodes: ["spare-*"]\n'
            "nodes:\n  spare-1:\n    streams:\n      wave: {driver: wave_sim, rate_hz: 10,"
            " channels: [{name: c0}]}\n",
        )
        text += (
            "rules:\n  split_everywhere:\n"
            "    when: {node: wec-a, alive: true}\n"
            "    do: [{record: split}, {record: snapshot}]\n"
        )
        rig.cfg.write_text(text)
        main = rig.main_hub()
        bay2 = rig.bay2_hub()  # bay3 stays down
        edges = [rig.edge("cell-a")]
        wait_until(
            lambda: ((rig.bay2_status() or {}).get("recorder") or {}).get("current_file"),
            60,
            "a file open on bay2 before the rule can fire",
        )
        edges.append(rig.edge("wec-a"))  # the rule fires when wec-a is there
        main_log = tmp_path / "main" / "events.log"
        line = wait_logged(
            main_log,
            "hub/bay2/recorder [split]",
            timeout=60,
            what="bay2's split, asked by the rule, in the main hub's log",
        )
        assert "by rule:split_everywhere@hub" in line
        wait_logged(
            main_log,
            "partition hub bay3: record split for rule:split_everywhere not done: no answer",
            what="bay3's missing split as a warning",
        )
        # The rule's snapshot reaches bay2 by the trigger (as an alarm's does).
        wait_logged(
            main_log,
            "hub/bay2/recorder [snapshot]",
            "(requested by rule:split_everywhere on the main hub)",
            timeout=60,
            what="bay2's snapshot, triggered by the rule, in the main hub's log",
        )
        for proc in (*edges, bay2, main):
            assert proc.terminate(30) == 0, proc.output()[-3000:]


SECURE_SITE = """\
site: sparts
security:
  tls: true
  pki_dir: {pki}
  operators: {{ann: control}}
hub:
  listen: [tls/127.0.0.1:{main}]
  recorder: {{file_duration_s: 3600, flush_interval_s: 0.5}}
  partitions:
    bay2:
      listen: [tls/127.0.0.1:{bay2}]
      nodes: [cell-a]
    bay3:
      listen: [tls/127.0.0.1:{bay3}]
      nodes: [cell-b]
nodes:
{nodes}
"""


def test_a_partitioned_site_with_security_on_meshes_over_mutual_tls(tmp_path: Path):
    """security.tls with partitions: three hubs' routers mesh by mutual TLS, the main hub with
    the site's hub pair, bay2 and bay3 each with its own, and the access control lets hubs,
    and only hubs, speak across the mesh. The main hub sees both partitions recording; an
    operator's split reaches them through the main hub, and `--partition` asks bay2 directly;
    a node's certificate can neither ask bay2's recorder nor put a report in bay2's name. A
    command to each partition's node crosses the mesh, and is applied (the node hears the main
    hub's heartbeat across it). bay2's own pair (CN ``hub:bay2``) is
    all its router has, and on the main hub's router that key speaks for bay2's slice only: it
    cannot publish a main-hub node's data, events or liveliness, ack its stream, beat the
    heartbeat, command its output or ask the main hub's services."""
    import os

    import zenoh

    from fleetdaq.pki import init, issue_node, issue_operator, issue_partition
    from fleetdaq.runtime.security import TlsFiles, read_certificate
    from fleetdaq.runtime.zenoh_session import client_config

    pki = tmp_path / "pki"
    init(pki, "sparts", ["127.0.0.1"])
    for node in ("wec-a", "cell-a"):
        issue_node(pki, node)
    issue_operator(pki, "ann", "control")
    issue_partition(pki, "bay2", ["127.0.0.1"])
    issue_partition(pki, "bay3", ["127.0.0.1"])
    issue_node(pki, "cell-b")
    main_port, bay2_port, bay3_port = free_port(), free_port(), free_port()
    port_of = {"cell-a": bay2_port, "cell-b": bay3_port}
    nodes = "".join(
        NODE.format(name=n)
        + f"    connect: [tls/127.0.0.1:{port_of.get(n, main_port)}]\n"
        + "    outputs:\n      lamp: {driver: pcf8574, address: 0x20, pin: 1, safe: 0, sim: {}}\n"
        for n in ("wec-a", "cell-a", "cell-b", "wec-z")  # wec-z: a main-hub node, never started
    )
    cfg = tmp_path / "site.yaml"
    cfg.write_text(
        SECURE_SITE.format(pki=pki, main=main_port, bay2=bay2_port, bay3=bay3_port, nodes=nodes)
    )
    env = {
        **os.environ,
        "FLEETDAQ_CERT": str(pki / "operators" / "ann.crt"),
        "FLEETDAQ_KEY": str(pki / "operators" / "ann.key"),
    }

    def ann(*args: str) -> subprocess.CompletedProcess[str]:
        return subprocess.run(
            [sys.executable, "-m", "fleetdaq", *args, "--config", str(cfg)],
            cwd=REPO, env=env, capture_output=True, text=True, timeout=200, check=False,
        )  # fmt: skip

    def status() -> dict[str, Any]:
        """The main hub's recorder status as ann asks it ({} while no hub answers yet)."""
        r = ann("rec", "status", "--json")
        out: dict[str, Any] = json.loads(r.stdout) if r.returncode == 0 else {}
        return out

    procs: list[Proc] = []
    try:
        for name, args in (
            ("main", ["hub", "--data", str(tmp_path / "main")]),
            ("bay2", ["hub", "--partition", "bay2", "--data", str(tmp_path / "bay2")]),
            ("bay3", ["hub", "--partition", "bay3", "--data", str(tmp_path / "bay3")]),
            ("wec-a", ["edge", "--node", "wec-a", "--spool", str(tmp_path / "spool")]),
            ("cell-a", ["edge", "--node", "cell-a", "--spool", str(tmp_path / "spool")]),
            ("cell-b", ["edge", "--node", "cell-b", "--spool", str(tmp_path / "spool")]),
        ):
            procs.append(Proc([args[0], "--config", str(cfg), *args[1:]], tmp_path / f"{name}.log"))
        # The main hub sees bay2 and bay3 across the TLS mesh (three routers, each partition
        # with its own pair): there, reporting, recording their nodes.
        wait_until(
            lambda: all(
                (p := (status().get("partitions") or {}).get(name) or {}).get("alive")
                and (p.get("recorder") or {}).get("current_file")
                for name in ("bay2", "bay3")
            ),
            90,
            "bay2 and bay3 there and recording, as the main hub sees them",
        )
        r = ann("rec", "split")
        assert r.returncode == 0, r.stdout + r.stderr
        assert "partition bay2: closed " in r.stdout
        assert "partition bay3: closed " in r.stdout
        # A command from the main hub to each partition's node: across the mesh, and applied
        # only because the node hears the main hub's heartbeat across it too.
        for node in ("cell-a", "cell-b"):
            r = ann("out", "set", f"{node}/lamp", "1", "--reason", "across the mesh")
            assert r.returncode == 0, r.stdout + r.stderr
            assert "applied" in r.stdout
        r = ann("rec", "status", "--partition", "bay2", "--json")
        assert r.returncode == 0, r.stdout + r.stderr
        assert len(json.loads(r.stdout)["recorder"]["files"]) == 1
        # The site at a glance, with the operator's certificate: the main hub's and bay2's own.
        r = ann("status")
        assert r.returncode in (0, 1), r.stdout + r.stderr  # 1: the host's disk nearly full
        assert re.search(r"^hub/bay2 +yes +0\.1\.0 ", r.stdout, re.M), r.stdout
        r = ann("status", "--partition", "bay2")
        assert r.returncode in (0, 1), r.stdout + r.stderr
        assert r.stdout.startswith("partition hub bay2 · site sparts"), r.stdout
        assert re.search(r"^cell-a/\w+ +- ", r.stdout, re.M), r.stdout  # its own slice
        # When bay2's own pair ends, from its health as the main hub hears it (what
        # certificate_expiring/hub/bay2 watches).
        bay2_ends = read_certificate(pki / "partitions" / "bay2.crt")["not_after_ns"]

        def bay2_health() -> dict[str, Any]:
            r = ann("status", "--json")
            view = json.loads(r.stdout) if r.returncode in (0, 1) else {}
            hubs = [h for h in view.get("partition_hubs", ()) if h["node"] == "hub/bay2"]
            return (hubs[0]["health"] or {}) if hubs else {}

        wait_until(
            lambda: bay2_health().get("certificate_not_after_ns") == bay2_ends,
            30,
            "bay2's health saying when its certificate ends",
        )
        main_log = tmp_path / "main" / "events.log"
        wait_logged(
            main_log,
            "hub/bay2/recorder [split]",
            "by ann@",
            what="bay2's split, naming ann, in the main hub's log",
        )

        # A node's certificate on bay2's router: not a hub.
        cell = TlsFiles(pki / "ca.crt", pki / "nodes" / "cell-a.crt", pki / "nodes" / "cell-a.key")
        s = zenoh.open(client_config([f"tls/127.0.0.1:{bay2_port}"], tls=cell))
        try:
            keys = SiteKeys("sparts")
            asked = list(
                s.get(
                    keys.hub("partition/bay2/recorder"),
                    payload=b'{"action": "stop", "user": "mallory"}',
                    timeout=5,
                )
            )
            assert [x for x in asked if x.ok is not None] == [], "a node may not ask bay2"
            s.put(keys.hub("partition/bay2/report"), b'{"streams": "forged"}')
        finally:
            s.close()
        assert status()["partitions"]["bay2"]["recorder"]["state"] == "recording"

        # bay2's own key on the main hub's router: bay2's slice, nothing of the main hub's.
        def wec_a() -> dict[str, Any]:
            r = ann("status", "--json")
            assert r.returncode in (0, 1), r.stdout + r.stderr
            view = json.loads(r.stdout)
            stream = stream_view(view, "wec-a", "wave")
            assert stream is not None
            return stream

        before = wec_a()
        bay2_key = TlsFiles(
            pki / "ca.crt", pki / "partitions" / "bay2.crt", pki / "partitions" / "bay2.key"
        )
        s = zenoh.open(client_config([f"tls/127.0.0.1:{main_port}"], tls=bay2_key))
        try:
            keys = SiteKeys("sparts")
            enc = BatchEncoder("wec-a", "wave", ("c0", "c1"), ("V", "V"))
            for i in range(20):  # wec-a's data, far ahead in sequence
                batch = enc.encode(10**9 + i, time.time_ns(), 1e3, np.full((100, 2), 7.0), UNSYNCED)
                s.put(keys.data("wec-a", "wave"), bytes(batch), attachment=encode_u64(0))
            s.put(keys.ack("wec-a", "wave"), encode_u64(10**12))  # an ack wec-a never earned
            s.put(keys.hub("heartbeat"), b"\x00" * 16)
            s.put(
                keys.events("wec-a"),
                encode(make_event(time.time_ns(), "wec-a", 50, "x", "forged", "forged")),
            )
            token = s.liveliness().declare_token(keys.alive("wec-z"))  # a main-hub node, off
            cmd = OutputCommand(
                "f1", "lamp", "set", 1.0, 0.0, "operator", "bay2", "", time.time_ns(), 0.0
            )
            for key in (keys.out("wec-a", "lamp"), keys.out("cell-a", "lamp")):
                asked = [r for r in s.get(key, payload=encode(cmd), timeout=3) if r.ok]
                assert asked == [], f"{key}: a partition hub's key cannot command"
            body = json.dumps({"action": "stop", "user": "ann"}).encode()
            for key in (keys.hub("recorder/by/ann"), keys.hub("status/by/ann")):
                assert [r for r in s.get(key, payload=body, timeout=3) if r.ok] == [], key
            token.undeclare()
        finally:
            s.close()
        after = wec_a()
        assert after["last_sequence"] < 10**9, "the forged batches never reached the recorder"
        assert after["malformed"] == before["malformed"]
        r = ann("status", "--json")
        view = json.loads(r.stdout)
        assert any(n["node"] == "wec-z" for n in view["nodes"])
        assert not node_alive(view, "wec-z"), "no token in another node's name"
        assert status()["recorder"]["state"] == "recording", "the recorder was not stopped"
        for p in procs:
            assert p.terminate(30) == 0, p.output()[-3000:]
    finally:
        for p in procs:
            p.kill()
    events = main_log.read_text()
    assert "refused a report" not in events, "the forged report never reached the main hub"
    assert "mallory" not in events
    for tag in ("ack_refused", "heartbeat_refused", "[forged]"):
        assert tag not in events, f"{tag}: a forgery with bay2's key reached a main-hub node"
    assert len([d for d in (tmp_path / "bay2").iterdir() if d.name[:1].isdigit()]) == 1


def test_alarms_and_rules_on_a_partitions_channel_run_on_the_main_hub(tmp_path: Path):
    """A channel alarm and a rule on bay2's node: the main hub follows that stream across the
    mesh for as long as it runs (nobody plotting it) and evaluates them there; the main hub
    still records only its own slice."""
    with running_rig(tmp_path, ("wec-a", "cell-a")) as rig:
        rig.cfg.write_text(
            rig.cfg.read_text()
            + "alarms:\n  cell_wave: {channel: cell-a/wave/c0, above: -100, severity: minor}\n"
            "rules:\n  cell_seen:\n    when: {channel: cell-a/wave/c1, below: 100}\n"
            "    do: [{event: cell-a is watched from the main hub}]\n"
        )
        main = rig.main_hub()
        bay2 = rig.bay2_hub()
        edges = [rig.edge("cell-a"), rig.edge("wec-a")]
        main_log = tmp_path / "main" / "events.log"
        wait_logged(main_log, "cell_wave raised", timeout=60, what="the alarm on cell-a's channel")
        wait_logged(main_log, "cell-a is watched from the main hub", what="the rule's event")
        assert "alarms and rules of cell-a/wave: following it across the mesh" in main.output()
        rig.client.wait(
            lambda s: (stream_view(s, "wec-a", "wave") or {}).get("batches", 0) >= 5,
            30,
            "the main hub's own slice recorded too",
        )
        for proc in (*edges, bay2, main):
            assert proc.terminate(30) == 0, proc.output()[-3000:]
    recorded = _recorded(tmp_path / "main")
    assert set(recorded) == {_topic("wec-a")}, "the main hub records its slice only"
