"""Devices that several drivers of one agent reach together.

A LabJack T8 can stream on one driver while its DAC and DIO lines are outputs of others; the
eight pins of one PCF8574 are eight outputs sharing one port register; a simulated weld cell is
seen by its robot's stream, by the thermocouple on its substrate and by its `resume` input. The
agent makes one `SharedDevices` and hands it to every driver it creates, so drivers that name
the same device get the same object. Nothing is global: two agents in one process (tests) never
share a device by accident.
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Hashable
from typing import TypeVar

T = TypeVar("T")


class SharedDevices:
    """Objects keyed by what they are (``("t8", "USB", "470012345")``), created on first use."""

    def __init__(self) -> None:
        self._items: dict[Hashable, object] = {}
        self._lock = threading.Lock()

    def get(self, key: Hashable, factory: Callable[[], T], kind: type[T]) -> T:
        """The object under `key`, made with `factory()` the first time.

        Raises TypeError when an object of another type is already there (two drivers that
        disagree on what a device is).
        """
        with self._lock:
            item = self._items.get(key)
            if item is None:
                item = self._items[key] = factory()
        if not isinstance(item, kind):
            raise TypeError(f"{key!r} is a {type(item).__name__}, not a {kind.__name__}")
        return item

    def find(self, key: Hashable, kind: type[T]) -> T | None:
        """The object under `key` if there is one (never creates it)."""
        with self._lock:
            item = self._items.get(key)
        return item if isinstance(item, kind) else None
