"""What the hub's services use of zenoh-python's objects, for tests that hand them samples and
replies without a router: a payload (`to_bytes`), a sample (`key_expr`, `payload`, `kind`) and
a query's reply (`ok` a sample or None, `err` the error). The services under test are the real
ones; only what Zenoh would deliver is made here."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any


@dataclass
class Payload:
    data: bytes

    def to_bytes(self) -> bytes:
        return self.data


@dataclass
class Sample:
    payload: Payload
    key_expr: str = ""
    kind: Any = None
    """zenoh.SampleKind.PUT or DELETE, for liveliness samples."""


@dataclass
class Reply:
    ok: Sample | None
    err: Sample | None = None
