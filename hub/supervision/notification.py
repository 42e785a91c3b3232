"""What the supervisor hands the notifier: one alarm transition, with what a mail needs.

The supervisor calls `Notifier.submit` on its own thread and never waits for it: a notifier
queues what it gets (on disk) and sends on its own threads.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

from fleetdaq.contract.messages import AlarmState


@dataclass(frozen=True, slots=True)
class Notification:
    state: AlarmState
    """The alarm after the transition (name, severity, state, transition, value, who, ...)."""
    description: str
    """The alarm's description from the site file ("" when none)."""


class Notifier(Protocol):
    def submit(self, n: Notification) -> None:
        """Take one transition. Never blocks, never raises."""
        ...
