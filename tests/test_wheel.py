"""A wheel that runs anywhere: built from this tree, installed with the hub extra into a fresh
virtualenv, `fleetdaq demo` run from an empty directory works (the demo site, the PTP templates
and the message definitions come from the package) and leaves nothing in that directory."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import zipfile
from pathlib import Path

from tests.procs import REPO, free_port


def _run(cmd: list[str], **kw: object) -> subprocess.CompletedProcess[str]:
    r = subprocess.run(cmd, capture_output=True, text=True, check=False, **kw)  # type: ignore[call-overload]
    assert r.returncode == 0, f"{cmd}: {r.stdout[-3000:]}\n{r.stderr[-3000:]}"
    return r  # type: ignore[no-any-return]


def test_the_wheel_installs_and_runs_the_demo_from_an_empty_directory(tmp_path: Path):
    dist = tmp_path / "dist"
    _run([sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w", str(dist), str(REPO)])
    (wheel,) = dist.glob("fleetdaq-*.whl")
    names = set(zipfile.ZipFile(wheel).namelist())
    for shipped in (
        "fleetdaq/contract/config/demo.yaml",
        "fleetdaq/contract/fleetdaq_msgs/msg/SampleBatch.msg",
        "fleetdaq/contract/fleetdaq_msgs/package.xml",
        "fleetdaq/ptp/templates/ptp4l-slave-software.conf",
        "fleetdaq/cli/__init__.py",
        "fleetdaq/edge/agent.py",
        "fleetdaq/hub/runtime.py",
        "fleetdaq/hub/live/web/static/index.html",
        "fleetdaq/hub/live/web/static/app.js",
        "fleetdaq/hub/live/web/static/style.css",
    ):
        assert shipped in names, shipped
    # One import name: nothing installs a top-level `edge`, `hub` or `ptp` that another project
    # on PyPI could also install.
    top = {n.split("/")[0] for n in names if not n.startswith("fleetdaq-")}
    assert top == {"fleetdaq"}, sorted(top)

    venv = tmp_path / "venv"
    _run([sys.executable, "-m", "venv", str(venv)])
    _run([str(venv / "bin" / "pip"), "install", "-q", f"{wheel}[hub]"], timeout=900)

    empty = tmp_path / "empty"
    empty.mkdir()
    state = tmp_path / "state"
    env = {k: v for k, v in os.environ.items() if not k.startswith(("PYTHON", "VIRTUAL_ENV"))}
    env["STATE_DIRECTORY"] = str(
        state
    )  # where the demo records by default (fleetdaq.runtime.paths)
    r = subprocess.run(
        [
            str(venv / "bin" / "fleetdaq"),
            "demo",
            "--duration",
            "20",
            "--json",
            "--listen",
            f"tcp/127.0.0.1:{free_port()}",
            "--dashboard",
            "127.0.0.1:0",
            "--foxglove",
            "127.0.0.1:0",
        ],
        cwd=empty,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
    )
    assert r.returncode == 0, r.stderr[-4000:]
    summary = json.loads(r.stdout)
    assert set(summary["streams"]) == {"wec/t8", "am-cell/tc", "am-cell/robot", "shore/env"}
    for name, s in summary["streams"].items():
        assert s["batches"] > 0, name
        assert s["gaps"] == 0, name
    assert summary["files"]
    assert all(Path(f).is_relative_to(state / "demo") for f in summary["files"])
    assert list(empty.iterdir()) == [], "the demo left nothing where it ran"
    assert summary["dashboard"]["url"].startswith("http://127.0.0.1:")
    assert "log in as demo / " in r.stderr
    # How to look from another terminal: a site file that exists, and the hub's endpoint.
    hint = re.search(r"fleetdaq status --config (\S+) --connect (\S+)", r.stderr)
    assert hint, r.stderr[:2000]
    assert Path(hint[1]).is_file()
    assert hint[2].startswith("tcp/127.0.0.1:")
