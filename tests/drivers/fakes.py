"""Strict fake transports for driver unit tests: they answer from datasheet tables and record
how the driver used the bus, so a test can also check mode, speed and the bytes sent."""

from __future__ import annotations

from collections import deque
from pathlib import Path
from typing import Any

DATA = Path(__file__).resolve().parent.parent / "data" / "drivers"


class FakeSpiDev:
    """Like spidev.SpiDev: `xfer2` answers from a queue of responses (or raises a queued
    error); everything sent is recorded."""

    def __init__(self, responses: list[Any] | None = None, open_error: OSError | None = None):
        self.responses: deque[Any] = deque(responses or [])
        self.open_error = open_error
        self.sent: list[list[int]] = []
        self.opened: tuple[int, int] | None = None
        self.closed = False
        self.mode = -1
        self.max_speed_hz = 0

    def __call__(self) -> FakeSpiDev:  # used as the driver's SpiDev factory
        return self

    def open(self, bus: int, device: int) -> None:
        if self.open_error is not None:
            raise self.open_error
        self.opened = (bus, device)
        self.closed = False

    def xfer2(self, data: list[int]) -> list[int]:
        self.sent.append(list(data))
        response = self.responses.popleft() if self.responses else [0xFF] * len(data)
        if isinstance(response, BaseException):
            raise response
        assert len(response) == len(data), "a SPI transfer returns as many bytes as it sends"
        return list(response)

    def close(self) -> None:
        self.closed = True
