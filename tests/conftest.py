"""`make test` runs the tests on two pytest-xdist workers. Each test module stays on one worker,
so its module fixtures (a deploy lab, a hub with its edges, a browser) are made once and its
tests run in file order; the PTP tests share one lab of ptp4l processes and the session's
guard on the host clock, so they all run on one worker.

The grouping is a scheduler of our own (xdist's `pytest_xdist_make_scheduler` hook): xdist's
``--dist loadgroup`` ignores ``xdist_group`` marks under pytest 9 (every test of a group was
spread over both workers), and ``--dist loadfile`` would make two PTP labs."""

from __future__ import annotations

import os
from typing import Any

import pytest
from xdist.scheduler import LoadScopeScheduling

SHARED_SESSION = ("tests/ptp/",)
"""Folders whose modules share session fixtures: all of a folder's tests run on one worker."""


def scope_of(nodeid: str) -> str:
    """The unit a worker takes whole: a test's module, or a folder of `SHARED_SESSION`."""
    module = nodeid.split("::", 1)[0]
    return next((folder for folder in SHARED_SESSION if module.startswith(folder)), module)


class ByModule(LoadScopeScheduling):
    def _split_scope(self, nodeid: str) -> str:
        return scope_of(nodeid)


class Scheduling:
    """Registered only when xdist is loaded (``-p no:xdist`` does not know its hook)."""

    @staticmethod
    def pytest_xdist_make_scheduler(config: pytest.Config, log: Any) -> ByModule:
        return ByModule(config, log)


def pytest_configure(config: pytest.Config) -> None:
    if config.pluginmanager.hasplugin("xdist"):
        config.pluginmanager.register(Scheduling(), "fleetdaq-scheduling")


REQUIRE_REAL = "FLEETDAQ_REQUIRE_REAL"
"""Set (to 1) by .ci/run: there every real part (namespaces, mounts, Chromium, sshd, ptp4l) is
installed, so a test that skips for want of one is a failure, never a green run that hid it."""


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item: pytest.Item, call: pytest.CallInfo[None]) -> Any:
    outcome = yield
    report = outcome.get_result()
    if report.skipped and os.environ.get(REQUIRE_REAL) == "1" and not hasattr(report, "wasxfail"):
        reason = report.longrepr[2] if isinstance(report.longrepr, tuple) else report.longrepr
        report.outcome = "failed"
        report.longrepr = f"skipped under {REQUIRE_REAL}=1 (a real part is missing): {reason}"
