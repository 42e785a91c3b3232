"""Hostile traffic never stops recording: a real hub and edge, and a separate process throwing
mutated copies of real traffic, junk, out-of-range times, floods on undefined keys and
flapping liveliness tokens at them. The hub stays up, refuses and counts what is wrong,
records the real stream without a gap, and every file it closes reads back."""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

from mcap.reader import make_reader
from rosbags.highlevel import AnyReader

from tests.procs import REPO, Proc, free_port, wait_for_port

SITE = """\
site: hostile
hub:
  listen: [tcp/127.0.0.1:{port}]
  recorder: {{file_duration_s: 5, flush_interval_s: 0.5}}
nodes:
  wec:
    spool: {{replay_after_s: 2}}
    streams:
      t8:
        driver: wave_sim
        rate_hz: 2000
        channels: [{{name: a}}, {{name: b}}, {{name: c}}, {{name: d}}]
  ghost:   # in the site file, but no edge runs it: the attacker speaks for it
    streams:
      g: {{driver: wave_sim, rate_hz: 10, channels: [{{name: a}}]}}
"""


def _wait_for_no_holes(port: int, timeout: float = 60.0) -> None:
    """Until the hub says wec/t8 has no hole waiting for a replay and has acked recently."""
    import zenoh

    from fleetdaq.contract.keys import SiteKeys
    from fleetdaq.hub.live.status_query import query_status
    from fleetdaq.runtime.zenoh_session import client_config

    session = zenoh.open(client_config([f"tcp/127.0.0.1:{port}"]))
    try:
        deadline = time.monotonic() + timeout
        while True:
            status = query_status(session, SiteKeys("hostile"), 5.0)
            t8 = next((s for s in (status or {}).get("streams", []) if s["stream"] == "t8"), None)
            caught_up = t8 and t8["missing"] == 0 and t8["acked"] is not None
            if caught_up and t8["last_sequence"] and t8["acked"] >= t8["last_sequence"] - 5:
                return
            assert time.monotonic() < deadline, f"the hub never caught up: {t8}"
            time.sleep(0.2)
    finally:
        session.close()


def test_hostile_traffic_never_stops_recording(tmp_path: Path):
    port = free_port()
    cfg = tmp_path / "site.yaml"
    cfg.write_text(SITE.format(port=port))
    data = tmp_path / "data"
    summary_path = tmp_path / "summary.json"
    hub = Proc(
        ["hub", "--config", str(cfg), "--data", str(data), "--summary", str(summary_path)],
        tmp_path / "hub.log",
    )
    edge = None
    try:
        wait_for_port(port)
        edge = Proc(
            ["edge", "--config", str(cfg), "--node", "wec", "--spool", str(tmp_path / "spool")],
            tmp_path / "edge.log",
        )
        attack = subprocess.run(
            [
                sys.executable,
                "-m",
                "tests.hostile_sender",
                "--port",
                str(port),
                "--site",
                "hostile",
                "--node",
                "wec",
                "--stream",
                "t8",
                "--ghost",
                "ghost",
                "--ghost-stream",
                "g",
                "--seconds",
                "15",
            ],
            cwd=REPO,
            capture_output=True,
            text=True,
            timeout=180,
            check=False,
        )
        assert attack.returncode == 0, attack.stderr[-3000:]
        sent = json.loads(attack.stdout.strip().splitlines()[-1])
        assert hub.popen.poll() is None, "the hub is still running"
        # The edge's replay (after 2 s) fills anything a flood made it miss: wait for it.
        _wait_for_no_holes(port)
        codes = [edge.terminate(), hub.terminate()]
    finally:
        if edge is not None:
            edge.kill()
        hub.kill()
    assert codes == [0, 0], hub.output()[-4000:]
    assert "Traceback" not in hub.output(), hub.output()[-6000:]
    summary = json.loads(summary_path.read_text())
    real = summary["streams"]["wec/t8"]
    ghost = summary["streams"]["ghost/g"]

    # The real stream: recorded without a gap; everything thrown at its key refused or a dup.
    assert real["batches"] > 100
    assert real["gaps"] == 0
    assert real["lost"] == 0
    assert real["malformed"] >= (sent["real_stream"] + sent["lying_floor"]) * 0.5
    assert real["duplicates"] > 0
    # The ghost stream: whatever decoded was recorded; impossible times were noticed.
    assert ghost["malformed"] > 0
    assert ghost["implausible_times"] > 0
    # Keys the site file does not define: refused at the subscriber, counted per key.
    assert summary["refused"] >= sent["unknown"] * 0.5
    assert any("/evil/" in k for k in summary["refused_keys"])
    assert summary["writer_errors"] == 0
    assert summary["failures"] == []

    # Every closed file reads back with two independent readers; the real stream's sequences
    # are contiguous across them.
    files = sorted(data.glob("*/*.mcap"))
    assert files
    assert not list(data.glob("*/*.mcap.active"))
    seqs = []
    for f in files:
        with f.open("rb") as fh:
            for _ in make_reader(fh).iter_messages():
                pass
    with AnyReader(files) as reader:
        conns = [c for c in reader.connections if c.topic == "/wec/t8"]
        for c, _, raw in reader.messages(conns):
            seqs.append(reader.deserialize(raw, c.msgtype).sequence)
    assert sorted(seqs) == list(range(len(seqs)))
    assert len(seqs) == real["batches"]
    verify = subprocess.run(
        [sys.executable, "-m", "fleetdaq", "verify", str(data)],
        cwd=REPO,
        capture_output=True,
        text=True,
        check=False,
    )
    assert verify.returncode == 0, verify.stdout + verify.stderr
