"""The host-clock guard itself: it fails when it should, on any host."""

from __future__ import annotations

import dataclasses
import shutil
import subprocess
from pathlib import Path

from fleetdaq.ptp.host import KernelClock
from tests.ptp.clock_guard import (
    ClockMark,
    Process,
    clock_changes,
    processes,
    ptp4l_problems,
    time_daemons,
    verdict,
)
from tests.ptp.conftest import PtpLab
from tests.ptp.lab import CAP_SYS_TIME, REFUSED, servo_refused, wait_for

UNSYNCED = KernelClock(False, 0x40, 0, 16_000_000, 16_000_000, 10_000, 0)
SYNCED = dataclasses.replace(UNSYNCED, synchronised=True, status=0x2001, maxerror_us=500)
LOCKED_LOG = f"""\
ptp4l[2138.743]: failed to set the clock status: Operation not permitted
ptp4l[2138.743]: {REFUSED}
ptp4l[2138.743]: port 1: INITIALIZING to LISTENING on INIT_COMPLETE
ptp4l[2139.735]: port 1: LISTENING to UNCALIBRATED on RS_SLAVE
ptp4l[2140.234]: {REFUSED}
ptp4l[2140.235]: port 1: UNCALIBRATED to SLAVE on MASTER_CLOCK_SELECTED
ptp4l[2140.359]: {REFUSED}
"""
MASTER_LOG = f"""\
ptp4l[2138.691]: {REFUSED}
ptp4l[2139.234]: selected local clock 7eaa70.fffe.16816a as best master
ptp4l[2139.234]: port 1: LISTENING to MASTER on ANNOUNCE_RECEIPT_TIMEOUT_EXPIRES
"""


@dataclasses.dataclass
class Started:
    name: str
    caps_seen: list[tuple[bool, bool]]
    log: str

    def output(self) -> str:
        return self.log


def _mark(kernel: KernelClock, offset: int = 0) -> ClockMark:
    return ClockMark(kernel, 1_700_000_000_000_000_000 + offset)


def test_a_locked_servo_must_show_the_kernel_refusing_it_after_locking():
    assert servo_refused(LOCKED_LOG) is True
    assert servo_refused(MASTER_LOG) is None  # never locked: its servo never ran
    # Refused only at start (clock init), nothing once the servo ran: it may have adjusted.
    lines = LOCKED_LOG.splitlines()
    allowed = "\n".join([*lines[:4], lines[5]])
    assert servo_refused(allowed) is False
    # Locked for a moment and gone before its next correction: the refusals that led to the
    # lock still show the kernel refused it.
    assert servo_refused("\n".join(lines[:-1])) is True


def test_every_ptp4l_must_lack_cap_sys_time_whenever_looked_at():
    fine = Started("s1", [(False, False), (False, False)], LOCKED_LOG)
    assert ptp4l_problems([fine, Started("gm1", [(False, False)], MASTER_LOG)]) == []
    held = Started("s2", [(False, False), (True, False)], LOCKED_LOG)
    never = Started("gm2", [], MASTER_LOG)
    adjusted = Started("s3", [(False, False)], LOCKED_LOG.replace(REFUSED, "x"))
    problems = ptp4l_problems([held, never, adjusted])
    assert [p.split(":")[0] for p in problems] == ["s2", "gm2", "s3"]


def test_any_change_of_an_undisciplined_clock_fails():
    before = _mark(UNSYNCED)
    assert verdict(before, _mark(UNSYNCED, 1_000_000), [], []).problems == []
    for after in (
        _mark(dataclasses.replace(UNSYNCED, freq=65536)),
        _mark(dataclasses.replace(UNSYNCED, status=0x2001, synchronised=True)),
        _mark(dataclasses.replace(UNSYNCED, tick_us=10_001)),
        _mark(UNSYNCED, 10_000_000),  # a 10 ms step
    ):
        result = verdict(before, after, [], [])
        assert len(result.problems) == 1, after
        assert result.not_counted == []


def test_a_host_time_service_owns_clock_changes_but_not_our_ptp4ls():
    chronyd = Process(412, "chronyd", sys_time=True)
    slewed = _mark(dataclasses.replace(SYNCED, freq=-123_456))
    held = Started("s2", [(True, True)], LOCKED_LOG)
    result = verdict(_mark(SYNCED), slewed, [chronyd], [held])
    assert result.problems == [f"s2: held CAP_SYS_TIME while running: {held.caps_seen}"]
    assert len(result.not_counted) == 1
    assert "chronyd (pid 412)" in result.not_counted[0]
    # Seen only as a kernel clock synchronised before the lab started (a container's host).
    unseen = verdict(_mark(SYNCED), slewed, [], [])
    assert unseen.problems == []
    assert "cannot see" in unseen.not_counted[0]


def test_only_time_services_that_hold_cap_sys_time_and_are_not_ours_count():
    procs = [
        Process(1, "chronyd", True),
        Process(2, "systemd-timesyn", True),
        Process(3, "ptp4l", False),  # another test run's ptp4l, under setpriv
        Process(4, "ptp4l", True),  # one of ours (by pid)
        Process(5, "phc2sys", True),
        Process(6, "python3", True),
    ]
    assert [p.pid for p in time_daemons(procs, ours={4})] == [1, 2, 5]


def test_clock_changes_name_what_moved():
    after = _mark(dataclasses.replace(UNSYNCED, freq=7, tai_offset_s=37), 6_000_000)
    assert clock_changes(_mark(UNSYNCED), after) == [
        "kernel clock frequency changed: 0 -> 7",
        "kernel clock TAI offset changed: 0 -> 37",
        "CLOCK_REALTIME moved 6000000 ns against CLOCK_MONOTONIC",
    ]


def test_processes_show_the_labs_ptp4l_without_cap_sys_time(ptp_lab: PtpLab):
    # What keeps a concurrent test run's ptp4l from counting as a host time service.
    procs = {p.pid: p for p in processes()}
    s1 = procs[ptp_lab.s1.popen.pid]
    assert (s1.comm, s1.sys_time) == ("ptp4l", False)
    assert ptp_lab.s1.popen.pid not in {p.pid for p in time_daemons(procs.values(), set())}


def test_a_process_named_like_a_time_daemon_counts_if_it_may_set_the_clock(tmp_path: Path):
    fake = tmp_path / "chronyd"  # `sleep` under a daemon's name: /proc shows that name
    shutil.copy(shutil.which("sleep") or "/bin/sleep", fake)
    own = Path("/proc/self/status").read_text()
    eff = next(int(line.split()[1], 16) for line in own.splitlines() if line.startswith("CapEff"))
    may_set_clock = bool(eff & (1 << CAP_SYS_TIME))  # inherited: root here, or not
    child = subprocess.Popen([str(fake), "30"])
    try:
        found = wait_for(
            lambda: next(
                (p for p in processes() if (p.pid, p.comm) == (child.pid, "chronyd")), None
            ),
            10,
            "the child to run as chronyd",
        )
        assert found.sys_time == may_set_clock
        daemons = time_daemons(processes(), set())
        assert (child.pid in {p.pid for p in daemons}) == may_set_clock
    finally:
        child.kill()
        child.wait()
