"""An SSH connection to a fleet host (paramiko), its host key verified, and commands on it.

Host keys are checked against ``~/.ssh/known_hosts``, ``/etc/ssh/ssh_known_hosts`` and any
file given with ``--known-hosts`` (`known_hosts`), under the name ssh itself records
(``[address]:port`` off port 22). An unknown host is refused with how to add it; a changed key
is refused with both fingerprints; a revoked one is refused. Nothing is ever written to a
known_hosts file. Keys come from the SSH agent and
``~/.ssh/id_*`` as with ``ssh``, plus ``--identity`` and ``ansible_ssh_private_key_file``.

Every way of not getting in becomes one `SshError` whose kind says why (`classify`).
"""

from __future__ import annotations

import errno
import getpass
import os
import select
import socket
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import Any

import paramiko

from fleetdaq.fleet.errors import CommandTimeout, SshError, Unreachable
from fleetdaq.fleet.inventory import Host
from fleetdaq.fleet.known_hosts import KnownHosts

SYSTEM_KNOWN_HOSTS = Path("/etc/ssh/ssh_known_hosts")


@dataclass(frozen=True, slots=True)
class SshOptions:
    known_hosts: tuple[Path, ...] = ()
    """Files read besides ``~/.ssh/known_hosts`` and ``/etc/ssh/ssh_known_hosts``."""
    identity: str | None = None
    """A private key tried for every host (besides the agent's and ``~/.ssh/id_*``)."""

    def known_hosts_files(self) -> list[Path]:
        user = Path(os.path.expanduser("~/.ssh/known_hosts"))
        return [user, SYSTEM_KNOWN_HOSTS, *self.known_hosts]

    def add_hint_file(self) -> str:
        """Where the hint says to add a key: the --known-hosts file, else the user's."""
        return str(self.known_hosts[0]) if self.known_hosts else "~/.ssh/known_hosts"


@dataclass(frozen=True, slots=True)
class Result:
    """A finished command: its exit status (-1: killed by a signal) and its output."""

    status: int
    stdout: str
    stderr: str


def known_hosts_name(host: Host) -> str:
    """The name a host's key is filed under in known_hosts (as ssh files it)."""
    return host.address if host.port == 22 else f"[{host.address}]:{host.port}"


class _UnknownHostKey(Exception):
    def __init__(self, key: paramiko.PKey, revoked: bool) -> None:
        super().__init__("revoked host key" if revoked else "unknown host key")
        self.key = key
        self.revoked = revoked


class _RefuseUnknown(paramiko.MissingHostKeyPolicy):
    """Never accept a key that no known_hosts file has (paramiko's RejectPolicy, but keeping
    the key so that the message can show its fingerprint), nor a revoked one."""

    def __init__(self, known: KnownHosts) -> None:
        self.known = known

    def missing_host_key(
        self, client: paramiko.SSHClient, hostname: str, key: paramiko.PKey
    ) -> None:
        raise _UnknownHostKey(key, self.known.is_revoked(key))


def _fingerprint(key: paramiko.PKey) -> str:
    return f"{key.get_name()} {key.fingerprint}"


def classify(err: BaseException, host: Host, options: SshOptions, timeout: float) -> SshError:
    """Why a connection failed, said plainly (and what to do about it)."""
    where = f"{host.address}:{host.port}"
    user = host.user or getpass.getuser()
    name = known_hosts_name(host)
    port = f" -p {host.port}" if host.port != 22 else ""
    if isinstance(err, _UnknownHostKey) and err.revoked:
        return SshError(
            Unreachable.HOST_KEY_REVOKED,
            f"host key of {name} ({_fingerprint(err.key)}) is marked @revoked in known_hosts: "
            f"refused",
        )
    if isinstance(err, _UnknownHostKey):
        return SshError(
            Unreachable.HOST_KEY_UNKNOWN,
            f"host key of {name} is not in known_hosts (it offers {_fingerprint(err.key)}); "
            f"after checking that fingerprint on the host (ssh-keygen -lf "
            f"/etc/ssh/ssh_host_*_key.pub), add it: ssh-keyscan{port} -t {err.key.get_name()} "
            f"{host.address} >> {options.add_hint_file()}, or log in once with "
            f"ssh{port} {user}@{host.address}",
        )
    if isinstance(err, paramiko.BadHostKeyException):
        return SshError(
            Unreachable.HOST_KEY_CHANGED,
            f"host key of {name} has CHANGED: known_hosts has {_fingerprint(err.expected_key)}, "
            f"the host offers {_fingerprint(err.key)}; someone may be intercepting the "
            f"connection, or the host was reinstalled: check, then ssh-keygen -R '{name}' and "
            f"add the new key",
        )
    if isinstance(err, socket.gaierror):
        return SshError(Unreachable.DNS, f"cannot resolve {host.address!r}: {err.strerror}")
    if isinstance(err, paramiko.ssh_exception.NoValidConnectionsError):
        codes = {getattr(e, "errno", None) for e in err.errors.values()}
        if codes == {errno.ECONNREFUSED}:
            return SshError(
                Unreachable.REFUSED, f"connection refused at {where} (no SSH server listening)"
            )
        return SshError(Unreachable.NO_ROUTE, f"no route to {where}")
    if isinstance(err, ConnectionRefusedError):
        return SshError(
            Unreachable.REFUSED, f"connection refused at {where} (no SSH server listening)"
        )
    if isinstance(err, TimeoutError):
        return SshError(Unreachable.TIMEOUT, f"no answer from {where} within {timeout:g} s")
    if isinstance(err, OSError) and err.errno in (
        errno.EHOSTUNREACH,
        errno.ENETUNREACH,
        errno.EHOSTDOWN,
    ):
        return SshError(Unreachable.NO_ROUTE, f"no route to {where}: {err.strerror}")
    if isinstance(err, paramiko.PasswordRequiredException):
        return SshError(
            Unreachable.AUTH,
            f"{user}@{where}: the key is protected by a passphrase: add it to ssh-agent "
            f"(ssh-add) first",
        )
    if isinstance(err, paramiko.AuthenticationException):
        tried = ["ssh-agent", "~/.ssh/id_*"] + [k for k in (host.identity, options.identity) if k]
        return SshError(
            Unreachable.AUTH,
            f"{user}@{where} refused our keys (tried {', '.join(tried)}); set ansible_user "
            f"or give --identity",
        )
    if isinstance(err, paramiko.SSHException):
        text = str(err)
        if "No authentication methods available" in text:
            return SshError(
                Unreachable.AUTH,
                f"{user}@{where}: no key to offer (no ssh-agent, no ~/.ssh/id_*): give "
                f"--identity or set ansible_ssh_private_key_file",
            )
        if "banner" in text:
            return _no_handshake(where, timeout)
        return SshError(Unreachable.SSH, f"{where}: ssh: {text}")
    if isinstance(err, EOFError):
        return SshError(Unreachable.SSH, f"{where} closed the connection during the handshake")
    if isinstance(err, OSError):
        return SshError(Unreachable.SSH, f"{where}: {err.strerror or err}")
    return SshError(Unreachable.SSH, f"{where}: {type(err).__name__}: {err}")


def _no_handshake(where: str, timeout: float) -> SshError:
    return SshError(
        Unreachable.TIMEOUT,
        f"{where} accepted the connection but did not complete an SSH handshake within "
        f"{timeout:g} s (not an SSH server, or overloaded)",
    )


class Connection:
    """A logged-in SSH connection to one host; a context manager (`close` is idempotent)."""

    def __init__(self, client: paramiko.SSHClient, host: Host) -> None:
        self.client = client
        self.host = host

    def run(
        self,
        command: str,
        timeout: float | None,
        sink: Callable[[bytes], None] | None = None,
    ) -> Result:
        """Run a shell command on the host and wait for it, at most `timeout` s in all (None:
        as long as it runs, e.g. ``journalctl --follow`` until Ctrl-C).

        With `sink`, standard output goes there as it arrives (and `Result.stdout` is empty).

        Raises:
            CommandTimeout: not finished in time (the channel is closed).
            paramiko.SSHException, OSError, EOFError: the connection was lost.
        """
        deadline = None if timeout is None else time.monotonic() + timeout
        transport = self.client.get_transport()
        if transport is None or not transport.is_active():
            raise EOFError("the connection is closed")
        chan = transport.open_session(timeout=timeout)
        try:
            chan.exec_command(command)
            out, err = bytearray(), bytearray()
            while True:
                if chan.recv_ready():
                    data = chan.recv(65536)
                    if sink is not None:
                        sink(data)
                    else:
                        out += data
                    continue
                if chan.recv_stderr_ready():
                    err += chan.recv_stderr(65536)
                    continue
                if chan.exit_status_ready() or chan.closed:
                    break
                remaining = None if deadline is None else deadline - time.monotonic()
                if remaining is not None and remaining <= 0:
                    raise CommandTimeout(f"did not finish within {timeout:g} s")
                # The channel's poll descriptor wakes on stdout, stderr and close alike.
                select.select([chan], [], [], remaining)
            status = chan.recv_exit_status() if chan.exit_status_ready() else -1
            return Result(status, out.decode("utf-8", "replace"), err.decode("utf-8", "replace"))
        finally:
            chan.close()

    def close(self) -> None:
        self.client.close()

    def __enter__(self) -> Connection:
        return self

    def __exit__(
        self, t: type[BaseException] | None, e: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()


def connect(host: Host, options: SshOptions, timeout: float) -> Connection:
    """Connect and log in, the host key verified.

    Raises:
        SshError: the host could not be reached or logged into (its kind says why).
    """
    client = paramiko.SSHClient()
    start = time.monotonic()
    try:
        known = KnownHosts.load(options.known_hosts_files(), into=client.get_host_keys())
        client.set_missing_host_key_policy(_RefuseUnknown(known))
        keys = [os.path.expanduser(k) for k in (host.identity, options.identity) if k]
        for key in keys:
            if not os.path.isfile(key):
                raise SshError(Unreachable.AUTH, f"identity file {key}: no such file")
        connect_args: dict[str, Any] = {
            "port": host.port,
            "username": host.user or getpass.getuser(),
            "key_filename": keys or None,
            "timeout": timeout,
            "banner_timeout": timeout,
            "auth_timeout": timeout,
            "channel_timeout": timeout,
        }
        client.connect(host.address, **connect_args)
    except SshError:
        client.close()
        raise
    except Exception as err:
        client.close()
        if type(err) is paramiko.SSHException and time.monotonic() - start >= timeout:
            # paramiko gives up negotiating at `timeout` and then finds "No existing session".
            raise _no_handshake(f"{host.address}:{host.port}", timeout) from err
        raise classify(err, host, options, timeout) from err
    except BaseException:
        client.close()
        raise
    return Connection(client, host)
