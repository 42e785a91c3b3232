"""Threads carry their names into the operating system: `top -H` on a hub shows "recorder" and
"dashboard", not thirty lines of "python"."""

from __future__ import annotations

import threading
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest

from fleetdaq.runtime.threads import NamedThread, name_os_thread, os_name
from tests.procs import Proc, free_port, wait_until
from tests.web.test_hub_dashboard import SITE as HUB_SITE  # a hub with its dashboard on


def comm(tid: int, pid: str = "self") -> str:
    return Path(f"/proc/{pid}/task/{tid}/comm").read_text().rstrip("\n")


def test_a_name_is_cut_to_what_the_kernel_keeps_without_splitting_a_character():
    assert os_name("recorder") == "recorder"
    assert os_name("feed-live-plots") == "feed-live-plots"  # 15 bytes: all kept
    assert os_name("partition-report") == "partition-repor"
    assert os_name("température-capteur") == "température-ca"  # é is 2 bytes
    assert os_name("stream-ééééééé") == "stream-éééé"  # a 16th byte mid-character is left out


def test_a_named_thread_shows_its_name_to_the_operating_system():
    seen: list[str] = []
    t = NamedThread(target=lambda: seen.append(comm(threading.get_native_id())), name="stream-t8")
    t.start()
    t.join(10)
    assert seen == ["stream-t8"]


def test_a_pool_names_its_workers_through_its_initializer():
    with ThreadPoolExecutor(1, thread_name_prefix="rule-actions", initializer=name_os_thread) as p:
        assert p.submit(lambda: comm(threading.get_native_id())).result(10) == "rule-actions_0"


@pytest.mark.timeout(90)
def test_a_running_hub_names_its_threads(tmp_path: Path):
    site = tmp_path / "site.yaml"
    site.write_text(HUB_SITE.format(router=free_port(), port=free_port()))
    hub = Proc(
        ["hub", "--config", str(site), "--data", str(tmp_path / "data")], tmp_path / "hub.log"
    )
    try:
        wait_until(lambda: "dashboard on" in hub.output(), 60, "the hub's dashboard")
        pid = str(hub.popen.pid)
        names = {comm(int(t.name), pid) for t in Path(f"/proc/{pid}/task").iterdir()}
    finally:
        hub.terminate()
    expected = {
        "recorder",
        "dashboard",
        "feed-live-plots",
        "supervisor",
        "rules",
        "heartbeat",
        "hub-health",
        "bus-event-log",
        "bus-recorder",
        "notify-policy",
    }
    assert expected <= names, f"missing: {sorted(expected - names)}; all: {sorted(names)}"
