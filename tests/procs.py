"""Real OS processes for system tests: started by us, ended by their pid, always cleaned up;
and what the tests need around them: readiness from the hub's own status request, a loopback
link that can be cut, and a read-only look into an edge's spool."""

from __future__ import annotations

import contextlib
import io
import signal
import socket
import struct
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from types import TracebackType
from typing import IO, Any

REPO = Path(__file__).resolve().parent.parent


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def wait_for_port(port: int, timeout: float = 20.0) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        with socket.socket() as s:
            if s.connect_ex(("127.0.0.1", port)) == 0:
                return
        time.sleep(0.05)
    raise TimeoutError(f"nothing listens on 127.0.0.1:{port} after {timeout} s")


def wait_until(cond: Callable[[], object], timeout: float, what: str, every: float = 0.1) -> Any:
    """Poll `cond` until it returns something truthy (returned); fail after `timeout` s."""
    deadline = time.monotonic() + timeout
    while True:
        value = cond()
        if value:
            return value
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout} s waiting for {what}")
        time.sleep(every)


class Proc:
    """A `fleetdaq` sub-command in its own process, output to a log file.

    With `relay_output` the output goes through a pipe that this process copies into the log:
    a child whose writes to files are refused (a full disk, RLIMIT_FSIZE) still logs.
    """

    def __init__(self, args: list[str], log: Path, relay_output: bool = False) -> None:
        self.log_path = log
        self._log: IO[bytes] = log.open("wb")
        self._relay: threading.Thread | None = None
        self.popen = subprocess.Popen(
            [sys.executable, "-m", "fleetdaq", *args],
            cwd=REPO,
            stdout=subprocess.PIPE if relay_output else self._log,
            stderr=subprocess.STDOUT,
            stdin=subprocess.DEVNULL,
        )
        if relay_output:
            self._relay = threading.Thread(target=self._copy_output, daemon=True)
            self._relay.start()

    def _copy_output(self) -> None:
        out = self.popen.stdout
        assert isinstance(out, io.BufferedReader)
        while chunk := out.read1(65536):  # whatever is there, as soon as it is there
            self._log.write(chunk)
            self._log.flush()

    def _close_log(self) -> None:
        if self._relay is not None:
            self._relay.join(10)
        self._log.close()

    def terminate(self, timeout: float = 20.0) -> int:
        """SIGTERM, wait; returns the exit code (kills and fails loudly if it hangs)."""
        if self.popen.poll() is None:
            self.popen.send_signal(signal.SIGTERM)
        try:
            return self.popen.wait(timeout)
        except subprocess.TimeoutExpired:
            self.popen.send_signal(signal.SIGUSR1)  # dump its thread stacks into the log
            time.sleep(1.0)
            self.popen.kill()
            self.popen.wait()
            raise AssertionError(
                f"{self.popen.args} ignored SIGTERM for {timeout} s; stacks:\n"
                f"{self.output()[-6000:]}"
            ) from None
        finally:
            self._close_log()

    def output(self) -> str:
        return self.log_path.read_text(errors="replace")

    def kill(self) -> None:
        if self.popen.poll() is None:
            self.popen.kill()
            self.popen.wait()
        self._close_log()


# --- the hub's own view, for readiness ----------------------------------------------------------


class HubClient:
    """A Zenoh client session of the test's own to a hub on loopback: asks the hub's status
    request (`fleetdaq/<site>/hub/status`), the hub's read model as JSON."""

    def __init__(self, port: int, site: str) -> None:
        import zenoh

        from fleetdaq.contract.keys import SiteKeys
        from fleetdaq.runtime.zenoh_session import client_config

        self.keys = SiteKeys(site)
        # Opening waits for the router at most 20 s; the session reconnects by itself after.
        self.session = zenoh.open(client_config([f"tcp/127.0.0.1:{port}"], timeout_ms=20_000))

    def status(self, timeout: float = 2.0) -> dict[str, Any] | None:
        """The hub's status, or None when no hub answers within `timeout` s."""
        from fleetdaq.hub.live.status_query import query_status

        return query_status(self.session, self.keys, timeout)

    def wait(self, cond: Callable[[dict[str, Any]], object], timeout: float, what: str) -> Any:
        """Poll the status until `cond(status)` is truthy; returns that value."""

        def probe() -> object:
            status = self.status()
            return cond(status) if status is not None else None

        return wait_until(probe, timeout, what, every=0.2)

    def close(self) -> None:
        self.session.close()

    def __enter__(self) -> HubClient:
        return self

    def __exit__(
        self, t: type[BaseException] | None, e: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()


def stream_view(status: dict[str, Any], node: str, stream: str) -> dict[str, Any] | None:
    """One stream's accounting in a hub status (`fleetdaq.hub.read_model.StreamView`)."""
    return next(
        (s for s in status.get("streams", []) if (s["node"], s["stream"]) == (node, stream)),
        None,
    )


def sessions(data: Path) -> list[Path]:
    """The recording sessions under a hub's data folder (named by their UTC start; not the
    ``snapshots`` folder, the outbox, ...)."""
    return sorted(p for p in data.iterdir() if p.is_dir() and p.name[:1].isdigit())


def node_alive(status: dict[str, Any], node: str) -> bool:
    return any(n["node"] == node and n["alive"] for n in status.get("nodes", []))


# --- an edge's network link, cut and restored ----------------------------------------------------


class Link:
    """A TCP relay on loopback to `target_port`: the network link between an edge and its hub.

    Point the edge at `port` (`fleetdaq edge --connect tcp/127.0.0.1:<port>`); `cut()` drops
    every connection through it and turns new ones away until `restore()`, like a cable pulled
    and plugged back in, while both processes run on.
    """

    def __init__(self, target_port: int) -> None:
        self.target = target_port
        self._listener = socket.create_server(("127.0.0.1", 0))
        self._listener.settimeout(0.2)
        self.port = int(self._listener.getsockname()[1])
        self._up = threading.Event()
        self._up.set()
        self._closed = threading.Event()
        self._lock = threading.Lock()
        self._open: set[socket.socket] = set()
        self.connections = 0
        """Connections relayed so far."""
        self._thread = threading.Thread(target=self._accept, name="link", daemon=True)
        self._thread.start()

    def _accept(self) -> None:
        while not self._closed.is_set():
            try:
                conn, _ = self._listener.accept()
            except TimeoutError:
                continue
            except OSError:
                return
            if not self._up.is_set():
                conn.close()
                continue
            try:
                upstream = socket.create_connection(("127.0.0.1", self.target), timeout=5)
            except OSError:
                conn.close()
                continue
            conn.settimeout(None)
            upstream.settimeout(None)
            with self._lock:
                self._open |= {conn, upstream}
                self.connections += 1
            for src, dst in ((conn, upstream), (upstream, conn)):
                threading.Thread(target=self._pump, args=(src, dst), daemon=True).start()

    def _pump(self, src: socket.socket, dst: socket.socket) -> None:
        try:
            while data := src.recv(65536):
                dst.sendall(data)
        except OSError:
            pass
        finally:
            self._drop(src, dst)

    def _drop(self, *socks: socket.socket) -> None:
        for s in socks:
            with contextlib.suppress(OSError):
                s.shutdown(socket.SHUT_RDWR)
            s.close()
            with self._lock:
                self._open.discard(s)

    def cut(self) -> None:
        self._up.clear()
        with self._lock:
            socks = list(self._open)
        self._drop(*socks)

    def restore(self) -> None:
        self._up.set()

    def close(self) -> None:
        self._closed.set()
        self.cut()
        self._thread.join(5)
        self._listener.close()


# --- an edge's spool, read without opening it ----------------------------------------------------

_SPOOL_RECORD = struct.Struct("<IQqII")  # magic, sequence, first-sample time ns, length, crc32
_SPOOL_MAGIC = 0x31514446


def spooled(directory: Path) -> list[tuple[int, int]]:
    """(sequence, first-sample time ns) of every complete record in a stream's spool segments,
    read from the files only: safe while the edge runs (segments are append-only; one deleted
    meanwhile is skipped)."""
    out: list[tuple[int, int]] = []
    for seg in sorted(directory.glob("*.seg")):
        try:
            data = seg.read_bytes()
        except FileNotFoundError:
            continue
        pos = 0
        while pos + _SPOOL_RECORD.size <= len(data):
            magic, seq, t_ns, length, _ = _SPOOL_RECORD.unpack_from(data, pos)
            end = pos + _SPOOL_RECORD.size + length
            if magic != _SPOOL_MAGIC or end > len(data):
                break
            out.append((seq, t_ns))
            pos = end
    return out
