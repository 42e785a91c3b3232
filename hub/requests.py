"""Operators' requests to the hub: a Zenoh query on ``fleetdaq/<site>/hub/<what>`` whose payload
is a JSON object and whose reply is JSON. The parsing every such service shares (size bound,
JSON object, no unknown field, bounded text) and `RequestService`, which declares the queryable
and answers each request on a small pool, never on a Zenoh thread (an answer may block: a
recorder flushing, an edge being asked). The dashboard calls the same `handle` directly, so
the command line and the page are the same path with the same checks.
"""

from __future__ import annotations

import contextlib
import json
import logging
from collections.abc import Iterable
from concurrent.futures import ThreadPoolExecutor
from typing import Any

from hub.read_model import to_jsonable
from hub.router import Router

log = logging.getLogger("fleetdaq.hub")

MAX_REQUEST_BYTES = 64 * 1024


class BadRequest(ValueError):
    pass


def parse_object(raw: bytes, allowed: Iterable[str]) -> dict[str, Any]:
    """The request as a dict: at most 64 KiB, a JSON object, only `allowed` keys."""
    if len(raw) > MAX_REQUEST_BYTES:
        raise BadRequest(f"a request of {len(raw)} bytes (at most {MAX_REQUEST_BYTES})")
    try:
        req = json.loads(raw or b"{}")
    except (ValueError, RecursionError):
        raise BadRequest("the request is not JSON") from None
    if not isinstance(req, dict):
        raise BadRequest("the request is not a JSON object")
    unknown = set(req) - set(allowed)
    if unknown:
        raise BadRequest(f"unknown field(s): {', '.join(sorted(map(str, unknown)))}")
    return req


def text(req: dict[str, Any], key: str, limit: int = 500, default: str = "") -> str:
    value = req.get(key, "")
    if not isinstance(value, str) or len(value) > limit:
        raise BadRequest(f"{key} must be text of at most {limit} characters")
    return value or default


class RequestService:
    """A queryable answering with ``handle(raw)`` (JSON-ready) on a worker pool."""

    name = "requests"

    def __init__(self, router: Router, key: str, workers: int = 2) -> None:
        self.router = router
        self.key = key
        self.workers = workers
        self._queryable: Any = None
        self._pool: ThreadPoolExecutor | None = None

    def handle(self, raw: bytes) -> dict[str, Any]:
        raise NotImplementedError

    def start(self) -> None:
        self._pool = ThreadPoolExecutor(self.workers, thread_name_prefix=self.name)
        self._queryable = self.router.session.declare_queryable(self.key, self._on_query)

    def stop(self) -> None:
        if self._queryable is not None:
            self._queryable.undeclare()
            self._queryable = None
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool = None

    def failure(self) -> str | None:
        return None

    def _on_query(self, query: Any) -> None:
        payload = query.payload
        raw = payload.to_bytes() if payload is not None else b""

        def answer() -> None:
            try:
                reply = self.handle(raw)
                query.reply(self.key, json.dumps(to_jsonable(reply)).encode())
            except Exception:  # one request must never take the service down
                log.exception("answering a request on %s failed", self.key)

        pool = self._pool
        if pool is not None:
            with contextlib.suppress(RuntimeError):  # the pool is shutting down: the hub stops
                pool.submit(answer)
