"""The readers' tier: recordings and exports opened by clients nobody on this project wrote
(pandas, pyarrow, DuckDB, polars, xarray, rosbags, mcap-ros2-support, jsonschema; the npm
Foxglove client under Node), each from an environment of its own that `make readers` builds
from tests/readers/requirements.txt and tests/readers/node/package.json. A missing reader
fails the test that needs it (it is installed by `make test`, never skipped)."""

from __future__ import annotations

import os
import subprocess
from dataclasses import dataclass
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent.parent
READERS_VENV = Path(os.environ.get("FLEETDAQ_READERS_VENV", REPO / ".venv-readers"))
NODE_DIR = REPO / "tests" / "readers" / "node"


@dataclass(frozen=True)
class Readers:
    """Runs code in the readers' own Python or Node, never the project's."""

    python: Path
    node_dir: Path

    def run(self, code: str, *args: str, cwd: Path | None = None, timeout: float = 180) -> str:
        """`code` run by the readers' Python with `args` as sys.argv[1:]; its stdout. A
        non-zero exit fails the test with what it printed."""
        done = subprocess.run(
            # -I: no PYTHONPATH, no user site, no current folder on sys.path (the repository's
            # own packages must not be found by accident)
            [str(self.python), "-I", "-c", code, *args],
            capture_output=True,
            text=True,
            cwd=cwd,
            timeout=timeout,
            check=False,
        )
        if done.returncode != 0:
            pytest.fail(f"the reader failed ({done.returncode}):\n{done.stdout}\n{done.stderr}")
        return done.stdout

    def node(self, script: Path, *args: str, timeout: float = 120) -> str:
        """`script` run by Node with the readers' node_modules; its stdout."""
        done = subprocess.run(
            ["node", str(script), *args],
            capture_output=True,
            text=True,
            timeout=timeout,
            env={**os.environ, "NODE_PATH": str(self.node_dir / "node_modules")},
            check=False,
        )
        if done.returncode != 0:
            pytest.fail(f"node failed ({done.returncode}):\n{done.stdout}\n{done.stderr}")
        return done.stdout


@pytest.fixture(scope="session")
def readers() -> Readers:
    python = READERS_VENV / "bin" / "python"
    if not python.exists():
        pytest.fail(f"no readers' environment at {READERS_VENV}: run `make readers`")
    if not (NODE_DIR / "node_modules" / "@foxglove" / "ws-protocol").is_dir():
        pytest.fail(f"no Foxglove client in {NODE_DIR}/node_modules: run `make readers`")
    return Readers(python, NODE_DIR)
