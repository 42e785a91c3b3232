"""Under FLEETDAQ_REQUIRE_REAL=1 (set by .ci/run) a skipped test fails the run; without it, a
skip stays a skip (a developer's machine may lack a real part)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

from tests.procs import REPO


def _run(tmp_path: Path, require: str | None) -> subprocess.CompletedProcess[str]:
    test = tmp_path / "test_wants_a_part.py"
    test.write_text(
        "import pytest\n\ndef test_wants_a_part():\n    pytest.skip('no network namespace')\n"
    )
    env = {k: v for k, v in os.environ.items() if k != "FLEETDAQ_REQUIRE_REAL"}
    if require is not None:
        env["FLEETDAQ_REQUIRE_REAL"] = require
    return subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-p", "no:xdist", "-p", "tests.conftest",
         "--rootdir", str(tmp_path), str(test)],
        cwd=REPO, env=env, capture_output=True, text=True, timeout=120, check=False,
    )  # fmt: skip


def test_a_skip_fails_the_run_where_every_real_part_is_required(tmp_path: Path) -> None:
    done = _run(tmp_path, "1")
    assert done.returncode == 1, done.stdout
    assert "1 failed" in done.stdout
    assert "skipped under FLEETDAQ_REQUIRE_REAL=1 (a real part is missing)" in done.stdout
    assert "no network namespace" in done.stdout


def test_a_skip_stays_a_skip_elsewhere(tmp_path: Path) -> None:
    done = _run(tmp_path, None)
    assert done.returncode == 0, done.stdout
    assert "1 skipped" in done.stdout
