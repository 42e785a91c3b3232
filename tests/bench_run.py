"""Running one bench script as its own process, the way `make bench` does, and reading the one
JSON line it ends with: what the `tests/test_bench_*.py` smoke tests share."""

from __future__ import annotations

import json
import subprocess
import sys
from typing import Any

from tests.procs import REPO


def run_bench(script: str, *args: str, timeout: float) -> dict[str, Any]:
    """`python bench/<script> ARGS`: it exits 0, and its last stdout line is its result, named
    after the script."""
    run = subprocess.run(
        [sys.executable, str(REPO / "bench" / script), *args],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=timeout,
        check=False,
    )
    assert run.returncode == 0, run.stderr[-4000:]
    result: dict[str, Any] = json.loads(run.stdout.strip().splitlines()[-1])
    assert result["bench"] == script.removesuffix(".py")
    return result
