"""Fixtures for the PTP tests: one lab of network namespaces per test session, and a guard that
the host clock's frequency and status are exactly as they were before any ptp4l ran."""

from __future__ import annotations

import shutil
import subprocess
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest

from ptp.host import KernelClock, read_kernel_clock
from ptp.reader import Ptp4lReader
from ptp.status import SyncState
from tests.ptp.lab import Lab, Ptp4l, netns_possible, wait_for

SLAVE = "ptp4l-slave-software.conf"
MASTER = "ptp4l-grandmaster-software.conf"


def ensure_linuxptp() -> None:
    """Install Debian's linuxptp (and iproute2) if missing: a missing package is not a reason
    to skip."""
    missing = [p for p, exe in (("linuxptp", "ptp4l"), ("iproute2", "ip")) if not _which(exe)]
    if not missing:
        return
    if shutil.which("apt-get") is None:
        pytest.fail(f"{', '.join(missing)} missing and no apt-get to install it")
    for cmd in (["apt-get", "install", "-y", "-qq", *missing], ["apt-get", "update", "-qq"]):
        subprocess.run(cmd, check=False, capture_output=True, timeout=600)
    subprocess.run(
        ["apt-get", "install", "-y", "-qq", *missing], check=False, capture_output=True, timeout=600
    )
    still = [p for p, exe in (("linuxptp", "ptp4l"), ("iproute2", "ip")) if not _which(exe)]
    if still:
        pytest.fail(f"could not install {', '.join(still)} with apt-get")


def _which(exe: str) -> str | None:
    return shutil.which(exe) or next(
        (p for p in (f"/usr/sbin/{exe}", f"/sbin/{exe}") if Path(p).exists()), None
    )


@dataclass
class ClockMark:
    kernel: KernelClock
    realtime_minus_monotonic_ns: int


def mark() -> ClockMark:
    a = time.clock_gettime_ns(time.CLOCK_REALTIME)
    b = time.clock_gettime_ns(time.CLOCK_MONOTONIC)
    return ClockMark(read_kernel_clock(), a - b)


@pytest.fixture(scope="session")
def host_clock() -> Iterator[ClockMark]:
    """Asserts at the end that nothing touched this machine's clock."""
    before = mark()
    yield before
    after = mark()
    k0, k1 = before.kernel, after.kernel
    assert (k1.freq, k1.status, k1.tick_us, k1.tai_offset_s) == (
        k0.freq,
        k0.status,
        k0.tick_us,
        k0.tai_offset_s,
    ), f"the host clock changed: {k0} -> {k1}"
    step = after.realtime_minus_monotonic_ns - before.realtime_minus_monotonic_ns
    assert abs(step) < 5_000_000, f"CLOCK_REALTIME moved {step} ns against CLOCK_MONOTONIC"


@dataclass
class PtpLab:
    lab: Lab
    gm1_ns: str
    gm2_ns: str
    s1_ns: str
    s2_ns: str
    lone_ns: str
    gm1: Ptp4l
    s1: Ptp4l
    s2: Ptp4l
    gm2: Ptp4l | None = None
    gm1_identity: str = ""

    def start_gm1(self) -> Ptp4l:
        if not self.gm1.running:
            self.gm1 = self.lab.ptp4l(self.gm1_ns, "gm1", MASTER)
        return self.gm1

    def start_gm2(self, priority1: int = 5) -> Ptp4l:
        """A second grandmaster that beats gm1 (lower priority1)."""
        self.gm2 = self.lab.ptp4l(self.gm2_ns, "gm2", MASTER, {"priority1": str(priority1)})
        return self.gm2

    def stop_gm2(self) -> None:
        if self.gm2 is not None:
            self.gm2.stop()
            self.gm2 = None

    def identity(self, p: Ptp4l) -> str:
        with_reader = Ptp4lReader(p.uds)
        try:
            return wait_for(lambda: with_reader.read().clock_identity, 5, f"{p.name} identity")
        finally:
            with_reader.close()


def locked_to(uds: str, gm: str) -> bool:
    r = Ptp4lReader(uds)
    try:
        s = r.read()
    finally:
        r.close()
    return s.state is SyncState.LOCKED and s.grandmaster_id == gm


@pytest.fixture(scope="session")
def ptp_lab(host_clock: ClockMark, tmp_path_factory: pytest.TempPathFactory) -> Iterator[PtpLab]:
    reason = netns_possible()
    if reason is not None:
        pytest.skip(f"PTP tests need network namespaces: {reason}")
    ensure_linuxptp()
    lab = Lab(tmp_path_factory.mktemp("ptplab"))
    try:
        hosts = [lab.host(n) for n in ("gm1", "gm2", "s1", "s2")]
        lone = lab.lone_host("lone")
        gm1 = lab.ptp4l(hosts[0], "gm1", MASTER)
        s1 = lab.ptp4l(hosts[2], "s1", SLAVE)
        s2 = lab.ptp4l(hosts[3], "s2", SLAVE)
        world = PtpLab(lab, *hosts, lone, gm1, s1, s2)
        world.gm1_identity = world.identity(gm1)
        yield world
    finally:
        lab.close()


@pytest.fixture
def baseline(ptp_lab: PtpLab) -> PtpLab:
    """gm1 is the only grandmaster and both slaves are locked to it."""
    ptp_lab.stop_gm2()
    ptp_lab.start_gm1()
    ptp_lab.gm1_identity = ptp_lab.identity(ptp_lab.gm1)
    for s in (ptp_lab.s1, ptp_lab.s2):
        wait_for(lambda s=s: locked_to(s.uds, ptp_lab.gm1_identity), 20, f"{s.name} to lock")
    return ptp_lab
