"""A small Foxglove WebSocket client for tests, written from the protocol's documentation
(github.com/foxglove/ws-protocol, docs/spec.md), not from the server's code: aiohttp on its own
event-loop thread, collecting what the server sends for the test's thread to wait on.

Server -> client: text frames are JSON with an ``op`` (``serverInfo``, ``advertise``,
``unadvertise``, ``status``, ...); binary frames start with an opcode byte: 1 = message data
(uint32 subscription id, uint64 log time ns, payload; little-endian), 2 = time (uint64 ns).
Client -> server: ``subscribe`` / ``unsubscribe`` (JSON).

It offers the subprotocols Lichtblick offers (``foxglove.websocket.v1``, then
``foxglove.sdk.v1``); the hub answers either (`fleetdaq.hub.live.foxglove.front`), the second when
both."""

from __future__ import annotations

import asyncio
import itertools
import json
import ssl
import struct
import threading
import time
from collections.abc import Callable, Coroutine
from dataclasses import dataclass
from typing import Any, TypeVar

import aiohttp

LICHTBLICK_SUBPROTOCOLS = ("foxglove.websocket.v1", "foxglove.sdk.v1")
MESSAGE_DATA = 1
TIME = 2
_MESSAGE_HEADER = struct.Struct("<BIQ")
_TIME = struct.Struct("<BQ")
T = TypeVar("T")


@dataclass(frozen=True, slots=True)
class Received:
    log_time_ns: int
    payload: bytes

    def json(self) -> Any:
        return json.loads(self.payload)


class FoxgloveClient:
    def __init__(
        self,
        url: str,
        subprotocols: tuple[str, ...] = LICHTBLICK_SUBPROTOCOLS,
        timeout: float = 20,
        tls: ssl.SSLContext | None = None,
    ) -> None:
        self.url = url
        self.tls = tls
        self.server_info: dict[str, Any] | None = None
        self.channels: dict[int, dict[str, Any]] = {}
        self.statuses: list[dict[str, Any]] = []
        self.times: list[int] = []
        self.unknown: list[bytes] = []
        self.closed = False
        self.protocol: str | None = None
        self._messages: dict[int, list[Received]] = {}
        self._lock = threading.Lock()
        self._ids = itertools.count(1)
        self._loop = asyncio.new_event_loop()
        self._thread = threading.Thread(target=self._loop.run_forever, daemon=True)
        self._thread.start()
        self._session: aiohttp.ClientSession | None = None
        self._ws: aiohttp.ClientWebSocketResponse | None = None
        try:
            self._call(self._connect(subprotocols), timeout)
        except BaseException:
            self.close()
            raise
        self._reader = asyncio.run_coroutine_threadsafe(self._read(), self._loop)

    # --- the loop's side ---------------------------------------------------------------------

    def _call(self, coro: Coroutine[Any, Any, T], timeout: float = 10) -> T:
        return asyncio.run_coroutine_threadsafe(coro, self._loop).result(timeout)

    async def _connect(self, subprotocols: tuple[str, ...]) -> None:
        self._session = aiohttp.ClientSession()
        self._ws = await self._session.ws_connect(
            self.url,
            protocols=subprotocols,
            max_msg_size=64 << 20,
            autoping=True,
            ssl=self.tls if self.tls is not None else True,
        )
        self.protocol = self._ws.protocol

    async def _read(self) -> None:
        assert self._ws is not None
        try:
            async for msg in self._ws:
                if msg.type == aiohttp.WSMsgType.TEXT:
                    self._on_text(json.loads(msg.data))
                elif msg.type == aiohttp.WSMsgType.BINARY:
                    self._on_binary(bytes(msg.data))
        finally:
            self.closed = True

    def _on_text(self, m: dict[str, Any]) -> None:
        with self._lock:
            op = m.get("op")
            if op == "serverInfo":
                self.server_info = m
            elif op == "advertise":
                for ch in m["channels"]:
                    self.channels[int(ch["id"])] = ch
            elif op == "unadvertise":
                for cid in m["channelIds"]:
                    self.channels.pop(int(cid), None)
            elif op == "status":
                self.statuses.append(m)

    def _on_binary(self, data: bytes) -> None:
        with self._lock:
            if data[:1] == bytes([MESSAGE_DATA]) and len(data) >= _MESSAGE_HEADER.size:
                _, sub, log_time = _MESSAGE_HEADER.unpack_from(data)
                received = Received(log_time, data[_MESSAGE_HEADER.size :])
                self._messages.setdefault(sub, []).append(received)
            elif data[:1] == bytes([TIME]) and len(data) == _TIME.size:
                self.times.append(_TIME.unpack(data)[1])
            else:
                self.unknown.append(data)

    # --- the test's side ---------------------------------------------------------------------

    def wait(self, cond: Callable[[], T | None], timeout: float, what: str) -> T:
        """Poll `cond` until it returns something truthy (returned); fail after `timeout` s."""
        deadline = time.monotonic() + timeout
        while True:
            value = cond()
            if value:
                return value
            if time.monotonic() > deadline:
                raise AssertionError(f"timed out after {timeout} s waiting for {what}")
            time.sleep(0.05)

    def channel(self, topic: str) -> dict[str, Any]:
        with self._lock:
            (ch,) = [c for c in self.channels.values() if c["topic"] == topic]
            return ch

    def topics(self) -> set[str]:
        with self._lock:
            return {c["topic"] for c in self.channels.values()}

    def send_json(self, m: object) -> None:
        self.send_text(json.dumps(m))

    def send_text(self, text: str) -> None:
        assert self._ws is not None
        self._call(self._ws.send_str(text))

    def send_bytes(self, data: bytes) -> None:
        assert self._ws is not None
        self._call(self._ws.send_bytes(data))

    def subscribe(self, topic: str) -> int:
        """Subscribe to `topic`; returns the subscription id its messages come with."""
        sub = next(self._ids)
        self.send_json(
            {
                "op": "subscribe",
                "subscriptions": [{"id": sub, "channelId": self.channel(topic)["id"]}],
            }
        )
        return sub

    def unsubscribe(self, sub: int) -> None:
        self.send_json({"op": "unsubscribe", "subscriptionIds": [sub]})

    def messages(self, sub: int) -> list[Received]:
        with self._lock:
            return list(self._messages.get(sub, []))

    def close(self) -> None:
        async def shut() -> None:
            if self._ws is not None:
                await self._ws.close()
            if self._session is not None:
                await self._session.close()

        if self._thread.is_alive():
            try:
                self._call(shut(), 10)
            finally:
                self._loop.call_soon_threadsafe(self._loop.stop)
                self._thread.join(10)
        self._loop.close()

    def __enter__(self) -> FoxgloveClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
