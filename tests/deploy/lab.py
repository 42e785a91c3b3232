"""A deploy lab: "hosts" that are real OpenSSH servers, each in a network namespace of its own,
joined by veth links to a bridge in a control namespace where ansible-playbook runs.

Nothing in the lab reaches any other network: 10.233.0.0/24 exists only on the lab's links and
no namespace has a route anywhere else, so pip on a host has no package registry (it must install
from the wheelhouse). A network namespace separates only the network: files and processes are
shared, so every host writes under its own prefix (``fleetdaq_prefix``).

Names carry this process's pid; `close()` ends only the sshds the lab started (by pid) and
deletes only the namespaces it created (plus leftovers of earlier runs whose pid is gone)."""

from __future__ import annotations

import contextlib
import os
import re
import signal
import subprocess
import time
from dataclasses import dataclass, field
from pathlib import Path

import psutil

from tests.fleet.hosts import SSHD, USER, keygen

PREFIX = "fdqdep"
SUBNET = "10.233.0"


def run(*args: str) -> str:
    done = subprocess.run(args, capture_output=True, text=True, check=False, timeout=30)
    if done.returncode != 0:
        raise RuntimeError(f"{' '.join(args)}: {done.stderr.strip() or done.stdout.strip()}")
    return done.stdout


def netns_possible() -> str | None:
    """None if this machine can create network namespaces, else why not."""
    probe = f"{PREFIX}{os.getpid()}-probe"
    try:
        run("ip", "netns", "add", probe)
    except (RuntimeError, OSError) as err:
        return f"cannot create a network namespace here: {err}"
    with contextlib.suppress(RuntimeError):
        run("ip", "netns", "del", probe)
    return None


def remove_stale_namespaces() -> None:
    """Namespaces left by an earlier run of these tests that was killed before cleaning up."""
    for line in run("ip", "netns", "list").splitlines():
        m = re.match(rf"^({PREFIX}(\d+)-\S+)", line)
        if m and not Path(f"/proc/{m.group(2)}").exists():
            subprocess.run(["ip", "netns", "del", m.group(1)], check=False, capture_output=True)


@dataclass
class Host:
    """One lab host: its namespace, address, sshd and prefix (its "root file system")."""

    name: str
    netns: str
    address: str
    root: Path
    host_key_public: str = ""
    popen: subprocess.Popen[bytes] | None = None
    log_path: Path = field(default_factory=Path)

    @property
    def fs(self) -> Path:
        return self.root / "fs"

    def known_hosts_line(self) -> str:
        kind, blob = self.host_key_public.split()[:2]
        return f"{self.address} {kind} {blob}"


class Lab:
    """The control namespace and its hosts; `close()` undoes everything it made."""

    def __init__(self, root: Path, names: list[str]) -> None:
        self.root = root
        self.tag = f"{PREFIX}{os.getpid()}"
        self.control = f"{self.tag}-ctl"
        self.hosts: list[Host] = []
        self._namespaces: list[str] = []
        root.mkdir(parents=True, exist_ok=True)
        self.client_key = root / "id_ed25519"
        self.client_public = keygen(self.client_key)
        remove_stale_namespaces()
        try:
            self._add_netns(self.control)
            self._in(self.control, "ip", "link", "set", "lo", "up")
            self._in(self.control, "ip", "link", "add", "br0", "type", "bridge")
            self._in(self.control, "ip", "addr", "add", f"{SUBNET}.1/24", "dev", "br0")
            self._in(self.control, "ip", "link", "set", "br0", "up")
            for i, name in enumerate(names):
                self.hosts.append(self._add_host(i, name))
        except BaseException:
            self.close()
            raise

    def _add_netns(self, name: str) -> None:
        run("ip", "netns", "add", name)
        self._namespaces.append(name)

    @staticmethod
    def _in(netns: str, *args: str) -> str:
        return run("ip", "netns", "exec", netns, *args)

    def _add_host(self, i: int, name: str) -> Host:
        netns = f"{self.tag}-h{i}"
        self._add_netns(netns)
        near, far = f"{self.tag}a{i}", f"{self.tag}b{i}"
        run("ip", "link", "add", near, "type", "veth", "peer", "name", far)
        run("ip", "link", "set", near, "netns", self.control)
        run("ip", "link", "set", far, "netns", netns)
        self._in(self.control, "ip", "link", "set", near, "master", "br0", "up")
        self._in(netns, "ip", "link", "set", far, "name", "eth0")
        address = f"{SUBNET}.{10 + i}"
        self._in(netns, "ip", "addr", "add", f"{address}/24", "dev", "eth0")
        self._in(netns, "ip", "link", "set", "eth0", "up")
        self._in(netns, "ip", "link", "set", "lo", "up")
        host = Host(name, netns, address, self.root / name)
        host.fs.mkdir(parents=True)
        self._start_sshd(host)
        return host

    def _start_sshd(self, host: Host) -> None:
        root = host.root
        host.host_key_public = keygen(root / "host_ed25519")
        (root / "authorized_keys").write_text(self.client_public + "\n")
        config = root / "sshd_config"
        lines = [
            "Port 22",
            f"ListenAddress {host.address}",
            f"HostKey {root / 'host_ed25519'}",
            f"PidFile {root / 'sshd.pid'}",
            f"AuthorizedKeysFile {root / 'authorized_keys'}",
            f"AllowUsers {USER}",
            "StrictModes no",
            "UsePAM no",
            "PasswordAuthentication no",
            "KbdInteractiveAuthentication no",
            "PubkeyAuthentication yes",
            "PermitRootLogin prohibit-password",
            "MaxStartups 100",
            "LogLevel VERBOSE",
            # As Debian's own sshd_config: Ansible copies files over SFTP (without it, each
            # copy first fails over SFTP and scp and then falls back to a piped shell).
            "Subsystem sftp internal-sftp",
        ]
        if os.geteuid() == 0:
            Path("/run/sshd").mkdir(mode=0o755, exist_ok=True)
        config.write_text("\n".join(lines) + "\n")
        host.log_path = root / "sshd.log"
        with host.log_path.open("wb") as log:
            # `ip netns exec` execs sshd: the pid is sshd's own.
            host.popen = subprocess.Popen(
                ["ip", "netns", "exec", host.netns, str(SSHD), "-D", "-e", "-f", str(config)],
                stdout=log,
                stderr=subprocess.STDOUT,
                stdin=subprocess.DEVNULL,
            )
        deadline = time.monotonic() + 20
        while "Server listening" not in host.log_path.read_text(errors="replace"):
            if host.popen.poll() is not None:
                raise RuntimeError(f"sshd of {host.name} exited:\n{host.log_path.read_text()}")
            if time.monotonic() > deadline:
                log = host.log_path.read_text()
                raise TimeoutError(f"sshd of {host.name} not listening:\n{log}")
            time.sleep(0.02)

    def run_in_control(
        self, args: list[str], env: dict[str, str], timeout: float
    ) -> subprocess.CompletedProcess[str]:
        """`args` inside the control namespace (where only the lab's hosts can be reached)."""
        return subprocess.run(
            ["ip", "netns", "exec", self.control, *args],
            env=env,
            capture_output=True,
            text=True,
            timeout=timeout,
            check=False,
        )

    def close(self) -> None:
        for host in self.hosts:
            p = host.popen
            if p is None or p.poll() is not None:
                continue
            # Its per-connection children first (ansible's ControlPersist sessions end with it).
            with contextlib.suppress(psutil.NoSuchProcess):
                for child in psutil.Process(p.pid).children(recursive=True):
                    with contextlib.suppress(psutil.NoSuchProcess):
                        child.terminate()
            p.send_signal(signal.SIGTERM)
            try:
                p.wait(10)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()
        for netns in reversed(self._namespaces):
            subprocess.run(["ip", "netns", "del", netns], check=False, capture_output=True)
        self._namespaces.clear()
