"""The shape every part of the hub has: a service that starts and stops, composed in a stack.

A `ServiceStack` starts its services in order and stops them in reverse. If one fails to start
(or a Ctrl-C lands part-way), the ones already started are stopped again, in reverse, and the
error goes on up. `failures()` names any service whose worker died while the hub runs: the hub
reports it loudly and exits non-zero instead of running on looking healthy.
"""

from __future__ import annotations

import logging
from typing import Protocol

log = logging.getLogger("fleetdaq.hub")


class Service(Protocol):
    name: str

    def start(self) -> None:
        """Start working (threads, subscriptions). Raises if it cannot."""
        ...

    def stop(self) -> None:
        """Stop and release everything. Idempotent; safe after a failed or partial start."""
        ...

    def failure(self) -> str | None:
        """Why this service no longer works (a worker thread died), None while it does."""
        ...


class ServiceStack:
    def __init__(self, services: list[Service]) -> None:
        self.services = services
        self._started: list[Service] = []

    def start(self) -> None:
        try:
            for service in self.services:
                log.debug("starting %s", service.name)
                service.start()
                self._started.append(service)
        except BaseException:
            self.stop()
            raise

    def stop(self) -> None:
        """Stop what was started, newest first; one service failing to stop does not keep the
        others running."""
        while self._started:
            service = self._started.pop()
            try:
                service.stop()
            except Exception:
                log.exception("stopping %s failed", service.name)

    def failures(self) -> list[tuple[str, str]]:
        out = []
        for service in self._started:
            reason = service.failure()
            if reason is not None:
                out.append((service.name, reason))
        return out
