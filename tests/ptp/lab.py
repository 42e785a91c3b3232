"""A PTP lab in network namespaces: real ptp4l processes on veth links joined by a bridge.

Safety, in order of importance:
- every ptp4l runs under ``setpriv --bounding-set=-sys_time --inh-caps=-sys_time``: the kernel
  refuses any change to the (shared) system clock while the servo still locks; the lab checks
  the bound once before starting anything and on every ptp4l it starts;
- software timestamping only, traffic only on links inside namespaces the lab created
  (10.231.0.0/24 exists nowhere else; nothing is routed to or from the host);
- names carry this process's pid; `close()` ends only the processes the lab started (by pid)
  and deletes only the namespaces it created (plus leftovers of earlier runs whose pid is gone).

Every ptp4l started is kept in `STARTED`, with what /proc said about its CAP_SYS_TIME each time
it was looked at while running (at start, and again before it is stopped); the session's clock
guard (tests/ptp/conftest.py) proves from these and from each log that no ptp4l of ours could
touch the host clock, whatever the host's own time service does meanwhile.
"""

from __future__ import annotations

import contextlib
import os
import re
import shutil
import signal
import subprocess
import time
from collections.abc import Callable
from pathlib import Path
from typing import IO, TypeVar

REPO = Path(__file__).resolve().parent.parent.parent
TEMPLATES = REPO / "ptp" / "templates"
SETPRIV = ["setpriv", "--bounding-set=-sys_time", "--inh-caps=-sys_time"]
DIE_WITH_US = ["--pdeathsig=KILL"]
"""setpriv option: if pytest itself is killed, its ptp4l processes die with it."""
CAP_SYS_TIME = 25
PREFIX = "fdqptp"
REFUSED = "failed to adjust the clock: Operation not permitted"
"""What ptp4l logs each time the kernel refuses a servo correction (clock_adjtime, EPERM)."""

# Fast intervals for tests: lock within ~2 s, notice a lost master within ~0.75 s. The PI
# constants make the servo lock after two samples instead of waiting ~16 s to estimate the
# frequency (software timestamping's default); its corrections are refused anyway.
FAST = {
    "logSyncInterval": "-3",
    "logAnnounceInterval": "-2",
    "logMinDelayReqInterval": "-3",
    "announceReceiptTimeout": "2",
    "pi_proportional_const": "0.7",
    "pi_integral_const": "0.3",
    "use_syslog": "0",
    "verbose": "1",
    "summary_interval": "4",
}

T = TypeVar("T")


def wait_for(probe: Callable[[], T | None], timeout: float, what: str, every: float = 0.05) -> T:
    """Poll `probe` until it returns something truthy; fail with `what` after `timeout`."""
    deadline = time.monotonic() + timeout
    while True:
        value = probe()
        if value:
            return value
        if time.monotonic() >= deadline:
            raise AssertionError(f"timed out after {timeout:g} s waiting for {what}")
        time.sleep(every)


def run(*args: str) -> str:
    done = subprocess.run(args, capture_output=True, text=True, check=False, timeout=30)
    if done.returncode != 0:
        raise RuntimeError(f"{' '.join(args)}: {done.stderr.strip() or done.stdout.strip()}")
    return done.stdout


def netns_possible() -> str | None:
    """None if this machine can create network namespaces, else why not."""
    if shutil.which("ip") is None:
        return "no `ip` command (iproute2)"
    probe = f"{PREFIX}{os.getpid()}-probe"
    try:
        run("ip", "netns", "add", probe)
    except (RuntimeError, OSError) as err:
        return f"cannot create a network namespace here: {err}"
    with contextlib.suppress(RuntimeError):
        run("ip", "netns", "del", probe)
    return None


def sys_time_capability(pid: int | str) -> tuple[bool, bool]:
    """(in the bounding set, effective) for CAP_SYS_TIME of a process."""
    text = Path(f"/proc/{pid}/status").read_text()
    caps = dict(re.findall(r"^(Cap\w+):\s+([0-9a-f]+)$", text, re.M))
    bit = 1 << CAP_SYS_TIME
    return bool(int(caps["CapBnd"], 16) & bit), bool(int(caps["CapEff"], 16) & bit)


def check_setpriv() -> None:
    """setpriv must really drop CAP_SYS_TIME before any ptp4l starts."""
    out = run(*SETPRIV, "cat", "/proc/self/status")
    caps = dict(re.findall(r"^(Cap\w+):\s+([0-9a-f]+)$", out, re.M))
    bit = 1 << CAP_SYS_TIME
    if int(caps["CapBnd"], 16) & bit or int(caps["CapEff"], 16) & bit:
        raise AssertionError("setpriv did not drop CAP_SYS_TIME: refusing to start ptp4l")


def remove_stale_namespaces() -> None:
    """Namespaces left by an earlier run of these tests that was killed before cleaning up."""
    for line in run("ip", "netns", "list").splitlines():
        m = re.match(rf"^({PREFIX}(\d+)-\S+)", line)
        if m and not Path(f"/proc/{m.group(2)}").exists():
            subprocess.run(["ip", "netns", "del", m.group(1)], check=False, capture_output=True)


def servo_refused(log: str) -> bool | None:
    """Whether the kernel refused this ptp4l's clock corrections once it was locked.

    None when it never locked (a grandmaster, or a slave that heard no master): its servo never
    ran. Otherwise True only if ptp4l logged a refused adjustment once its servo ran: from the
    UNCALIBRATED state that led to its first SLAVE (the servo's first corrections, which it
    needs to lock at all) onwards. A ptp4l allowed to adjust the clock logs nothing there.
    (Not from SLAVE on only: a grandmaster that is SLAVE to a better one for a moment before it
    goes away may never make another correction after locking.)
    """
    locked = re.search(r"^.*\bto SLAVE\b.*$", log, re.M)
    if locked is None:
        return None
    servo = log.rfind("to UNCALIBRATED", 0, locked.start())
    return REFUSED in log[servo if servo >= 0 else locked.end() :]


class Ptp4l:
    """One ptp4l in a namespace, under setpriv, logging to a file."""

    def __init__(
        self, ns: str, name: str, template: str, options: dict[str, str], tmp: Path
    ) -> None:
        self.name = name
        self.ns = ns
        self.uds = str(tmp / f"{name}.sock")
        self.log_path = tmp / f"{name}.log"
        self._log_from = self.log_path.stat().st_size if self.log_path.exists() else 0
        self._log: IO[bytes] = self.log_path.open("ab")
        self.caps_seen: list[tuple[bool, bool]] = []
        """(in the bounding set, effective) for CAP_SYS_TIME, each time it was looked at."""
        opts = {**FAST, **options, "uds_address": self.uds}
        exe = shutil.which("ptp4l") or "/usr/sbin/ptp4l"
        args = [exe, "-f", str(TEMPLATES / template), "-i", "eth0", "-m"]
        args += [f"--{k}={v}" for k, v in opts.items()]
        self.popen = subprocess.Popen(
            ["ip", "netns", "exec", ns, *SETPRIV, *DIE_WITH_US, *args],
            stdout=self._log,
            stderr=subprocess.STDOUT,
            stdin=subprocess.DEVNULL,
        )
        STARTED.append(self)
        # `ip netns exec` and setpriv both exec: the pid becomes ptp4l's.
        try:
            wait_for(self._is_ptp4l, 5.0, f"{name}: ptp4l to start")
            caps = self.look_at_capabilities()
        except (AssertionError, OSError):
            self.kill()
            raise
        if caps is None or any(caps):
            self.kill()
            raise AssertionError(f"{name}: ptp4l holds CAP_SYS_TIME ({caps}) or died; killed it")
        wait_for(lambda: os.path.exists(self.uds), 5.0, f"{name}: its UDS socket")

    def look_at_capabilities(self) -> tuple[bool, bool] | None:
        """CAP_SYS_TIME of the running ptp4l (in the bounding set, effective), also kept in
        `caps_seen`; None if it is not running."""
        if self.popen.poll() is not None:
            return None
        try:
            caps = sys_time_capability(self.popen.pid)
        except OSError:
            return None
        if self.popen.poll() is not None:
            return None  # exited meanwhile: what was read may be another process's
        self.caps_seen.append(caps)
        return caps

    def _is_ptp4l(self) -> bool:
        if self.popen.poll() is not None:
            raise AssertionError(f"{self.name}: ptp4l exited: {self.output()[-1500:]}")
        try:
            return Path(f"/proc/{self.popen.pid}/comm").read_text().strip() == "ptp4l"
        except OSError:
            return False

    @property
    def running(self) -> bool:
        return self.popen.poll() is None

    def output(self) -> str:
        """This ptp4l's log (a restarted one appends to the file of the one before)."""
        with self.log_path.open("rb") as fh:
            fh.seek(self._log_from)
            return fh.read().decode(errors="replace")

    def kill(self) -> None:
        """SIGKILL, the way a crash or a power cut ends it."""
        self.look_at_capabilities()  # once more while it runs, for the clock guard
        if self.popen.poll() is None:
            self.popen.send_signal(signal.SIGKILL)
        self.popen.wait(10)
        self._log.close()

    def stop(self) -> None:
        self.look_at_capabilities()  # once more while it runs, for the clock guard
        if self.popen.poll() is None:
            self.popen.send_signal(signal.SIGTERM)
            try:
                self.popen.wait(5)
            except subprocess.TimeoutExpired:
                self.popen.kill()
                self.popen.wait(5)
        self._log.close()


STARTED: list[Ptp4l] = []
"""Every ptp4l the lab started in this test session, for the clock guard."""


class Lab:
    """Namespaces joined by one bridge (itself in a namespace), plus isolated ones."""

    def __init__(self, tmp: Path) -> None:
        self.tmp = tmp
        self.tag = f"{PREFIX}{os.getpid()}"
        self.namespaces: list[str] = []
        self.ptp4ls: list[Ptp4l] = []
        self._hosts = 0
        try:
            check_setpriv()
            remove_stale_namespaces()
            self.bridge = self._namespace("br")
            run("ip", "-n", self.bridge, "link", "add", "br0", "type", "bridge")
            run("ip", "-n", self.bridge, "link", "set", "br0", "up")
        except BaseException:
            self.close()
            raise

    def _namespace(self, name: str) -> str:
        ns = f"{self.tag}-{name}"
        run("ip", "netns", "add", ns)
        self.namespaces.append(ns)
        run("ip", "-n", ns, "link", "set", "lo", "up")
        return ns

    def host(self, name: str) -> str:
        """A namespace with eth0 on the bridge (10.231.0.N/24)."""
        ns = self._namespace(name)
        self._hosts += 1
        peer = f"v{self._hosts}"
        run("ip", "-n", ns, "link", "add", "eth0", "type", "veth", "peer", "name", peer,
            "netns", self.bridge)  # fmt: skip
        run("ip", "-n", self.bridge, "link", "set", peer, "master", "br0")
        run("ip", "-n", self.bridge, "link", "set", peer, "up")
        run("ip", "-n", ns, "addr", "add", f"10.231.0.{self._hosts}/24", "dev", "eth0")
        run("ip", "-n", ns, "link", "set", "eth0", "up")
        return ns

    def lone_host(self, name: str) -> str:
        """A namespace whose eth0 leads nowhere (its veth peer sits idle in the same one)."""
        ns = self._namespace(name)
        run("ip", "-n", ns, "link", "add", "eth0", "type", "veth", "peer", "name", "eth1")
        run("ip", "-n", ns, "addr", "add", "10.231.1.1/24", "dev", "eth0")
        run("ip", "-n", ns, "link", "set", "eth0", "up")
        run("ip", "-n", ns, "link", "set", "eth1", "up")
        return ns

    def ptp4l(
        self, ns: str, name: str, template: str, options: dict[str, str] | None = None
    ) -> Ptp4l:
        p = Ptp4l(ns, name, template, options or {}, self.tmp)
        self.ptp4ls.append(p)
        return p

    def close(self) -> None:
        for p in self.ptp4ls:
            with contextlib.suppress(OSError, subprocess.TimeoutExpired):
                p.kill()
        self.ptp4ls.clear()
        for ns in reversed(self.namespaces):
            subprocess.run(["ip", "netns", "del", ns], check=False, capture_output=True)
        self.namespaces.clear()
