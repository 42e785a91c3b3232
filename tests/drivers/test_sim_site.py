"""System test of the driver sims: `fleetdaq demo` (hub + edges as OS processes over Zenoh on
loopback) on a site whose real drivers run on simulated transports with faults injected from
config. The recording must hold the faults as invalid samples and events, never as data, and
the unplugged T8 must come back in-process (the edge never exits for it)."""

from __future__ import annotations

import json
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from rosbags.highlevel import AnyReader

from tests.procs import REPO, free_port

SITE = """\
site: simtest
hub: {{listen: [tcp/127.0.0.1:{port}], recorder: {{file_duration_s: 30}}}}
nodes:
  wec:
    streams:
      t8:
        driver: labjack_t8
        rate_hz: 5000
        scans_per_batch: 250
        sim:
          drift_ppm: 40
          seed: 1
          faults:
            - {{kind: skipped_scans, at_s: 1.5, every_s: 2.5, for_s: 1, scans: 40}}
            - {{kind: unplug, at_s: 4.0, for_s: 0.6}}
        channels:
          - {{name: heave, unit: m, scale: 0.5}}
          - {{name: surge, unit: m}}
  am-cell:
    streams:
      tc:
        driver: max31855
        rate_hz: 8
        sim: {{seed: 2, faults: [{{kind: open_circuit, at_s: 2, for_s: 1}}]}}
        channels: [{{name: substrate, unit: degC}}, {{name: cold_junction, unit: degC}}]
    displays:
      lcd: {{sim: {{}}, lines: ["TC {{tc.substrate:6.1f}}C"]}}
  shore:
    streams:
      env:
        driver: sht3x
        rate_hz: 4
        sim: {{seed: 3, faults: [{{kind: nack, at_s: 0, probability: 0.2}}]}}
        channels: [{{name: air_temperature, unit: degC}}, {{name: humidity, unit: "%RH"}}]
"""


@pytest.fixture(scope="module")
def run(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[dict, dict]]:
    tmp = tmp_path_factory.mktemp("simsite")
    port = free_port()
    cfg = tmp / "site.yaml"
    cfg.write_text(SITE.format(port=port))
    result = subprocess.run(
        [
            sys.executable,
            "-m",
            "fleetdaq",
            "demo",
            "--config",
            str(cfg),
            # The faults are at fixed times after each edge starts (unplug at 4 s, back by ~6 s);
            # an edge may take seconds to start on a loaded machine: room for both.
            "--duration",
            "16",
            "--data",
            str(tmp / "rec"),
            "--json",
            "--listen",
            f"tcp/127.0.0.1:{port}",
        ],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert result.returncode == 0, result.stderr[-3000:]
    summary = json.loads(result.stdout)
    (session,) = [p for p in (tmp / "rec").iterdir() if p.is_dir() and p.name[:1].isdigit()]
    messages: dict[str, list] = {}
    with AnyReader(sorted(session.glob("*.mcap"))) as reader:
        for conn, _, raw in reader.messages():
            messages.setdefault(conn.topic, []).append(reader.deserialize(raw, conn.msgtype))
    return summary, messages


def _scans(batches: list) -> tuple[np.ndarray, np.ndarray]:
    data = np.concatenate([b.data.reshape(b.scan_count, b.channel_count) for b in batches])
    status = np.concatenate(
        [
            np.asarray(b.sample_status).reshape(b.scan_count, b.channel_count)
            if len(b.sample_status)
            else np.zeros((b.scan_count, b.channel_count), dtype=np.uint8)
            for b in batches
        ]
    )
    return data, status


def test_every_stream_is_recorded_without_gaps_and_no_edge_failed(run: tuple[dict, dict]) -> None:
    summary, _ = run
    assert summary["edge_failures"] == []
    for name, stream in summary["streams"].items():
        assert stream["gaps"] == 0, name
        assert stream["batches"] > 0, name


def test_skipped_scans_are_nan_with_their_status_never_data(run: tuple[dict, dict]) -> None:
    _, messages = run
    data, status = _scans(messages["/wec/t8"])
    skipped = status == 1  # SampleStatus.SKIPPED_SCAN
    assert skipped.any(axis=1).sum() >= 40
    assert np.isnan(data[skipped]).all()
    assert np.isfinite(data[~skipped]).all()


def test_the_unplugged_t8_comes_back_in_process_with_events(run: tuple[dict, dict]) -> None:
    _, messages = run
    tags = [(e.node, e.tag) for e in messages["/events"]]
    assert ("wec", "driver_error") in tags
    assert ("wec", "reconnected") in tags
    assert ("wec", "skipped_scans") in tags
    times = np.array([b.first_sample_time_ns for b in messages["/wec/t8"]])
    assert (np.diff(times) > 0).all()


def test_an_open_thermocouple_is_invalid_with_an_event_and_the_cold_junction_stays(
    run: tuple[dict, dict],
) -> None:
    _, messages = run
    data, status = _scans(messages["/am_cell/tc"])
    assert (status[:, 0] == 2).sum() >= 6  # OPEN_CIRCUIT for ~1 s at 8 Hz
    assert np.isnan(data[status[:, 0] == 2, 0]).all()
    assert (status[:, 1] == 0).all()
    assert np.isfinite(data[:, 1]).all()
    tags = [(e.node, e.tag) for e in messages["/events"]]
    assert ("am-cell", "thermocouple_fault") in tags
    assert ("am-cell", "thermocouple_fault_cleared") in tags


def test_occasional_i2c_nacks_are_retried_away(run: tuple[dict, dict]) -> None:
    _, messages = run
    data, status = _scans(messages["/shore/env"])
    assert len(data) >= 20
    assert (status == 0).mean() > 0.9
    assert np.all((data[status[:, 0] == 0, 1] > 0) & (data[status[:, 0] == 0, 1] < 100))


def test_a_cli_edge_naming_a_real_t8_without_ljm_fails_that_node_in_one_line(
    tmp_path: Path,
) -> None:
    from tests.procs import Proc, wait_for_port

    port = free_port()
    cfg = tmp_path / "site.yaml"
    cfg.write_text(
        f"site: s\nhub: {{listen: [tcp/127.0.0.1:{port}]}}\nnodes:\n"
        f"  wec:\n    spool: {{dir: {tmp_path / 'spool'}}}\n    streams:\n"
        "      t8: {driver: labjack_t8, rate_hz: 1000, channels: [{name: a}]}\n"
        f"  shore:\n    spool: {{dir: {tmp_path / 'spool'}}}\n    streams:\n"
        "      env: {driver: sht3x, rate_hz: 1, sim: {}, channels: [{name: t}]}\n"
    )
    hub = Proc(["hub", "--config", str(cfg), "--data", str(tmp_path / "d")], tmp_path / "hub.log")
    try:
        wait_for_port(port)
        r = subprocess.run(
            [sys.executable, "-m", "fleetdaq", "edge", "--config", str(cfg), "--node", "wec"],
            cwd=REPO,
            capture_output=True,
            text=True,
            timeout=60,
            check=False,
        )
        assert r.returncode == 1
        assert "Traceback" not in r.stderr
        # The agent's own log lines (timestamped) may come first; the error is one line.
        lines = [x for x in r.stderr.strip().splitlines() if not x[:4].isdigit()]
        assert len(lines) == 1, r.stderr
        assert lines[0].startswith(f"{cfg}: nodes.wec: the LabJack T8 needs")
        assert "labjack.com/ljm" in lines[0]
        other = subprocess.Popen(
            [sys.executable, "-m", "fleetdaq", "edge", "--config", str(cfg), "--node", "shore"],
            cwd=REPO,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
            text=True,
        )
        try:
            with pytest.raises(subprocess.TimeoutExpired):
                other.wait(3)  # the other node runs on, unaffected
        finally:
            other.terminate()
            other.wait(20)
        assert other.returncode == 0
    finally:
        hub.terminate()
