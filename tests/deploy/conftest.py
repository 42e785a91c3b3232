"""Fixtures for the deploy tests: the wheelhouse the playbook installs from (built once per
session), and the Ansible commands of this venv."""

from __future__ import annotations

import hashlib
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from tests.procs import REPO

BIN = Path(sys.executable).parent
ANSIBLE = REPO / "ansible"
DEPS_CACHE = REPO / "build" / "test-wheelhouse"
"""Dependency wheels, kept between sessions (keyed by pyproject.toml's dependencies)."""


def _run(cmd: list[str], timeout: float) -> None:
    r = subprocess.run(cmd, capture_output=True, text=True, check=False, timeout=timeout)
    assert r.returncode == 0, f"{cmd}: {r.stdout[-3000:]}\n{r.stderr[-3000:]}"


@pytest.fixture(scope="session")
def wheelhouse(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """What `make wheelhouse EXTRAS=` makes: fleetdaq's wheel, built from this tree, and the
    wheels of its dependencies (no extra: the test hosts run neither the hub's extras nor
    hardware). The dependencies are downloaded once and kept in build/test-wheelhouse."""
    folder = tmp_path_factory.mktemp("wheelhouse")
    _run(
        [sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w", str(folder), str(REPO)],
        timeout=600,
    )
    (wheel,) = folder.glob("fleetdaq-*.whl")
    text = (REPO / "pyproject.toml").read_text()
    deps = text[text.index("dependencies = [") : text.index("[project.optional-dependencies]")]
    cache = DEPS_CACHE / hashlib.sha256(deps.encode()).hexdigest()[:16]
    if not (cache / "complete").exists():
        shutil.rmtree(cache, ignore_errors=True)
        cache.mkdir(parents=True)
        _run(
            [
                sys.executable,
                "-m",
                "pip",
                "download",
                "-q",
                "--only-binary=:all:",
                "--dest",
                str(cache),
                str(wheel),
            ],
            timeout=600,
        )
        (cache / wheel.name).unlink()
        (cache / "complete").touch()
    for dep in cache.glob("*.whl"):
        shutil.copy2(dep, folder / dep.name)
    return folder
