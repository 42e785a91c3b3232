"""The whole way with real processes: a hub and three simulated edges record (`fleetdaq
demo`), then the recording is read with `fleetdaq.read` (checked against rosbags on the same
files), exported and reported on by the commands a person would type."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
from rosbags.highlevel import AnyReader

import fleetdaq.read as fr
from tests.procs import REPO, free_port

SITE = """\
site: e2e
hub: {{listen: [tcp/127.0.0.1:{port}], recorder: {{file_duration_s: 2}}}}
nodes:
  wec:
    streams:
      t8:
        driver: wave_sim
        rate_hz: 2000
        channels: [{{name: heave, unit: m}}, {{name: surge, unit: m}}]
  shore:
    streams:
      env: {{driver: environment_sim, rate_hz: 4, channels: [{{name: air, unit: degC}}]}}
"""


def _fleetdaq(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "fleetdaq", *args],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=180,
        check=False,
    )


def test_a_real_recording_reads_exports_and_reports(tmp_path: Path):
    site = tmp_path / "site.yaml"
    site.write_text(SITE.format(port=free_port()))
    r = _fleetdaq(
        "demo", "--config", str(site), "--duration", "5", "--data", str(tmp_path / "d"), "--json"
    )
    assert r.returncode == 0, r.stderr[-3000:]
    summary = json.loads(r.stdout)
    (session,) = (p for p in (tmp_path / "d").iterdir() if p.is_dir() and p.name[0].isdigit())
    assert {s.name for s in fr.list_streams(session)} == {"wec/t8", "shore/env"}

    t8 = fr.read_stream(session, "wec/t8")
    assert t8.channels == ("heave", "surge")
    assert t8.units == ("m", "m")
    assert len(t8) == summary["streams"]["wec/t8"]["scans"]
    assert t8.gaps == ()
    assert np.all(np.diff(t8.time_ns) > 0)
    with AnyReader([session]) as reader:
        conns = [c for c in reader.connections if c.topic == "/wec/t8"]
        msgs = [reader.deserialize(raw, c.msgtype) for c, _, raw in reader.messages(conns)]
    msgs.sort(key=lambda m: m.first_sample_time_ns)
    theirs = np.concatenate([m.data.reshape(m.scan_count, m.channel_count) for m in msgs])
    assert np.array_equal(t8.data, theirs, equal_nan=True)
    assert {h.node for h in fr.read_health(session)} >= {"wec", "shore", "hub"}
    assert fr.read_events(session)

    out = tmp_path / "pq"
    r = _fleetdaq("export", str(session), "--to", "parquet", "-o", str(out), "--quiet")
    assert r.returncode == 0, r.stderr
    # every file has every stream's columns (the other streams' are null): pick the stream's own
    df = pd.read_parquet(out / "channel=wec_t8", columns=list(t8.channels)).sort_index()
    assert np.array_equal(df.index.asi8, t8.time_ns)
    assert np.array_equal(df.to_numpy(), t8.data, equal_nan=True)

    report = tmp_path / "r.html"
    r = _fleetdaq("report", str(session), "-o", str(report), "--quiet")
    assert r.returncode == 0, r.stderr
    html = report.read_text()
    assert html.count("<svg") == 5
    assert "wec/t8" in html
    assert "shore/env" in html
