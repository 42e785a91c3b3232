"""systemd's notify protocol, against a real datagram socket standing in for systemd: READY and
STATUS at start, WATCHDOG pings only while the real work loops move (a stalled recorder writer
withholds them, so systemd would restart the hub), STOPPING at a stop; the edge process too."""

from __future__ import annotations

import socket
import subprocess
import sys
import threading
from collections.abc import Iterator
from pathlib import Path

import pytest

from fleetdaq.hub.config.load import parse_config
from fleetdaq.hub.runtime import HubRuntime
from fleetdaq.runtime.systemd import Beat, Systemd
from tests.procs import REPO, free_port, wait_until

SITE = """\
site: sd
hub:
  listen: [tcp/127.0.0.1:{port}]
nodes:
  wec:
    streams:
      t8: {{driver: wave_sim, rate_hz: 100, channels: [{{name: a}}]}}
"""


class FakeSystemd:
    """A Unix datagram socket collecting what a service sends to $NOTIFY_SOCKET."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self.sock.bind(str(path))
        self.sock.settimeout(0.2)
        self.messages: list[str] = []
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                data = self.sock.recv(65536)
            except TimeoutError:
                continue
            except OSError:
                return
            with self._lock:
                self.messages.extend(data.decode().split("\n"))

    def got(self) -> list[str]:
        with self._lock:
            return list(self.messages)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2)
        self.sock.close()


@pytest.fixture
def systemd(tmp_path: Path) -> Iterator[FakeSystemd]:
    fake = FakeSystemd(tmp_path / "notify.sock")
    yield fake
    fake.close()


def test_a_loop_that_stops_moving_withholds_the_ping(systemd: FakeSystemd):
    sd = Systemd({"NOTIFY_SOCKET": str(systemd.path), "WATCHDOG_USEC": "600000"})
    moving, stuck = sd.beat("mover"), sd.beat("stuck")
    assert isinstance(moving, Beat)
    stop = threading.Event()

    def mover() -> None:
        while not stop.wait(0.02):
            moving.beat()
            stuck.beat()

    t = threading.Thread(target=mover, daemon=True)
    t.start()
    sd.ready("up")
    try:
        wait_until(lambda: systemd.got().count("WATCHDOG=1") >= 3, 10, "pings while all move")
        assert systemd.got()[:2] == ["READY=1", "STATUS=up"]
        stuck.quiet(0)  # from now on only "mover" beats
        stop.set()
        t.join()
        keep = threading.Event()

        def only_mover() -> None:
            while not keep.wait(0.02):
                moving.beat()

        t2 = threading.Thread(target=only_mover, daemon=True)
        t2.start()
        wait_until(lambda: any("STATUS=stalled: stuck" in m for m in systemd.got()), 10, "stall")
        at_stall, tick = len(systemd.got()), sd.ticks
        wait_until(lambda: sd.ticks >= tick + 3, 10, "three watchdog periods")
        after = systemd.got()[at_stall:]
        assert "WATCHDOG=1" not in after, after
        stuck.beat()  # it moves again: the pings come back
        wait_until(lambda: "WATCHDOG=1" in systemd.got()[at_stall:], 10, "pings again")
        keep.set()
        t2.join()
    finally:
        sd.stopping()
    # STOPPING is the last thing said (the receiver gets it on its own thread: wait for it)
    wait_until(lambda: "STOPPING=1" in systemd.got(), 10, "STOPPING")
    assert systemd.got()[-2:] == ["STOPPING=1", "STATUS=stopping"]


def test_a_stalled_recorder_writer_stops_the_hubs_pings(
    systemd: FakeSystemd, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
):
    monkeypatch.setenv("NOTIFY_SOCKET", str(systemd.path))
    monkeypatch.setenv("WATCHDOG_USEC", "900000")
    site = parse_config(SITE.format(port=free_port()), "<test>")
    hub = HubRuntime(site, tmp_path / "data")
    hub.start()
    try:
        wait_until(lambda: "READY=1" in systemd.got(), 10, "READY")
        status = next(m for m in systemd.got() if m.startswith("STATUS="))
        assert "recording" in status
        assert "0/1 nodes alive" in status
        wait_until(lambda: systemd.got().count("WATCHDOG=1") >= 2, 10, "pings")
        with hub.recorder.lock:  # the writer loop blocks on its next turn
            wait_until(
                lambda: any("stalled: recorder writer" in m for m in systemd.got()), 20, "stall"
            )
            at_stall, tick = len(systemd.got()), hub.systemd.ticks
            wait_until(lambda: hub.systemd.ticks >= tick + 3, 10, "three watchdog periods")
            assert "WATCHDOG=1" not in systemd.got()[at_stall:]
        wait_until(lambda: "WATCHDOG=1" in systemd.got()[at_stall:], 10, "pings again")
    finally:
        hub.close()
    wait_until(lambda: "STOPPING=1" in systemd.got(), 10, "STOPPING from the hub")


def test_the_edge_process_says_ready_with_its_status(systemd: FakeSystemd, tmp_path: Path):
    cfg = tmp_path / "site.yaml"
    cfg.write_text(SITE.format(port=free_port()))
    env = {
        **__import__("os").environ,
        "NOTIFY_SOCKET": str(systemd.path),
        "WATCHDOG_USEC": "3000000",
    }
    p = subprocess.Popen(
        [sys.executable, "-m", "fleetdaq", "edge", "--config", str(cfg), "--node", "wec",
         "--spool", str(tmp_path / "spool")],
        cwd=REPO,
        env=env,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )  # fmt: skip
    try:
        wait_until(lambda: "READY=1" in systemd.got(), 30, "READY from the edge")
        status = next(m for m in systemd.got() if m.startswith("STATUS="))
        assert status.startswith("STATUS=node wec: t8 ")
        assert "hub not reachable" in status or "hub connected" in status
        wait_until(lambda: "WATCHDOG=1" in systemd.got(), 10, "the acquisition loop's pings")
    finally:
        p.terminate()
        assert p.wait(30) == 0
    wait_until(lambda: "STOPPING=1" in systemd.got(), 10, "STOPPING from the edge")
