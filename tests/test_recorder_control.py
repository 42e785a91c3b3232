"""Recorder control by request (`fleetdaq rec status|start|stop|split|snapshot`) on a real hub and
a real sim edge, each its own process over Zenoh on loopback: every action answers with the
recorder's state, is an event naming who asked, a stopped recorder still acks the edge, and a
snapshot taken while nothing records holds the last seconds of data, read back by
`fleetdaq.read`."""

from __future__ import annotations

import getpass
import json
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from fleetdaq.read import list_streams, read_events, read_stream
from tests.procs import REPO, HubClient, Proc, free_port, stream_view, wait_for_port

SITE = """\
site: rectest
hub:
  listen: [tcp/127.0.0.1:{port}]
  recorder: {{file_duration_s: 3600, flush_interval_s: 0.2}}
  snapshot: {{seconds: 5}}
  dashboard: {{enabled: false}}
nodes:
  wec:
    streams:
      t8:
        driver: wave_sim
        rate_hz: 1000
        scans_per_batch: 50
        channels: [{{name: heave, unit: m}}, {{name: surge, unit: m}}]
"""


@pytest.fixture(scope="module")
def site(tmp_path_factory: pytest.TempPathFactory) -> Iterator[dict[str, Any]]:
    tmp = tmp_path_factory.mktemp("rec")
    port = free_port()
    cfg = tmp / "site.yaml"
    cfg.write_text(SITE.format(port=port))
    data = tmp / "data"
    procs: list[Proc] = []
    try:
        procs.append(Proc(["hub", "--config", str(cfg), "--data", str(data)], tmp / "hub.log"))
        wait_for_port(port)
        procs.append(
            Proc(
                ["edge", "--config", str(cfg), "--node", "wec", "--spool", str(tmp / "spool")],
                tmp / "wec.log",
            )
        )
        with HubClient(port, "rectest") as hub:
            hub.wait(
                lambda s: (v := stream_view(s, "wec", "t8")) and v["batches"] > 20,
                30,
                "batches from the edge",
            )
            yield {"cfg": cfg, "data": data, "hub": hub, "procs": procs}
        codes = [p.terminate() for p in reversed(procs)]
        assert codes == [0, 0], [p.output()[-3000:] for p in procs]
    finally:
        for p in procs:
            p.kill()


def rec(cfg: Path, *args: str) -> tuple[int, dict[str, Any]]:
    r = subprocess.run(
        [sys.executable, "-m", "fleetdaq", "rec", *args, "--config", str(cfg), "--json"],
        cwd=REPO,
        capture_output=True,
        check=False,
        text=True,
        timeout=180,
    )
    assert r.stdout, r.stderr
    return r.returncode, json.loads(r.stdout)


def events(status: dict[str, Any], tag: str) -> list[dict[str, Any]]:
    return [e for e in status["recent_events"] if e["tag"] == tag]


def by(event: dict[str, Any]) -> str:
    return next(kv["value"] for kv in event["fields"] if kv["key"] == "by")


def test_status_split_stop_snapshot_start(site: dict[str, Any]):
    cfg, data, hub = site["cfg"], site["data"], site["hub"]
    me = getpass.getuser()

    code, st = rec(cfg, "status")
    assert code == 0
    assert st["ok"]
    assert st["recorder"]["state"] == "recording"
    session = Path(st["recorder"]["session_dir"])
    assert st["snapshots"]["seconds"] == 5

    # Split: the file being written is closed and renamed; the next one opens.
    code, split = rec(cfg, "split", "--note", "layer 3")
    assert code == 0, split
    assert split["ok"], split
    assert split["result"].startswith("closed ")
    hub.wait(lambda s: len(s["recorder"]["files"]) == 1, 20, "one finished file")
    finished = Path(hub.status()["recorder"]["files"][0])
    assert finished.exists()
    assert finished.suffix == ".mcap"
    hub.wait(lambda s: s["recorder"]["current_file"], 20, "the next file")
    assert by(events(hub.status(), "split")[-1]).startswith(f"{me}@")

    # Stop: the session closes, an event names who stopped it, and the edge is still acked.
    code, stop = rec(cfg, "stop")
    assert code == 0
    assert stop["recorder"]["state"] == "stopped"
    stopped = events(hub.status(), "recording_stopped")
    assert stopped
    assert by(stopped[-1]).startswith(f"{me}@")
    acked_at_stop = stream_view(hub.status(), "wec", "t8")["acked"]  # type: ignore[index]
    hub.wait(
        lambda s: stream_view(s, "wec", "t8")["acked"] > acked_at_stop + 20,  # type: ignore[index]
        20,
        "acks while the recorder is stopped",
    )
    files_after_stop = sorted(session.glob("*.mcap"))
    assert not list(session.glob("*.active")), "every file is closed"

    # Snapshot with nothing being recorded: the last 5 s, read back like a recording.
    code, snap = rec(cfg, "snapshot", "--note", "after the stop")
    assert code == 0, snap
    assert snap["ok"], snap
    folder = Path(snap["result"])
    assert folder.parent == data / "snapshots"
    assert snap["snapshots"]["written"] == 1
    assert [f"{i.node}/{i.stream}" for i in list_streams(folder)] == ["wec/t8"]
    s = read_stream(folder, "wec/t8")
    span = (s.time_ns[-1] - s.time_ns[0]) / 1e9
    assert 3.0 < span <= 5.5, f"the snapshot holds the last 5 s, not {span:.1f} s"
    assert s.data.shape[1] == 2
    assert np.isfinite(s.data).all()
    assert np.all(np.diff(s.time_ns) > 0)
    assert not s.gaps, "a snapshot of a healthy stream has no gaps"
    snap_events = [e.tag for e in read_events(folder)]
    assert "recording_stopped" in snap_events, "the events of the last seconds are in it"
    assert sorted(session.glob("*.mcap")) == files_after_stop, "the stopped session is untouched"
    taken = events(hub.status(), "snapshot")
    assert taken
    assert by(taken[-1]).startswith(f"{me}@")

    # Start: a new session folder.
    code, start = rec(cfg, "start")
    assert code == 0
    assert start["recorder"]["state"] == "recording"
    assert start["recorder"]["session_dir"] != str(session)
    hub.wait(lambda s: s["recorder"]["current_file"], 20, "a file in the new session")
    assert rec(cfg, "start")[1]["result"] == "already recording"


def test_bad_requests_are_refused_with_a_reason(site: dict[str, Any]):
    r = subprocess.run(
        [sys.executable, "-m", "fleetdaq", "rec", "explode", "--config", str(site["cfg"])],
        cwd=REPO,
        capture_output=True,
        check=False,
        text=True,
        timeout=60,
    )
    assert r.returncode == 2
    assert "explode" in r.stderr
    # Straight to the hub: unknown fields and actions are refused, nothing is done.
    session = site["hub"].session
    from fleetdaq.contract.keys import SiteKeys

    key = SiteKeys("rectest").hub("recorder")
    for body, why in (
        (b'{"action": "stop", "evil": 1}', "unknown field"),
        (b'{"action": "format-disk"}', "unknown action"),
        (b"[1, 2]", "not a JSON object"),
        (b"\xff\xfe", "not JSON"),
        (b'{"action": "split", "user": "' + b"x" * 200 + b'"}', "at most 100 characters"),
    ):
        replies = list(session.get(key, payload=body, timeout=10))
        answer = json.loads(replies[0].ok.payload.to_bytes())
        assert not answer["ok"], (body, answer)
        assert why in answer["error"], (body, answer)
    assert site["hub"].status()["recorder"]["state"] == "recording"
