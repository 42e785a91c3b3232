"""A loopback-only network namespace for the dashboard's browser tests, and the processes run in
it: Chromium looks up outside hosts at start even with background networking off, so it (and
the hub it talks to) only ever run where there is nothing but `lo`.

Names carry this process's pid (`fdqweb<pid>-<tag>`); `close()` ends the processes started here
by their pid, then anything still inside the namespace (only ever our own descendants: nobody
else knows its name), and deletes it. Namespaces left by an earlier run whose pid is gone are
deleted at the next start.
"""

from __future__ import annotations

import contextlib
import os
import re
import shutil
import signal
import subprocess
import time
from pathlib import Path
from types import TracebackType
from typing import IO

from tests.procs import REPO

PREFIX = "fdqweb"
CHROMIUM = "/usr/bin/chromium"


def run(*args: str) -> str:
    done = subprocess.run(args, capture_output=True, text=True, check=False, timeout=30)
    if done.returncode != 0:
        raise RuntimeError(f"{' '.join(args)}: {done.stderr.strip() or done.stdout.strip()}")
    return done.stdout


def netns_problem() -> str | None:
    """None if this machine can create network namespaces, else why not."""
    if shutil.which("ip") is None:
        return "no `ip` command (iproute2)"
    if os.geteuid() != 0:
        return "creating a network namespace needs root"
    return None


def ensure_chromium() -> None:
    """Debian's Chromium, installed with apt-get when missing (`.ci/run` installs it too)."""
    if Path(CHROMIUM).exists():
        return
    if shutil.which("apt-get") is None:
        raise AssertionError(f"{CHROMIUM} is missing and there is no apt-get to install it")
    subprocess.run(["apt-get", "update", "-qq"], check=False, capture_output=True, timeout=600)
    install = ["apt-get", "install", "-y", "-qq", "chromium"]
    subprocess.run(install, check=False, capture_output=True, timeout=900)
    if not Path(CHROMIUM).exists():
        raise AssertionError("could not install Debian's chromium with apt-get")


def remove_stale() -> None:
    for line in run("ip", "netns", "list").splitlines():
        m = re.match(rf"^({PREFIX}(\d+)-\S+)", line)
        if m and not Path(f"/proc/{m.group(2)}").exists():
            subprocess.run(["ip", "netns", "del", m.group(1)], check=False, capture_output=True)


def child_env() -> dict[str, str]:
    """This checkout's code first (an editable install elsewhere must not win), no browser
    download ever."""
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(
        p for p in (str(REPO), env.get("PYTHONPATH", "")) if p
    )  # fmt: skip
    env["PLAYWRIGHT_SKIP_BROWSER_DOWNLOAD"] = "1"
    env["PYTHONUNBUFFERED"] = "1"
    return env


class NsProc:
    """One process in the namespace (`ip netns exec` execs, so the pid is the program's)."""

    def __init__(self, ns: str, args: list[str], log: Path, stdout: Path | None = None) -> None:
        self.args = args
        self.log_path = log
        self._log: IO[bytes] = log.open("wb")
        self._out: IO[bytes] | None = stdout.open("wb") if stdout is not None else None
        self.popen = subprocess.Popen(
            ["ip", "netns", "exec", ns, *args],
            cwd=REPO,
            env=child_env(),
            stdout=self._out if self._out is not None else self._log,
            stderr=self._log,
            stdin=subprocess.DEVNULL,
        )

    def output(self) -> str:
        return self.log_path.read_text(errors="replace")

    def wait(self, timeout: float) -> int:
        try:
            return self.popen.wait(timeout)
        except subprocess.TimeoutExpired:
            self.popen.send_signal(signal.SIGUSR1)  # a fleetdaq process prints its stacks
            time.sleep(1.0)
            self.kill()
            raise AssertionError(
                f"{self.args[:4]} did not finish within {timeout} s:\n{self.output()[-4000:]}"
            ) from None

    def terminate(self, timeout: float = 30.0) -> int:
        if self.popen.poll() is None:
            self.popen.send_signal(signal.SIGTERM)
        return self.wait(timeout)

    def kill(self) -> None:
        if self.popen.poll() is None:
            self.popen.kill()
            self.popen.wait(10)
        self.close_files()

    def close_files(self) -> None:
        self._log.close()
        if self._out is not None:
            self._out.close()


class Netns:
    """A network namespace with only `lo`, up; processes started in it; all gone at close."""

    def __init__(self, tag: str) -> None:
        self.name = f"{PREFIX}{os.getpid()}-{tag}"
        self.procs: list[NsProc] = []
        remove_stale()
        subprocess.run(["ip", "netns", "del", self.name], check=False, capture_output=True)
        run("ip", "netns", "add", self.name)
        try:
            run("ip", "-n", self.name, "link", "set", "lo", "up")
            links = run("ip", "-n", self.name, "-o", "link", "show")
            names = re.findall(r"^\d+:\s+([^:@\s]+)", links, re.M)
            if names != ["lo"]:
                raise AssertionError(f"namespace {self.name} has more than lo: {names}")
        except BaseException:
            self.close()
            raise

    def start(self, args: list[str], log: Path, stdout: Path | None = None) -> NsProc:
        p = NsProc(self.name, args, log, stdout)
        self.procs.append(p)
        return p

    def pids(self) -> list[int]:
        out = subprocess.run(
            ["ip", "netns", "pids", self.name], capture_output=True, text=True, check=False
        )
        return [int(x) for x in out.stdout.split()]

    def close(self) -> list[int]:
        """End every process started here (SIGTERM, then SIGKILL by pid), then whatever is left
        in the namespace; delete it. Returns the pids that had to be killed that way."""
        for p in self.procs:
            with contextlib.suppress(OSError, AssertionError):
                p.terminate(20)
            p.kill()
        left = self.pids()
        for pid in left:
            with contextlib.suppress(OSError):
                os.kill(pid, signal.SIGKILL)
        subprocess.run(["ip", "netns", "del", self.name], check=False, capture_output=True)
        return left

    def __enter__(self) -> Netns:
        return self

    def __exit__(
        self, t: type[BaseException] | None, e: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()
