"""The `fleetdaq` command as a user runs it: demo, Ctrl-C, clear errors, a lean edge."""

from __future__ import annotations

import contextlib
import json
import signal
import socket
import subprocess
import sys
import time
from collections import deque
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from fleetdaq.hub.recording.session import ACTIVE_SUFFIX
from tests.procs import REPO, free_port

DEMO_SITE = """\
site: clitest
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
      env: {{driver: environment_sim, rate_hz: 2, channels: [{{name: air, unit: degC}}]}}
"""


def _fleetdaq(*args: str, timeout: float = 120) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "fleetdaq", *args],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=timeout,
        check=False,
    )


@pytest.fixture
def site(tmp_path: Path) -> Path:
    p = tmp_path / "site.yaml"
    p.write_text(DEMO_SITE.format(port=free_port()))
    return p


def test_demo_runs_unattended_and_prints_a_json_summary(site: Path, tmp_path: Path):
    # 10 s: on a loaded 2-core CI an edge's start (imports, first open) took over 5 s, and a
    # 5 s demo ended before its first batch.
    r = _fleetdaq(
        "demo", "--config", str(site), "--duration", "10", "--data", str(tmp_path / "rec"), "--json"
    )
    assert r.returncode == 0, r.stderr[-3000:]
    summary = json.loads(r.stdout)
    assert set(summary["streams"]) == {"wec/t8", "shore/env"}
    for name, s in summary["streams"].items():
        assert s["gaps"] == 0, name
        assert s["first_sequence"] == 0, name
        assert s["batches"] == s["last_sequence"] + 1, name
    assert summary["streams"]["wec/t8"]["samples"] >= 2000 * 2 * 3
    assert summary["files"], "files written"
    assert all(Path(f).exists() and f.endswith(".mcap") for f in summary["files"])
    assert summary["edge_failures"] == []
    assert "gaps" in r.stderr, "the table is shown"


def start_demo(site: Path, rec: Path) -> subprocess.Popen[str]:
    """The demo as a terminal runs it: its own session, so a test can signal its process group
    as the terminal would (and nothing else)."""
    return subprocess.Popen(
        [sys.executable, "-m", "fleetdaq", "demo", "--config", str(site), "--data", str(rec)],
        cwd=REPO,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
    )


@contextlib.contextmanager
def demo_and_its_edges(
    site: Path, rec: Path, recording: bool = False
) -> Iterator[tuple[subprocess.Popen[str], list[Any]]]:
    """The demo (`start_demo`) once it has started its two edges (with `recording`: and its
    first file), and their psutil processes; on the way out none of them is left running."""
    import psutil

    p = start_demo(site, rec)
    edges: list[psutil.Process] = []
    try:
        deadline = time.monotonic() + 60
        while len(edges) < 2 or (recording and not list(rec.glob("*/*.mcap" + ACTIVE_SUFFIX))):
            assert p.poll() is None, p.communicate()[1][-3000:]
            assert time.monotonic() < deadline, "the demo never started its edges (or recording)"
            edges = [c for c in psutil.Process(p.pid).children() if "edge" in " ".join(c.cmdline())]
            time.sleep(0.01)
        yield p, edges
    finally:
        if p.poll() is None:
            p.kill()
            p.wait()
        for e in edges:
            with contextlib.suppress(psutil.NoSuchProcess):
                e.kill()


def test_ctrl_c_stops_the_demo_cleanly_with_every_file_closed(site: Path, tmp_path: Path):
    rec = tmp_path / "rec"
    p = start_demo(site, rec)
    try:
        deadline = time.monotonic() + 30
        while not list(rec.glob("*/*.mcap" + ACTIVE_SUFFIX)):
            assert time.monotonic() < deadline, "the demo never started recording"
            time.sleep(0.1)
        time.sleep(2)
        # Ctrl-C in a terminal reaches the whole foreground process group.
        import os

        os.killpg(p.pid, signal.SIGINT)
        _, err = p.communicate(timeout=60)
    finally:
        if p.poll() is None:
            p.kill()
            p.wait()
    (session,) = [p for p in rec.iterdir() if p.is_dir() and p.name != "spool"]
    logs = {f.name: f.read_text()[-4000:] for f in (session / "logs").glob("*.log")}
    assert p.returncode == 0, (err[-3000:], logs)
    assert "Traceback" not in err
    assert not list(session.glob("*" + ACTIVE_SUFFIX))
    assert list(session.glob("*.mcap"))
    assert (session / "metadata.yaml").exists()


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGHUP], ids=["ctrl-c", "hangup"])
def test_a_ctrl_c_or_hangup_while_the_edges_start_stops_everything_cleanly(
    site: Path, tmp_path: Path, sig: signal.Signals
):
    """The terminal's Ctrl-C (or its closing: SIGHUP) reaches its foreground process group.
    Sent the moment the demo has started its edges, while they are still importing: the demo
    stops them, none is reported failed, none is left running."""
    import psutil

    rec = tmp_path / "rec"
    with demo_and_its_edges(site, rec) as (p, edges):
        import os

        os.killpg(p.pid, sig)
        _, err = p.communicate(timeout=60)
        _, alive = psutil.wait_procs(edges, timeout=10)
        assert alive == [], "edges left running after the demo ended"
    (session,) = [d for d in rec.iterdir() if d.is_dir() and d.name != "spool"]
    logs = {f.name: f.read_text()[-2000:] for f in (session / "logs").glob("*.log")}
    assert p.returncode == 0, (err[-3000:], logs)
    assert "failed" not in err, err[-3000:]
    assert not any("Aborted!" in log or "Traceback" in log for log in logs.values()), logs
    assert not list(session.glob("*" + ACTIVE_SUFFIX))


def test_a_demo_killed_outright_leaves_no_edge_running(site: Path, tmp_path: Path):
    """SIGKILL (or the OOM killer) gives the demo no chance to stop its edges, which run in
    process groups of their own: the kernel tells each (SIGTERM) and each stops cleanly."""
    import psutil

    rec = tmp_path / "rec"
    with demo_and_its_edges(site, rec, recording=True) as (p, edges):
        p.kill()
        p.communicate(timeout=30)
        _, alive = psutil.wait_procs(edges, timeout=30)
        assert alive == [], "edges left running after the demo was killed"
    (session,) = [d for d in rec.iterdir() if d.is_dir() and d.name != "spool"]
    logs = {f.name: f.read_text()[-2000:] for f in (session / "logs").glob("*.log")}
    assert len(logs) == len(edges), logs
    for name, text in logs.items():  # stopped as by SIGTERM: the agent's own clean stop
        assert "agent [stopped]" in text, (name, text)
        assert "Traceback" not in text, (name, text)


def test_an_edge_whose_starter_is_already_gone_stops_at_once(site: Path, tmp_path: Path):
    """`--with-parent` with a pid that is not its parent (the starter ended before the edge
    could ask to be told): the edge stops cleanly instead of running on unwatched."""
    r = _fleetdaq(
        "edge", "--config", str(site), "--node", "shore", "--spool", str(tmp_path / "spool"),
        "--with-parent", "1", timeout=60,
    )  # fmt: skip
    assert r.returncode == 0, r.stderr[-3000:]
    assert "agent [stopped]" in r.stderr


def test_unknown_node_is_one_line_and_exit_2(site: Path):
    r = _fleetdaq("edge", "--config", str(site), "--node", "buoy-7")
    assert r.returncode == 2
    assert r.stderr.strip().count("\n") == 0
    assert "buoy-7" in r.stderr
    assert str(site) in r.stderr


def test_hub_says_clearly_when_its_port_is_taken(site: Path, tmp_path: Path):
    port = int(site.read_text().split("127.0.0.1:")[1].split("]")[0])
    with socket.socket() as s:
        s.bind(("127.0.0.1", port))
        s.listen()
        r = _fleetdaq("hub", "--config", str(site), "--data", str(tmp_path / "d"), timeout=60)
    assert r.returncode == 1
    assert "cannot start the Zenoh router" in r.stderr
    assert "Traceback" not in r.stderr


def test_an_edge_loads_no_hub_code_or_hub_dependencies(site: Path, tmp_path: Path):
    """`fleetdaq edge` as a Pi runs it: the command's own module, the agent, its drivers and a
    real start (stopped by SIGTERM); nothing of the hub package or its dependencies loads."""
    code = (
        "import os, sys, signal, threading\n"
        "from fleetdaq.cli import main\n"
        "def report():\n"
        "    bad = sorted(m for m in sys.modules if m.split('.')[0] in\n"
        "                 {'hub', 'mcap', 'rich', 'zstandard', 'rosbags'})\n"
        "    print('LOADED', bad, flush=True)\n"
        "    os.kill(os.getpid(), signal.SIGTERM)\n"
        "threading.Timer(3.0, report).start()\n"
        f"main(['edge', '--config', {str(site)!r}, '--node', 'shore',"
        f" '--spool', {str(tmp_path / 'spool')!r}])\n"
    )
    r = subprocess.run(
        [sys.executable, "-c", code],
        cwd=REPO,
        capture_output=True,
        text=True,
        check=False,
        timeout=120,
    )
    assert r.returncode == 0, r.stdout + r.stderr
    assert "LOADED []" in r.stdout, r.stdout


def test_the_am_cell_lcd_shows_the_live_thermocouple_temperature(tmp_path: Path):
    """The demo's AM-cell node: its (simulated) 16x2 LCD shows the substrate temperature
    the node is acquiring — the agent feeds its displays from the newest scan."""
    from fleetdaq.contract.config.site import demo_config_path
    from fleetdaq.edge.agent import EdgeAgent
    from fleetdaq.hub.config.load import load_config

    site = load_config(demo_config_path())
    port = free_port()  # nothing listens: the agent runs without a hub
    agent = EdgeAgent(site, "am-cell", [f"tcp/127.0.0.1:{port}"], tmp_path / "spool")
    with agent:
        # Before the thermocouple opens (12 s after start in the demo site).
        deadline = time.monotonic() + 10
        (display,) = agent.displays
        lcd = display.smbus.buses[1][0x27]  # the simulated LCD the driver table attached
        # The LCD shows what was newest when it last refreshed (2 Hz) and the value moves at
        # 4 Hz, so it may trail the newest by a scan or two: any of the last few values is live.
        recent: deque[str] = deque(maxlen=12)
        while True:
            value = agent.latest_value("tc", "substrate")
            if value is not None and (not recent or recent[-1] != f"{value:7.2f}".strip()):
                recent.append(f"{value:7.2f}".strip())
            shown = lcd.lines()
            if "TC" in shown[0] and any(v in shown[0] for v in recent):
                break
            assert time.monotonic() < deadline, (list(recent), shown)
            time.sleep(0.05)
