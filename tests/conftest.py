"""`make test` runs the tests on two pytest-xdist workers (`--dist loadgroup`). Each test
module stays on one worker, so its module fixtures (a deploy lab, a hub with its edges, a
browser) are made once; the PTP tests share one lab of ptp4l processes and the session's
guard on the host clock, so they all run on one worker."""

from __future__ import annotations

import pytest

SHARED_SESSION = {"tests/ptp": "ptp"}
"""Folders whose modules share session fixtures: one group (one worker) each."""


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    for item in items:
        if item.get_closest_marker("xdist_group") is not None:
            continue
        module = item.nodeid.split("::", 1)[0]
        group = next(
            (g for folder, g in SHARED_SESSION.items() if module.startswith(folder + "/")), module
        )
        item.add_marker(pytest.mark.xdist_group(group))
