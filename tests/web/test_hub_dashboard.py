"""The dashboard as part of the hub process: a taken port stops the hub with one line."""

from __future__ import annotations

import socket
import subprocess
import sys
from pathlib import Path

from tests.procs import REPO, free_port

SITE = """\
site: webport
hub:
  listen: [tcp/127.0.0.1:{router}]
  dashboard: {{enabled: true, listen: "127.0.0.1:{port}"}}
nodes:
  wec:
    streams:
      t8: {{driver: wave_sim, rate_hz: 100, channels: [{{name: heave, unit: m}}]}}
"""


def test_a_hub_whose_dashboard_port_is_taken_does_not_start_and_says_why_in_one_line(
    tmp_path: Path,
):
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        port = s.getsockname()[1]
        site = tmp_path / "site.yaml"
        site.write_text(SITE.format(router=free_port(), port=port))
        r = subprocess.run(
            [sys.executable, "-m", "fleetdaq", "hub", "--config", str(site), "--data",
             str(tmp_path / "data")],
            cwd=REPO, capture_output=True, text=True, timeout=120, check=False,
        )  # fmt: skip
    assert r.returncode == 1
    assert "Traceback" not in r.stderr
    last = r.stderr.strip().splitlines()[-1]
    assert last == (
        f"dashboard: cannot listen on 127.0.0.1:{port}: the address is in use (another hub or "
        "program); set hub.dashboard.listen to a free port, or hub.dashboard.enabled: false"
    )
