"""`hub.memory`: the hub's malloc settings are applied on glibc, and an operator's own
MALLOC_* environment wins."""

from __future__ import annotations

import os
import platform
import subprocess
import sys

import pytest

from tests.procs import REPO

PROBE = "from hub.memory import keep_payload_pages; print(keep_payload_pages())"


def _probe(**env: str) -> str:
    clean = {k: v for k, v in os.environ.items() if not k.startswith("MALLOC_")}
    out = subprocess.run(
        [sys.executable, "-c", PROBE],
        cwd=REPO,
        env={**clean, **env},
        capture_output=True,
        text=True,
        timeout=60,
        check=True,
    )
    return out.stdout.strip()


@pytest.mark.skipif(platform.libc_ver()[0] != "glibc", reason="mallopt is glibc's")
def test_applied_on_glibc() -> None:
    assert _probe() == "True"


def test_the_operators_environment_wins() -> None:
    assert _probe(MALLOC_TOP_PAD_="0") == "False"
