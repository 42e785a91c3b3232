"""The PTP tests' guard on the host clock: proof that no ptp4l of ours could touch it.

Two proofs, checked when the test session ends:

- Ours could not: every ptp4l the lab started lacked CAP_SYS_TIME (bounding set and effective)
  each time /proc was read while it ran, and every one that locked logged the kernel refusing
  its corrections ("failed to adjust the clock: Operation not permitted") after locking. This
  holds on any host, whatever else runs there.
- Nobody did: the kernel's frequency, status, tick and TAI offset, and CLOCK_REALTIME against
  CLOCK_MONOTONIC (a step), are as they were before. Only meaningful where nothing else
  disciplines the clock. Where a host time service may (a chronyd, ntpd, systemd-timesyncd,
  ptp4l or phc2sys holding CAP_SYS_TIME that the tests did not start, or a kernel clock that
  was already synchronised before any ptp4l of ours ran, e.g. by the host of a container), a
  change is that service's doing: it is reported, not failed.
"""

from __future__ import annotations

import re
import time
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

from fleetdaq.ptp.host import KernelClock, read_kernel_clock
from tests.ptp.lab import CAP_SYS_TIME, servo_refused

TIME_DAEMONS = frozenset(
    {
        "chronyd",
        "ntpd",
        "ntpdate",
        "sntp",
        "openntpd",
        "ntp-daemon",  # ntpd-rs
        "systemd-timesyn",  # systemd-timesyncd: /proc/<pid>/comm keeps 15 characters
        "htpdate",
        "ptp4l",
        "phc2sys",
        "ts2phc",
        "timemaster",
    }
)
"""Programs that discipline CLOCK_REALTIME (as /proc/<pid>/comm names them)."""
MAX_STEP_NS = 5_000_000
"""CLOCK_REALTIME - CLOCK_MONOTONIC read twice, a moment apart, agrees within this."""


@dataclass(frozen=True, slots=True)
class Process:
    pid: int
    comm: str
    sys_time: bool
    """CAP_SYS_TIME is in its effective set: it could set or adjust the clock."""


def processes() -> list[Process]:
    """Every process this PID namespace shows, with its CAP_SYS_TIME."""
    out = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            status = (entry / "status").read_text()
        except OSError:
            continue  # gone meanwhile, or not ours to read
        name = re.search(r"^Name:\s*(.*)$", status, re.M)
        eff = re.search(r"^CapEff:\s*([0-9a-f]+)$", status, re.M)
        if name and eff:
            has = bool(int(eff.group(1), 16) & (1 << CAP_SYS_TIME))
            out.append(Process(int(entry.name), name.group(1).strip(), has))
    return out


def time_daemons(procs: Iterable[Process], ours: set[int]) -> list[Process]:
    """Time services that may move the clock: not started by the tests, holding CAP_SYS_TIME
    (another test run's ptp4l under setpriv cannot touch the clock either)."""
    return [p for p in procs if p.comm in TIME_DAEMONS and p.sys_time and p.pid not in ours]


@dataclass(frozen=True, slots=True)
class ClockMark:
    kernel: KernelClock
    realtime_minus_monotonic_ns: int


def mark() -> ClockMark:
    a = time.clock_gettime_ns(time.CLOCK_REALTIME)
    b = time.clock_gettime_ns(time.CLOCK_MONOTONIC)
    return ClockMark(read_kernel_clock(), a - b)


def clock_changes(before: ClockMark, after: ClockMark) -> list[str]:
    """What differs in the host clock between two marks (empty: untouched)."""
    k0, k1 = before.kernel, after.kernel
    out = [
        f"kernel clock {what} changed: {a} -> {b}"
        for what, a, b in (
            ("frequency", k0.freq, k1.freq),
            ("status", hex(k0.status), hex(k1.status)),
            ("tick", k0.tick_us, k1.tick_us),
            ("TAI offset", k0.tai_offset_s, k1.tai_offset_s),
        )
        if a != b
    ]
    step = after.realtime_minus_monotonic_ns - before.realtime_minus_monotonic_ns
    if abs(step) >= MAX_STEP_NS:
        out.append(f"CLOCK_REALTIME moved {step} ns against CLOCK_MONOTONIC")
    return out


class StartedPtp4l(Protocol):
    name: str
    caps_seen: list[tuple[bool, bool]]

    def output(self) -> str: ...


def ptp4l_problems(started: Iterable[StartedPtp4l]) -> list[str]:
    """Why a ptp4l of ours might have touched the clock (empty: none could)."""
    out = []
    for p in started:
        if not p.caps_seen:
            out.append(f"{p.name}: its capabilities were never read while it ran")
        elif any(bounded or effective for bounded, effective in p.caps_seen):
            out.append(f"{p.name}: held CAP_SYS_TIME while running: {p.caps_seen}")
        if servo_refused(p.output()) is False:
            out.append(
                f"{p.name}: locked, but its log shows no refused clock correction after "
                "locking: the kernel may have let it adjust the clock"
            )
    return out


@dataclass(frozen=True, slots=True)
class Verdict:
    problems: list[str]
    """What fails the session."""
    not_counted: list[str]
    """Clock changes left to a host time service, and which one."""


def verdict(
    before: ClockMark, after: ClockMark, daemons: list[Process], started: Iterable[StartedPtp4l]
) -> Verdict:
    problems = ptp4l_problems(started)
    changes = clock_changes(before, after)
    services = [f"{d.comm} (pid {d.pid})" for d in daemons]
    if before.kernel.synchronised:
        services.append(
            "a time service this test cannot see (the kernel clock was synchronised before "
            "any ptp4l of ours ran)"
        )
    if not services:
        return Verdict(problems + changes, [])
    note = f"left to {', '.join(services)}"
    return Verdict(problems, [f"{c} ({note})" for c in changes])
