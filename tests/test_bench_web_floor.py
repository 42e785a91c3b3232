"""`bench/web_floor.py` runs end to end on short windows: the real hub and edge in a loopback-only
namespace, the sizes of the dashboard's real messages read off it, and the bare server measured
under each load. What README's account of the dashboard's CPU target rests on must at least
work."""

from __future__ import annotations

import json
import subprocess
import sys

from tests.procs import REPO


def test_web_floor_measures_every_load_against_the_budget_of_the_same_hub() -> None:
    run = subprocess.run(
        [sys.executable, str(REPO / "bench" / "web_floor.py"), "--window", "2", "--warmup", "2"],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=240,
        check=False,
    )
    assert run.returncode == 0, run.stderr[-4000:]
    result = json.loads(run.stdout.strip().splitlines()[-1])
    assert result["bench"] == "web_floor"
    f = result["figures"]
    assert f["hub_cpu_pct_without"] > 0
    assert f["budget_pct_of_a_core"] == result["targets"]["dashboard_floor_pct_at_most"]
    sizes = f["message_bytes"]
    # A delta of 4 channels is ~14 columns of float32 min/max plus its header; the state and
    # /metrics are the hub's whole view: both far larger than a frame.
    assert 200 < sizes["frame"] < 5000, sizes
    assert sizes["state"] > sizes["frame"], sizes
    assert sizes["metrics"] > sizes["frame"], sizes
    floor = f["floor_pct_of_a_core"]
    assert set(floor) == {"wake", "frames", "dashboard"}
    assert all(v > 0 for v in floor.values()), floor
    assert f["floor_over_budget"] == round(floor["dashboard"] / f["budget_pct_of_a_core"], 2)
    assert result["met"]["dashboard_floor_within_budget"] == (f["floor_over_budget"] <= 1.0)
