"""Fleet "hosts" for the tests: each a real OpenSSH server (``sshd -D -e -f CONFIG``) of its
own on 127.0.0.1, with its own host key, config, pid file and authorized key in a tmp folder,
and a fake-but-real fleetdaq layout under a prefix: ``<venv>/bin/fleetdaq`` runs this repo's
fleetdaq, the site file, a spool with known bytes, a hub's data folder.

Started by us, ended by their pid (SIGTERM, then SIGKILL), whatever happens."""

from __future__ import annotations

import contextlib
import getpass
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import psutil

from tests.procs import REPO, free_port

SSHD = Path("/usr/sbin/sshd")
VENV = "/opt/fleetdaq/venv"
SITE_FILE = "/etc/fleetdaq/site.yaml"
STATE_DIR = "/var/lib/fleetdaq"
USER = getpass.getuser()


def keygen(path: Path) -> str:
    """A new ed25519 key pair at `path` (+ ``.pub``); returns the public key line."""
    subprocess.run(
        ["ssh-keygen", "-q", "-t", "ed25519", "-N", "", "-C", "fleet-test", "-f", str(path)],
        check=True,
        capture_output=True,
    )
    return path.with_name(path.name + ".pub").read_text().strip()


def _port_open(port: int) -> bool:
    with socket.socket() as s:
        return s.connect_ex(("127.0.0.1", port)) == 0


class Sshd:
    """A real sshd on 127.0.0.1:`port` serving one fleet host; `stop` ends it by its pid."""

    def __init__(self, root: Path, client_public_key: str, path_env: str | None = None) -> None:
        self.root = root
        root.mkdir(parents=True, exist_ok=True)
        self.fs = root / "fs"
        """The host's ``fleetdaq_prefix``: its fleetdaq files are under it."""
        self.fs.mkdir(exist_ok=True)
        self.host_key_public = keygen(root / "host_ed25519")
        (root / "authorized_keys").write_text(client_public_key + "\n")
        self.port = free_port()
        self.config = root / "sshd_config"
        self.log_path = root / "sshd.log"
        lines = [
            f"Port {self.port}",
            "ListenAddress 127.0.0.1",
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
        ]
        if path_env is not None:
            lines.append(f"SetEnv PATH={path_env}")
        # OpenSSH 9.8+ blocks a source address after failed attempts; these tests fail on
        # purpose, all from 127.0.0.1. Older sshds do not know the option.
        if os.geteuid() == 0:
            # sshd started by root insists on its privilege-separation folder (systemd's
            # RuntimeDirectory=sshd makes it; nothing does in a container).
            Path("/run/sshd").mkdir(mode=0o755, exist_ok=True)
        self.config.write_text("\n".join([*lines, "PerSourcePenalties no"]) + "\n")
        check = self._check()
        if check.returncode != 0 and "PerSourcePenalties" in check.stderr:
            self.config.write_text("\n".join(lines) + "\n")
            check = self._check()
        assert check.returncode == 0, check.stderr
        self._log = self.log_path.open("wb")
        self.popen = subprocess.Popen(
            [str(SSHD), "-D", "-e", "-f", str(self.config)],
            stdout=self._log,
            stderr=subprocess.STDOUT,
            stdin=subprocess.DEVNULL,
        )
        try:
            self._wait_ready()
        except BaseException:
            self.stop()
            raise

    def _check(self) -> subprocess.CompletedProcess[str]:
        return subprocess.run(
            [str(SSHD), "-t", "-f", str(self.config)], capture_output=True, text=True, check=False
        )

    def _wait_ready(self, timeout: float = 20.0) -> None:
        deadline = time.monotonic() + timeout
        while not _port_open(self.port):
            if self.popen.poll() is not None:
                raise RuntimeError(f"sshd exited at start:\n{self.log_path.read_text()}")
            if time.monotonic() > deadline:
                raise TimeoutError(f"sshd not listening on {self.port}:\n{self.log()}")
            time.sleep(0.02)

    def log(self) -> str:
        return self.log_path.read_text(errors="replace")

    def known_hosts_line(self, public_key: str | None = None) -> str:
        """The known_hosts line for this host (ssh's ``[address]:port`` form), with its own
        key or `public_key`."""
        kind, blob = (public_key or self.host_key_public).split()[:2]
        return f"[127.0.0.1]:{self.port} {kind} {blob}"

    def stop(self) -> None:
        """End this sshd and the per-connection sshds it forked, by their pids."""
        sessions: list[psutil.Process] = []
        if self.popen.poll() is None:
            with contextlib.suppress(psutil.NoSuchProcess):
                sessions = psutil.Process(self.popen.pid).children(recursive=True)
            # Sessions still closing are given the time to: their listener reaps them.
            _, sessions = psutil.wait_procs(sessions, timeout=5)
            for p in sessions:
                with contextlib.suppress(psutil.NoSuchProcess):
                    p.terminate()
            self.popen.send_signal(signal.SIGTERM)
            try:
                self.popen.wait(10)
            except subprocess.TimeoutExpired:
                self.popen.kill()
                self.popen.wait()
            for p in psutil.wait_procs(sessions, timeout=5)[1]:
                with contextlib.suppress(psutil.NoSuchProcess):
                    p.kill()
        self._log.close()

    # --- the fleetdaq layout on this host ---------------------------------------------------

    def install_fleetdaq(self, site_text: str) -> None:
        """``<venv>/bin/fleetdaq`` running this repo's fleetdaq (PYTHONPATH set by the
        wrapper, whatever the SSH session's environment), and the site file."""
        bin_dir = self.fs / VENV.lstrip("/") / "bin"
        bin_dir.mkdir(parents=True, exist_ok=True)
        wrapper = bin_dir / "fleetdaq"
        wrapper.write_text(f'#!/bin/sh\nPYTHONPATH={REPO} exec {sys.executable} -m fleetdaq "$@"\n')
        wrapper.chmod(0o755)
        site = self.fs / SITE_FILE.lstrip("/")
        site.parent.mkdir(parents=True, exist_ok=True)
        site.write_text(site_text)

    def spool(self, node: str, stream: str, sizes: list[int]) -> int:
        """Segments of the given sizes in the node's spool; returns the bytes written."""
        folder = self.fs / STATE_DIR.lstrip("/") / "spool" / node / stream
        folder.mkdir(parents=True, exist_ok=True)
        for i, n in enumerate(sizes):
            (folder / f"{i:08d}.seg").write_bytes(os.urandom(n))
        return sum(sizes)

    def data_dir(self) -> Path:
        return self.fs / STATE_DIR.lstrip("/") / "data"


def bin_without(root: Path, *missing: str) -> Path:
    """A folder of links to every command of /usr/bin but `missing`: a PATH for a host that
    does not have those commands."""
    folder = root / "bin"
    folder.mkdir(parents=True)
    for p in Path("/usr/bin").iterdir():
        if p.name not in missing:
            (folder / p.name).symlink_to(p)
    return folder


def ensure_sshd() -> None:
    """Install Debian's openssh-server (sshd, ssh-keygen, ssh-keyscan) if missing: a missing
    package is not a reason to skip (`.ci/run` installs it too). In a container without an
    init the package's service is not started; the tests start their own sshds."""
    if SSHD.is_file() and shutil.which("ssh-keyscan") is not None:
        return
    if shutil.which("apt-get") is None:
        raise RuntimeError("OpenSSH's sshd is missing and there is no apt-get to install it")
    for cmd in (
        ["apt-get", "update", "-qq"],
        ["apt-get", "install", "-y", "-qq", "openssh-server"],
    ):
        subprocess.run(
            cmd,
            check=False,
            capture_output=True,
            timeout=600,
            env={**os.environ, "DEBIAN_FRONTEND": "noninteractive"},
        )
    if not SSHD.is_file():
        raise RuntimeError("could not install openssh-server with apt-get")
