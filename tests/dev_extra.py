"""Vendor wrappers that pyproject's `dev` extra installs so that tests can compare our fake
transports with the real API (labjack-ljm, smbus2). `make test` installs that extra: a missing
wrapper is a broken test environment, so the checks fail instead of skipping."""

from __future__ import annotations

import contextlib
import importlib
import io
import re
import tomllib
from types import ModuleType

import pytest

from tests.procs import REPO


def _name(requirement: str) -> str:
    """The normalised distribution name of a requirement (PEP 503)."""
    match = re.match(r"[A-Za-z0-9._-]+", requirement.strip())
    assert match is not None, requirement
    return re.sub(r"[-_.]+", "-", match.group(0)).lower()


def dev_extra() -> set[str]:
    project = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]
    return {_name(r) for r in project["optional-dependencies"]["dev"]}


def vendor_module(distribution: str, module: str) -> ModuleType:
    """Import `module` of a vendor wrapper that the dev extra lists; fail if it is missing."""
    assert _name(distribution) in dev_extra(), f"{distribution} is not in the dev extra"
    try:
        # labjack-ljm prints to stdout when the native libLabJackM is missing.
        with contextlib.redirect_stdout(io.StringIO()):
            return importlib.import_module(module)
    except ImportError as err:
        pytest.fail(
            f"{distribution} is in pyproject's dev extra but cannot be imported ({err}): "
            "pip install -e '.[dev]'"
        )
