"""The front of the Foxglove live view: what listens on ``hub.dashboard.foxglove.listen``, so
that clients offering either name of the Foxglove WebSocket protocol get in.

Why a front: the protocol is named ``foxglove.websocket.v1`` by its specification and by the
clients built on it (the npm ``@foxglove/ws-protocol`` client, Lichtblick before 1.22, tools on
the open protocol), and ``foxglove.sdk.v1`` by foxglove-sdk, whose server (Rust, in
``handshake.rs``) answers any handshake that does not offer ``foxglove.sdk.v1`` with HTTP 400
"Missing expected sec-websocket-protocol header". No release up to 0.30.3 and no option of
``start_server`` changes that; the two names are one wire protocol (the SDK's own clients and
Lichtblick treat them as equal).

How: the SDK's server listens on an ephemeral port of 127.0.0.1; this front listens where the
site file says (TLS ends here when ``tls`` is set), reads each connection's HTTP upgrade
request (at most `MAX_HEAD` bytes, within `HEAD_TIMEOUT_S`), and

- a request offering ``foxglove.sdk.v1`` (Foxglove, Lichtblick, fleetdaq's own clients) goes
  to the SDK unchanged;
- a request offering ``foxglove.websocket.v1`` but not ``foxglove.sdk.v1`` goes with that
  header renamed, and the SDK's answer comes back with the name the client offered;
- anything else goes unchanged, for the SDK to refuse (400) as it would without the front;
- a request head that is too long, too slow or not HTTP is answered 400 or 408 here, counted.

After the handshake the front copies bytes both ways without reading them: every frame is still
the SDK's to check, and a slow client still fills the SDK's per-client queue (the copy waits
for the client's socket to drain before reading more), so the SDK's drop-oldest holds.

Chosen over a WebSocket relay (aiohttp on both sides) because that would decode and re-encode
every message in Python and put a second WebSocket implementation, with its own limits,
compression and close handling, between the viewer and the SDK; the byte copy has no
per-message work and changes one header line. Its cost, measured with ``bench/foxglove.py``, is
in the README (Foxglove live view). What the SDK's log says about a client names the front's
loopback address, not the client's.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import socket
import ssl
import threading
from typing import Final

from fleetdaq.hub.bus import worth_telling
from fleetdaq.runtime.threads import NamedThread

log = logging.getLogger("fleetdaq.foxglove")

SDK_SUBPROTOCOL: Final = "foxglove.sdk.v1"
SPEC_SUBPROTOCOL: Final = "foxglove.websocket.v1"
MAX_HEAD: Final = 16 << 10
"""An upgrade request's head (request line and headers): browsers send under 2 KiB."""
HEAD_TIMEOUT_S: Final = 10.0
COPY_CHUNK: Final = 256 << 10
_PROTOCOL_HEADER: Final = b"sec-websocket-protocol"


def offered(head: bytes) -> list[str]:
    """The subprotocols a request head offers, in its order (every
    ``Sec-WebSocket-Protocol`` line, comma-separated)."""
    out: list[str] = []
    for line in head.split(b"\r\n")[1:]:
        name, colon, value = line.partition(b":")
        if colon and name.strip().lower() == _PROTOCOL_HEADER:
            out += [t.strip() for t in value.decode("latin-1").split(",") if t.strip()]
    return out


def with_protocol(head: bytes, protocol: str) -> bytes:
    """`head` with its ``Sec-WebSocket-Protocol`` lines replaced by one naming `protocol`."""
    lines = head.split(b"\r\n")
    kept = [ln for ln in lines[1:] if ln.partition(b":")[0].strip().lower() != _PROTOCOL_HEADER]
    # The head ends with an empty line (b"...\r\n\r\n" splits into two empty strings).
    while kept and not kept[-1]:
        kept.pop()
    line = f"Sec-WebSocket-Protocol: {protocol}".encode()
    return b"\r\n".join([lines[0], *kept, line]) + b"\r\n\r\n"


def _answer(status: str, reason: str) -> bytes:
    body = reason.encode()
    return (
        f"HTTP/1.1 {status}\r\nContent-Type: text/plain\r\nContent-Length: {len(body)}\r\n"
        "Connection: close\r\n\r\n"
    ).encode() + body


class SubprotocolFront:
    """Listens on (`host`, `port`) and hands each connection to the SDK's server on
    127.0.0.1:`upstream_port`, renaming the subprotocol for clients that offer only the
    specification's name. Its own thread and event loop; `start` binds or raises `OSError`."""

    def __init__(
        self, host: str, port: int, upstream_port: int, tls: ssl.SSLContext | None = None
    ) -> None:
        self.host = host
        self.requested_port = port
        self.upstream_port = upstream_port
        self.tls = tls
        self.counts = {
            "connections": 0, "renamed": 0, "refused": 0, "upstream_errors": 0,
            "connection_errors": 0,
        }  # fmt: skip
        self._sock: socket.socket | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._server: asyncio.Server | None = None
        self._ready = threading.Event()
        self._failed: BaseException | None = None
        self._thread = NamedThread(target=self._run, name="foxglove-front", daemon=True)
        self._connections: set[asyncio.Task[None]] = set()

    @property
    def port(self) -> int:
        """The port as bound (the system's choice when the site file says 0)."""
        if self._sock is None:
            return self.requested_port
        return int(self._sock.getsockname()[1])

    def alive(self) -> bool:
        return self._thread.is_alive()

    def bind(self) -> None:
        """Take the listening address (`OSError` when it cannot be had)."""
        family, _, _, _, address = socket.getaddrinfo(
            self.host or None, self.requested_port, type=socket.SOCK_STREAM,
            flags=socket.AI_PASSIVE,
        )[0]  # fmt: skip
        self._sock = socket.create_server(address[:2], family=family, backlog=128)

    def start(self) -> None:
        """Serve (after `bind`, and once `upstream_port` is the SDK's)."""
        if self._sock is None:
            self.bind()
        self._thread.start()
        self._ready.wait(30)
        if self._failed is not None:
            self.stop()
            raise OSError(f"the front did not start: {self._failed}")

    def stop(self) -> None:
        loop = self._loop
        if loop is not None and self._thread.is_alive():
            asyncio.run_coroutine_threadsafe(self._shutdown(), loop)
            self._thread.join(15)
        if self._sock is not None:
            self._sock.close()

    # --- the loop's thread ---------------------------------------------------------------------

    def _run(self) -> None:
        loop = asyncio.new_event_loop()
        loop.set_exception_handler(self._loop_error)
        self._loop = loop
        try:
            self._server = loop.run_until_complete(
                asyncio.start_server(
                    self._connection, sock=self._sock, ssl=self.tls, limit=MAX_HEAD,
                    ssl_handshake_timeout=HEAD_TIMEOUT_S if self.tls else None,
                )
            )  # fmt: skip
        except BaseException as err:  # said by start(), on the caller's thread
            self._failed = err
            self._ready.set()
            loop.close()
            return
        self._ready.set()
        try:
            loop.run_forever()
        finally:
            loop.close()

    async def _shutdown(self) -> None:
        if self._server is not None:
            self._server.close()
        for task in list(self._connections):
            task.cancel()
        if self._connections:
            await asyncio.wait(self._connections, timeout=5)
        asyncio.get_running_loop().stop()

    def _loop_error(self, loop: asyncio.AbstractEventLoop, context: dict[str, object]) -> None:
        """What asyncio would log about one connection (a failed TLS handshake, ...): counted,
        said the first times and every 1000th, so a client in a loop cannot fill the log."""
        self.counts["connection_errors"] += 1
        if worth_telling(self.counts["connection_errors"], first=10):
            log.warning(
                "Foxglove live view: a connection failed: %s %s (%d so far)",
                context.get("message", ""), context.get("exception", ""),
                self.counts["connection_errors"],
            )  # fmt: skip

    def _refused(self, why: str) -> None:
        self.counts["refused"] += 1
        if worth_telling(self.counts["refused"], first=10):
            log.warning(
                "Foxglove live view: refused a connection (%s; %d so far)",
                why, self.counts["refused"],
            )  # fmt: skip

    async def _connection(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        task = asyncio.current_task()
        assert task is not None
        self._connections.add(task)
        self.counts["connections"] += 1
        upstream: asyncio.StreamWriter | None = None
        try:
            try:
                head = await asyncio.wait_for(reader.readuntil(b"\r\n\r\n"), HEAD_TIMEOUT_S)
            except TimeoutError:
                self._refused(f"no request head within {HEAD_TIMEOUT_S:g} s")
                writer.write(_answer("408 Request Timeout", "no request head in time"))
                return
            except (asyncio.LimitOverrunError, ValueError):
                self._refused(f"a request head over {MAX_HEAD} bytes")
                writer.write(_answer("400 Bad Request", "request head too long"))
                return
            except asyncio.IncompleteReadError:
                return  # gone before it said anything: nothing to answer
            if not head.split(b"\r\n", 1)[0].endswith((b" HTTP/1.1", b" HTTP/1.0")):
                self._refused("not an HTTP request")
                writer.write(_answer("400 Bad Request", "not an HTTP request"))
                return
            protocols = offered(head)
            rename = SPEC_SUBPROTOCOL in protocols and SDK_SUBPROTOCOL not in protocols
            if rename:
                head = with_protocol(head, SDK_SUBPROTOCOL)
            try:
                up_reader, upstream = await asyncio.open_connection(
                    "127.0.0.1", self.upstream_port, limit=COPY_CHUNK
                )
            except OSError as err:
                self.counts["upstream_errors"] += 1
                if worth_telling(self.counts["upstream_errors"], first=10):
                    log.error("Foxglove live view: its server did not take a client: %s", err)
                writer.write(_answer("503 Service Unavailable", "the live view is not running"))
                return
            upstream.write(head)
            if rename:
                answer = await asyncio.wait_for(up_reader.readuntil(b"\r\n\r\n"), HEAD_TIMEOUT_S)
                if answer.startswith(b"HTTP/1.1 101"):
                    answer = with_protocol(answer, SPEC_SUBPROTOCOL)
                    self.counts["renamed"] += 1
                writer.write(answer)
            await _pipe(reader, writer, up_reader, upstream)
        except (OSError, asyncio.IncompleteReadError, asyncio.LimitOverrunError, TimeoutError):
            pass  # a connection that broke: the SDK sees it end
        finally:
            for w in (writer, upstream):
                if w is not None:
                    with contextlib.suppress(Exception):
                        w.close()
            self._connections.discard(task)


async def _copy(src: asyncio.StreamReader, dst: asyncio.StreamWriter) -> None:
    while data := await src.read(COPY_CHUNK):
        dst.write(data)
        await dst.drain()  # a slow reader holds the copy, and so the sender, back
    if dst.can_write_eof():
        with contextlib.suppress(OSError):
            dst.write_eof()


async def _pipe(
    client_r: asyncio.StreamReader,
    client_w: asyncio.StreamWriter,
    up_r: asyncio.StreamReader,
    up_w: asyncio.StreamWriter,
) -> None:
    """Both directions until one ends; the other then has a moment to finish its close."""
    tasks = {
        asyncio.ensure_future(_copy(client_r, up_w)),
        asyncio.ensure_future(_copy(up_r, client_w)),
    }
    try:
        _, pending = await asyncio.wait(tasks, return_when=asyncio.FIRST_COMPLETED)
        if pending:
            await asyncio.wait(pending, timeout=2)
    finally:
        for t in tasks:
            t.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
