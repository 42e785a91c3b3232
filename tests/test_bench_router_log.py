"""bench/router_log.py runs and reports what it measured (its figures, not a speed limit)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent


def test_the_router_log_bench_measures_the_tap_against_a_bare_drain() -> None:
    done = subprocess.run(
        [sys.executable, str(REPO / "bench" / "router_log.py"), "--lines", "6400"],
        capture_output=True,
        text=True,
        timeout=120,
        check=True,
    )
    result = json.loads(done.stdout.strip().splitlines()[-1])
    figures = result["figures"]
    assert figures["lines"] == 6400
    assert figures["tap_us_per_line"] > 0
    assert figures["drain_us_per_line"] > 0
    assert set(result["met"]) == set(result["targets"]) == {"tap_core_share_at_load"}
    assert "tap: 6400 lines" in done.stderr
