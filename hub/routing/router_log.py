"""What the embedded Zenoh router refuses, read from the router's own log: messages its access
control list drops, and TLS handshakes it refuses.

Why the log: zenoh 1.10 tells these nowhere else. The router decides both in Rust; the
admin space lists open transports only, the drop counters (``zenoh_stats``) are not compiled
into the eclipse-zenoh wheel, and zenoh-python's bridge of Rust logs into Python `logging` is
commented out in its ``lib.rs``. What remains is the ``tracing`` subscriber that
``zenoh.try_init_log_from_env`` installs: it writes to the process's stdout (fd 1), filtered by
``RUST_LOG``. So, with TLS on, the hub

- turns on exactly the lines it needs (`DIRECTIVES`, added to any ``RUST_LOG`` of the user's),
- points fd 1 at a pipe that a thread reads: the lines below are parsed, every other line
  (the hub's own prints, a user's ``RUST_LOG`` output) goes on to the real stdout unchanged,
- and confirms at start that the router's log does arrive (`ACL_ENABLED`, written while the
  router opens): a zenoh that writes other lines, or a log already taken by someone else, is
  a start-up error event instead of a counter that silently stays at 0.

The lines (zenoh 1.10.x; ``tests/test_refused_traffic.py`` runs them against the real
router, so an upgrade that changes them fails that test):

- ``zenoh::net::routing::interceptor::access_control`` TRACE: ``<zid> on <subject> is
  unauthorized to Put (ingress) on <key>`` for every denied message (and ``Using cached
  result: <zid> is unauthorized to ...``); INFO at a transport's start: ``<zid> did not match
  any configured ACL subject. Default permission `Deny` ...`` (a certificate the site does not
  know: everything it sends is then dropped with no line of its own).
- ``zenoh_transport::unicast::establishment::accept`` DEBUG, once per connection: ``New
  transport link accepted from <zid> to <zid>: ... dst: tls/<address>`` (who a zid is).
- ``zenoh_link_tls::unicast`` DEBUG, once per connection: ``Accepted TLS connection on
  <address>: <peer address>. Common Name: <cn>.``; WARN: ``<rustls error>. Hint: increase the
  system open file limit.`` for a refused handshake. zenoh does not write the peer's address
  there (the TLS listener's error carries it, the log line does not), so a refused handshake
  is counted by its reason.

Cost: the ACL's TRACE level also writes one line per *allowed* message the router filters
(an edge's batches, health and events); the thread drops them with one byte search each.
"""

from __future__ import annotations

import contextlib
import fcntl
import os
import re
import sys
import threading
from dataclasses import dataclass
from typing import Protocol

import zenoh

from fleetdaq.hub.bus import worth_telling

DIRECTIVES = (
    "zenoh::net::routing::interceptor::access_control=trace",
    "zenoh_transport::unicast::establishment::accept=debug",
    "zenoh_link_tls::unicast=debug",
)
_LONGEST_LINE = 1 << 20
ACL_ENABLED = "Access control is enabled"
"""The line the ACL writes (DEBUG) while the router opens: proof that the log arrives."""

_ANSI = re.compile(r"\x1b\[[0-9;]*m")
_LINE = re.compile(
    r"^\S+\s+(?P<level>TRACE|DEBUG|INFO|WARN|ERROR)\s.*?ThreadId\((?P<thread>\d+)\)"
    r".*? (?P<target>zenoh[\w:]*): (?P<msg>.*)$"
)
_ACL_TARGET = "zenoh::net::routing::interceptor::access_control"
_ACCEPT_TARGET = "zenoh_transport::unicast::establishment::accept"
_TLS_TARGET = "zenoh_link_tls::unicast"
_DENIED = re.compile(
    r"^(?:Using cached result: (?P<czid>[0-9a-f]+)|(?P<zid>[0-9a-f]+) on (?P<subject>\S+))"
    r" is unauthorized to (?P<what>.+?) \((?P<flow>ingress|egress)\)"
    r" on (?:Some\((?P<some>.+)\)|(?P<key>.+))$"
)
_CACHING = re.compile(
    r"^ACL \((?P<flow>ingress|egress)\): caching permissions for `(?P<key>.*)` \.\.\.$"
)
CACHED_ACTIONS = (
    "Query",
    "Reply",
    "Put",
    "Delete",
    "Declare/Undeclare Subscriber",
    "Declare/Undeclare Queryable",
    "Declare/Undeclare Liveliness Token",
    "Liveliness Query",
    "Declare Liveliness Subscriber",
)
"""What the ACL decides, in this order, when it caches its decisions for a key (its
``compute_keyexpr_cache``): lines that are no message of anyone's."""
_NO_SUBJECT = re.compile(r"^(?P<zid>[0-9a-f]+) did not match any configured ACL subject\.")
_ACCEPTED = re.compile(
    r"^New transport link accepted from (?P<zid>[0-9a-f]+) to [0-9a-f]+: .*?"
    r"\bdst: (?:tls|quic|tcp)/(?P<address>[^,\s]+)"
)
_TLS_ACCEPTED = re.compile(
    r"^Accepted TLS connection on \S+: (?P<address>\S+)\. Common Name: (?P<cn>.*)\.$"
)
_TLS_REFUSED = re.compile(r"^(?P<reason>.+)\. Hint: increase the system open file limit\.$")
_CN = re.compile(r"CertCommonName\((?P<cn>[^)]*)\)")


@dataclass(frozen=True, slots=True)
class AclDenial:
    """A message the router's ACL dropped: from `zid` (certificate `cn`), `what` (``Put
    (ingress)``, ``Query (ingress)``, ...) on `key`; `cn` is "" when the line does not say."""

    zid: str
    cn: str
    what: str
    key: str


@dataclass(frozen=True, slots=True)
class UnknownSubject:
    """A peer whose certificate matches no subject of the ACL: all it sends is dropped."""

    zid: str


@dataclass(frozen=True, slots=True)
class PeerAccepted:
    """A transport accepted from `zid` at `address` (``ip:port``)."""

    zid: str
    address: str


@dataclass(frozen=True, slots=True)
class TlsAccepted:
    """A TLS connection accepted from `address` with a certificate whose common name is `cn`."""

    address: str
    cn: str


@dataclass(frozen=True, slots=True)
class TlsRefusal:
    """A TLS handshake the router refused, with rustls' reason."""

    reason: str


RouterLine = AclDenial | UnknownSubject | PeerAccepted | TlsAccepted | TlsRefusal


class RefusalSink(Protocol):
    """Where the tap's findings go (`fleetdaq.hub.routing.refused_traffic.RefusedTraffic`)."""

    def refused(self, line: RouterLine) -> None:
        """One finding, in the log's order."""

    def publish(self) -> None:
        """After each read that held findings."""


class RouterLogReader:
    """Turns the router's log, line by line, into what it tells about refused traffic.

    Stateful for one reason: when the ACL first meets a key it decides every kind of message
    on it at once (`CACHED_ACTIONS`), writing an "is unauthorized" line for each kind it
    denies although no such message came; those lines follow its "caching permissions" line
    on the same thread and are skipped here."""

    def __init__(self) -> None:
        self._caching: dict[str, tuple[str, str, int]] = {}  # thread -> flow, key, next action

    def read(self, line: str) -> RouterLine | None:
        """What `line` tells (None: nothing)."""
        m = _LINE.match(_ANSI.sub("", line).rstrip("\r\n"))
        if m is None:
            return None
        target, msg, thread = m["target"], m["msg"], m["thread"]
        if target == _ACL_TARGET:
            return self._acl(thread, msg)
        if target == _ACCEPT_TARGET:
            if a := _ACCEPTED.match(msg):
                return PeerAccepted(a["zid"], a["address"])
        elif target == _TLS_TARGET:
            if m["level"] == "WARN" and (t := _TLS_REFUSED.match(msg)):
                return TlsRefusal(t["reason"])
            if c := _TLS_ACCEPTED.match(msg):
                return TlsAccepted(c["address"], c["cn"])
        return None

    def _acl(self, thread: str, msg: str) -> RouterLine | None:
        caching = self._caching.pop(thread, None)
        if c := _CACHING.match(msg):
            self._caching[thread] = (c["flow"], c["key"], 0)
            return None
        d = _DENIED.match(msg)
        if d is None:
            if u := _NO_SUBJECT.match(msg):
                return UnknownSubject(u["zid"])
            return None
        key = d["key"] if d["key"] is not None else d["some"]
        if caching is not None and d["czid"] is None:
            flow, cached_key, at = caching
            try:
                action = CACHED_ACTIONS.index(d["what"], at)
            except ValueError:
                action = -1
            if action >= 0 and (d["flow"], key) == (flow, cached_key):
                self._caching[thread] = (flow, cached_key, action)
                return None
        cn = _CN.search(d["subject"] or "")
        what = f"{d['what']} ({d['flow']})"
        return AclDenial(d["czid"] or d["zid"], cn["cn"] if cn else "", what, key)


class RouterLogError(Exception):
    """The router's log cannot be read (it is already taken, or says other things)."""


class RouterLogTap:
    """Reads the router's log from fd 1 while it runs (see the module's docstring); calls
    `sink` with what it finds, on the tap's own thread.

    One per process at a time (there is one fd 1 and one Rust log subscriber); `start` before
    the router opens, `wait_enabled` after, `stop` after it closes."""

    def __init__(self, sink: RefusalSink) -> None:
        self.sink = sink
        self._reader = RouterLogReader()
        self._found = False
        self._saved: int | None = None
        self._read: int | None = None
        self._thread: threading.Thread | None = None
        self._enabled = threading.Event()
        self._verbose = bool(os.environ.get("RUST_LOG"))
        self.died: str | None = None
        """Why the tap's thread stopped while the router ran (None: it runs, or was stopped)."""

    def start(self) -> None:
        with _PROCESS.lock:
            if _PROCESS.taken:
                raise RouterLogError("another router in this process already reads the log")
            _PROCESS.taken = True
        try:
            _PROCESS.init_rust_log()
            sys.stdout.flush()
            saved = os.dup(1)
            try:
                self._read, write = os.pipe()
                # Room for a burst of lines while this thread waits for the GIL: a full pipe
                # would hold up the router's threads that write them (1 MiB, the default most
                # a process may ask for; the kernel's 64 KiB if refused).
                with contextlib.suppress(OSError, AttributeError):
                    fcntl.fcntl(write, fcntl.F_SETPIPE_SZ, 1 << 20)
                os.dup2(write, 1)
                os.close(write)
            except OSError:
                os.close(saved)
                raise
        except BaseException:
            with _PROCESS.lock:
                _PROCESS.taken = False
            raise
        self._saved = saved
        self._thread = threading.Thread(target=self._pump, name="router-log", daemon=True)
        self._thread.start()

    def wait_enabled(self, timeout: float = 10.0) -> None:
        """Raise `RouterLogError` unless the router's ACL line arrived within `timeout` s."""
        if not self._enabled.wait(timeout):
            raise RouterLogError(
                f"the router's log did not say {ACL_ENABLED!r} within {timeout:g} s: this zenoh "
                "writes other lines than hub/router_log.py reads, or something else in this "
                "process set up zenoh's log first"
            )

    def stop(self) -> None:
        """Give fd 1 back and let the thread pass on what is left (idempotent)."""
        saved, self._saved = self._saved, None
        if saved is None:
            return
        with contextlib.suppress(ValueError, OSError):
            sys.stdout.flush()
        os.dup2(saved, 1)  # closes the pipe's write end: the thread reads to its end
        if self._thread is not None:
            self._thread.join(5.0)
        os.close(saved)
        with _PROCESS.lock:
            _PROCESS.taken = False

    def _pump(self) -> None:
        read, out = self._read, self._saved
        assert read is not None
        assert out is not None
        try:
            self._drain(read, out)
        except BaseException as err:
            # Nobody would read the pipe any more: a full one would hold up every thread that
            # writes a line (the router's included). Give fd 1 back first, then say so.
            if self._saved is not None:
                with contextlib.suppress(OSError):
                    os.dup2(out, 1)
            self.died = f"{type(err).__name__}: {err}"
            _complain(err)
            raise
        finally:
            os.close(read)

    def _drain(self, read: int, out: int) -> None:
        rest = b""
        while chunk := os.read(read, 65536):
            lines = (rest + chunk).split(b"\n")
            rest = lines.pop()
            if len(rest) > _LONGEST_LINE:  # output that is no log line: pass it on as it is
                lines.append(rest)
                rest = b""
            keep = [line for line in lines if self._take(line)]
            if self._found:
                self._found = False
                self._publish()
            if keep:
                _write_all(out, b"\n".join(keep) + b"\n")
        if rest:
            _write_all(out, rest)

    def _publish(self) -> None:
        try:
            self.sink.publish()
        except Exception as err:  # the pipe must be drained whatever happens
            _complain(err)

    def _take(self, raw: bytes) -> bool:
        """Handle one line; True to pass it on to the real stdout."""
        if b"zenoh" not in raw:
            return True  # the hub's own output: the common case, one search
        if b" is authorized to " in raw:
            return self._verbose
        line = raw.decode(errors="replace")
        if not self._enabled.is_set() and ACL_ENABLED in line:
            self._enabled.set()
            return self._verbose
        found = None
        try:
            found = self._reader.read(line)
            if found is not None:
                self._found = True
                self.sink.refused(found)
        except Exception as err:  # one line never stops the tap
            _complain(err)
        # what the hub turned on for itself stays out of its stdout, but for a problem
        return self._verbose or (found is None and (b" WARN " in raw or b" ERROR " in raw))


class _ProcessLog:
    """What there is one of per process: fd 1 and Rust's log subscriber."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.taken = False
        self.rust_log_on = False
        self.complaints = 0

    def init_rust_log(self) -> None:
        """Install zenoh's log subscriber with `DIRECTIVES` (once: Rust allows one)."""
        if self.rust_log_on:
            return
        user = os.environ.get("RUST_LOG", "")
        saved = {k: os.environ.get(k) for k in ("RUST_LOG", "NO_COLOR")}
        os.environ["RUST_LOG"] = ",".join([user or "off", *DIRECTIVES])
        os.environ["NO_COLOR"] = "1"  # plain lines into the pipe
        try:
            zenoh.try_init_log_from_env()
        finally:
            for k, v in saved.items():
                if v is None:
                    os.environ.pop(k, None)
                else:
                    os.environ[k] = v
        self.rust_log_on = True


_PROCESS = _ProcessLog()


def _complain(err: BaseException) -> None:
    # stderr: the bus may be what failed; a stopped tap would block the router's threads
    _PROCESS.complaints += 1
    if worth_telling(n := _PROCESS.complaints):
        _write_all(2, f"fleetdaq: the router's log tap ({n} so far): {err!r}\n".encode())


def _write_all(fd: int, data: bytes) -> None:
    view = memoryview(data)
    while view:
        try:
            n = os.write(fd, view)
        except OSError:
            return  # the real stdout is gone (a closed pipe): nothing more to pass on
        view = view[n:]
