"""Fixtures for the PTP tests: one lab of network namespaces per test session, and a guard on the
host clock: no ptp4l of ours could touch it, and (where no host time service may have) its
frequency and status are exactly as they were before any ptp4l ran."""

from __future__ import annotations

import shutil
import subprocess
import warnings
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest

from fleetdaq.ptp.reader import Ptp4lReader
from fleetdaq.ptp.time_status import SyncState
from tests.ptp import clock_guard as guard
from tests.ptp.clock_guard import ClockMark, mark
from tests.ptp.lab import STARTED, Lab, Ptp4l, netns_possible, wait_for

SLAVE = "ptp4l-slave-software.conf"
MASTER = "ptp4l-grandmaster-software.conf"


TOOLS = (("linuxptp", "ptp4l"), ("iproute2", "ip"), ("ethtool", "ethtool"))
"""Debian packages the PTP tests run, with the command each provides."""


def ensure_linuxptp() -> None:
    """Install Debian's linuxptp, iproute2 and ethtool if missing: a missing package is not a
    reason to skip (`.ci/run` installs them too)."""
    missing = [p for p, exe in TOOLS if not tool_path(exe)]
    if not missing:
        return
    if shutil.which("apt-get") is None:
        pytest.fail(f"{', '.join(missing)} missing and no apt-get to install it")
    for cmd in (["apt-get", "install", "-y", "-qq", *missing], ["apt-get", "update", "-qq"]):
        subprocess.run(cmd, check=False, capture_output=True, timeout=600)
    subprocess.run(
        ["apt-get", "install", "-y", "-qq", *missing], check=False, capture_output=True, timeout=600
    )
    still = [p for p, exe in TOOLS if not tool_path(exe)]
    if still:
        pytest.fail(f"could not install {', '.join(still)} with apt-get")


def tool_path(exe: str) -> str | None:
    return shutil.which(exe) or next(
        (p for p in (f"/usr/sbin/{exe}", f"/sbin/{exe}") if Path(p).exists()), None
    )


@pytest.fixture(scope="session")
def host_clock() -> Iterator[ClockMark]:
    """Proves at the end that no ptp4l of ours could touch this machine's clock, and that
    nothing did where no host time service may have (tests/ptp/clock_guard.py)."""
    before = mark()
    seen = {p.pid: p for p in guard.processes()}
    yield before
    after = mark()
    seen.update({p.pid: p for p in guard.processes()})
    ours = {p.popen.pid for p in STARTED}
    daemons = guard.time_daemons(seen.values(), ours)
    result = guard.verdict(before, after, daemons, STARTED)
    for note in result.not_counted:
        warnings.warn(f"host clock: {note}", stacklevel=1)
    assert not result.problems, "the host clock guard failed:\n" + "\n".join(result.problems)


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
